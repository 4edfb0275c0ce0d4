"""Bounded soak over TCP loopback with seeded faults: every frame is delivered intact or reported, and the
host's counters equal the device's fault ledger; disconnects are recovered by reconnect(); a full-resolution
capture works in-process."""

import threading
import time

import numpy as np

from devices import DeviceRemovedError, FrameStatus, Roi, open_camera
from firmware_sim import FaultPlan, FirmwareDevice, FirmwareServer, FlatField
from firmware_sim.faults import Fault

ROI = Roi(1000, 2000, 32, 16)
FRAMES = 400


def test_soak_with_faults_counters_match_ledger():
    plan = FaultPlan(seed=4, drop=0.06, corrupt=0.06, incomplete=0.06, stall=0.02, disconnect=0.02, stall_s=0.02)
    dev = FirmwareDevice(faults=plan)
    rows = np.arange(ROI.y_px, ROI.y_px + ROI.height_px)[:, None]
    cols = np.arange(ROI.x_px, ROI.x_px + ROI.width_px)[None, :]
    seen = {}
    bad_pixels = []
    lock = threading.Lock()
    dropped_link = threading.Event()

    def on_frame(frame):
        with lock:
            seen[frame.frame_id] = frame.status
            if frame.status == FrameStatus.COMPLETE and not np.array_equal(
                    frame.data, (rows + cols + frame.frame_id) % 4096):
                bad_pixels.append(frame.frame_id)

    with FirmwareServer(dev) as server:
        with open_camera(server.uri, on_frame=on_frame, on_disconnect=lambda r: dropped_link.set(),
                         timeout_s=2) as cam:
            cam.settings.roi = ROI
            cam.settings.test_pattern = 2  # walking ramp: intact frames are checkable bit for bit
            cam.start("oldest_first", buffers=4)
            deadline = time.monotonic() + 20
            reconnects = 0
            while time.monotonic() < deadline:
                if dropped_link.wait(0.05):
                    dropped_link.clear()
                    cam.reconnect()
                    reconnects += 1
                with lock:
                    if seen and max(seen) >= FRAMES:
                        break
            try:
                cam.stop()
            except DeviceRemovedError:  # the last fault may have dropped the link
                pass
            stats = dict(cam.stats)
            last_header = cam._last_header_id  # the last frame id the link saw: frames that arrive while the host
            #                                    stops are counted (their gaps as lost) but never delivered
    last = max(seen)
    ledger = {k: [i for i in v if i <= last] for k, v in dev.injector.ledger.items()}
    assert last >= FRAMES, "soak did not finish in its time bound"
    assert not bad_pixels
    by_status = {s: sorted(i for i, st in seen.items() if st == s) for s in FrameStatus}
    assert by_status[FrameStatus.CORRUPT] == ledger[Fault.CORRUPT]
    assert by_status[FrameStatus.INCOMPLETE] == sorted(ledger[Fault.INCOMPLETE] + ledger[Fault.DISCONNECT])
    # the host counts a dropped frame when it sees the next header, which may come after the last delivered frame
    assert stats["lost"] == len([i for i in dev.injector.ledger[Fault.DROP] if i < last_header])
    assert not set(seen) & set(ledger[Fault.DROP])
    assert set(ledger[Fault.STALL]) <= set(by_status[FrameStatus.COMPLETE])
    # Every disconnect up to the last delivered frame is counted; one more may be counted when the device
    # drops the link on the frame after it (while the host stops): it is in the device's full ledger.
    assert len(ledger[Fault.DISCONNECT]) <= stats["disconnects"] <= len(dev.injector.ledger[Fault.DISCONNECT])
    assert reconnects in (stats["disconnects"], stats["disconnects"] - 1)  # the last one may end the soak
    assert len(seen) + len(ledger[Fault.DROP]) == last + 1  # every id accounted for
    assert min(len(v) for v in ledger.values()) > 0  # each kind of fault actually happened


def test_full_resolution_capture_in_process():
    with open_camera("sim://", device=FirmwareDevice(source=FlatField())) as cam:
        frame = cam.capture(timeout_s=30)
    assert frame.data.shape == (4500, 6000) and frame.roi == Roi(0, 0, 6000, 4500)
    centre = frame.data[2200:2300, 2950:3050].astype(float)
    assert abs(centre.mean() - (256 + 0.64 * 0.5 * 6000)) < 20  # black + g μ at the axis
