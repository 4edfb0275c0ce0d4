"""Point-source targets, the capture plan, and captures through the (simulated) camera.

A *target* is a set of point sources at known directions (θ, φ) and ranges
from the lens centre (a rig of pinhole lamps, or one lamp on a calibrated
rotation stage); a *capture plan* says what to record for each source: a
readout window (ROI) around where the design puts its spot, several exposures
(the longest one that does not saturate is used), repeats (they give the
per-pixel noise by photon transfer) and dark frames with the lamp off at each
exposure. The same plan is followed with the real device (``CapturePlan.steps``).

In the simulated world, ``PointSourceScene`` is the irradiance source: each
point's exact perturbed PSF (``bmi_sdk.optics.perturb.spot_kernels``) placed
where the perturbed lens puts the spot, sub-pixel exact. A point source is a
delta function, so this *is* the exact rendering; the frames then go through
the device's own readout (relative illumination, shot and read noise, RGGB,
12-bit ADC) and the camera API, ROI by ROI.

Captures are a folder: one DNG (+ sidecar) per frame and ``captures.json``
(target, plan, device, frame list with pixel hashes; ``injected`` for
simulations).
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from bmi_sdk.geometry import BMI_SENSOR
from bmi_sdk.io_atomic import write_json
from bmi_sdk.json_files import read_json_object
from bmi_sdk.lenses import LENS_KERNEL_PX
from bmi_sdk.optics import get_lens
from bmi_sdk.optics.perturb import Perturbation, chief_landing_px, spot_kernels

CAPTURES_SCHEMA = "bmi-calibration-captures/1"
CHANNEL_NM = (656.3, 587.6, 486.1)  # the tensor's representative lines (R, G, B)


class CalibrationError(ValueError):
    """Captures or settings a calibration cannot use (the message says why and what to do)."""


@dataclass(frozen=True)
class PointSource:
    field_deg: float
    azimuth_deg: float
    depth_m: float
    peak_fill: float = 0.6  # simulation: brightest pixel / full well at the plan's longest exposure
    held_out: bool = False  # captured for the check, not used by the fit

    def __post_init__(self):
        if not 0 <= self.field_deg <= 60:
            raise CalibrationError(f"point source field_deg must lie in [0, 60], got {self.field_deg}")
        if not 0.1 <= self.depth_m <= 1e4:
            raise CalibrationError(f"point source depth_m must lie in [0.1, 1e4] m, got {self.depth_m}")
        if not self.peak_fill > 0:
            raise CalibrationError(f"peak_fill must be > 0, got {self.peak_fill}")


@dataclass(frozen=True)
class Target:
    sources: tuple
    rgb: tuple = (0.0, 1.0, 0.0)  # lamp spectrum on the R, G, B channels (default: a green 587.6 nm line)
    name: str = "points"

    def __post_init__(self):
        if len(self.rgb) != 3 or min(self.rgb) < 0 or max(self.rgb) <= 0:
            raise CalibrationError(f"target rgb must be three weights >= 0, not all 0, got {self.rgb}")

    @property
    def channels(self) -> list[int]:
        return [c for c in range(3) if self.rgb[c] > 0]

    def to_dict(self) -> dict:
        return {"name": self.name, "rgb": list(self.rgb), "sources": [asdict(s) for s in self.sources]}

    @classmethod
    def from_dict(cls, d: dict) -> "Target":
        return cls(tuple(PointSource(**s) for s in d["sources"]), tuple(d["rgb"]), d.get("name", "points"))


# Candidate directions in the order a growing target adds them: the axis, the four corners at 55°
# (only the diagonals reach that far on a 4:3 sensor), the long and short axes near their edges, then
# inner rings. Azimuths on the pixel axes use the separable PSF transform (faster).
_DIAGONAL = math.degrees(math.atan2(2250, 3000))
_CANDIDATES = [(0.0, 0.0)] + [(55.0, a) for a in (_DIAGONAL, 180 - _DIAGONAL, 180 + _DIAGONAL, 360 - _DIAGONAL)] + \
    [(44.0, 0.0), (32.0, 90.0), (44.0, 180.0), (32.0, 270.0)] + [(20.0, a) for a in (0.0, 90.0, 180.0, 270.0)] + \
    [(38.0, a) for a in (45.0, 135.0, 225.0, 315.0)] + [(50.0, a) for a in (20.0, 160.0, 200.0, 340.0)]
_HELD_OUT = [(30.0, 180.0), (26.0, 270.0), (48.0, 150.0), (48.0, 330.0), (12.0, 90.0), (40.0, 0.0)]
_DEPTHS_M = (0.7, 10.0, 1.5, 4.0, 2.5, 1.0)


def standard_target(n_points: int = 13, n_held_out: int = 4, rgb=(0.0, 1.0, 0.0)) -> Target:
    """The standard point-source target: ``n_points`` fit sources + ``n_held_out`` check sources.

    Ranges cycle through 0.7–10 m so every ring sees several depths.
    """
    if not 1 <= n_points <= len(_CANDIDATES):
        raise CalibrationError(f"n_points must lie in [1, {len(_CANDIDATES)}], got {n_points}")
    if not 0 <= n_held_out <= len(_HELD_OUT):
        raise CalibrationError(f"n_held_out must lie in [0, {len(_HELD_OUT)}], got {n_held_out}")
    sources = [PointSource(t, a, _DEPTHS_M[i % len(_DEPTHS_M)]) for i, (t, a) in enumerate(_CANDIDATES[:n_points])]
    sources += [PointSource(t, a, _DEPTHS_M[(i + 3) % len(_DEPTHS_M)], held_out=True)
                for i, (t, a) in enumerate(_HELD_OUT[:n_held_out])]
    return Target(tuple(sources), tuple(rgb), f"standard-{n_points}+{n_held_out}")


@dataclass(frozen=True)
class CapturePlan:
    exposures_us: tuple = (2500, 10000)
    n_repeats: int = 4
    n_dark: int = 4
    kernel_px: int = LENS_KERNEL_PX["bmi_monocentric"]  # PSF patch side: the design lens's kernel size
    roi_margin_px: int = 16  # room around the design position for the spot to move
    analog_gain: float = 1.0
    one_lamp_at_a_time: bool = True  # False: every lamp lit in every frame (spots may overlap)

    def __post_init__(self):
        if not self.exposures_us or min(self.exposures_us) <= 0:
            raise CalibrationError(f"exposures_us must be positive, got {self.exposures_us}")
        if self.n_repeats < 2 or self.n_dark < 2:
            raise CalibrationError("the plan needs ≥ 2 repeats and ≥ 2 dark frames (noise comes from their spread)")
        if self.kernel_px % 2 == 0 or self.kernel_px < 9:
            raise CalibrationError(f"kernel_px must be odd and ≥ 9, got {self.kernel_px}")

    @property
    def roi_px(self) -> int:
        return 2 * ((self.kernel_px + 2 * self.roi_margin_px + 1) // 2)

    def to_dict(self) -> dict:
        return dict(asdict(self), exposures_us=list(self.exposures_us))

    @classmethod
    def from_dict(cls, d: dict) -> "CapturePlan":
        return cls(**dict(d, exposures_us=tuple(d["exposures_us"])))

    def steps(self, target: Target) -> list[str]:
        """The plan as instructions for a person at the real camera."""
        lamps = "one lamp on at a time" if self.one_lamp_at_a_time else "all lamps on together"
        out = [f"Mount the camera on the rig; lamps at the {len(target.sources)} directions of the target "
               f"(θ, φ, range from the lens centre), {lamps}."]
        for i, s in enumerate(target.sources):
            out.append(f"source {i}: θ={s.field_deg}°, φ={s.azimuth_deg:.2f}°, {s.depth_m} m — ROI "
                       f"{self.roi_px}×{self.roi_px} px around its design position; for each exposure "
                       f"{list(self.exposures_us)} µs (gain {self.analog_gain}): {self.n_repeats} frames lamp on, "
                       f"{self.n_dark} frames lamp off")
        return out


def design_landing_px(target: Target, geometry=BMI_SENSOR, lens_name: str = "bmi_monocentric") -> np.ndarray:
    """(n, 2) (row, col) where the design lens puts each source's chief ray (green line)."""
    s = target.sources
    return chief_landing_px(get_lens(lens_name), Perturbation(), [p.field_deg for p in s], [p.azimuth_deg for p in s],
                            [p.depth_m for p in s], CHANNEL_NM[1] * 1e-3, geometry.centre_px, geometry.pitch_um)


def plan_rois(target: Target, plan: CapturePlan, geometry=BMI_SENSOR, lens_name: str = "bmi_monocentric"):
    """(x, y, w, h) per source: the plan's ROI around the design position, clipped to the sensor (even)."""
    land = design_landing_px(target, geometry, lens_name)
    rois = []
    size = plan.roi_px
    for row, col in land:
        x0 = 2 * int(math.floor((col - size / 2) / 2))
        y0 = 2 * int(math.floor((row - size / 2) / 2))
        x1, y1 = min(x0 + size, geometry.width_px), min(y0 + size, geometry.height_px)
        x0, y0 = max(x0, 0), max(y0, 0)
        if x1 - x0 < 2 or y1 - y0 < 2:
            raise CalibrationError(f"a source at (row {row:.0f}, col {col:.0f}) lands outside the sensor")
        rois.append((x0, y0, x1 - x0, y1 - y0))
    return rois


class PointSourceScene:
    """Irradiance of lit point sources through a perturbed lens (see module doc)."""

    def __init__(self, target: Target, perturbation: Perturbation, plan: CapturePlan, geometry=BMI_SENSOR,
                 lens_name: str = "bmi_monocentric"):
        self.name = "point-sources"
        self.target = target
        self.perturbation = perturbation
        self.lens_name = lens_name
        lens = get_lens(lens_name)
        s = target.sources
        k = plan.kernel_px
        theta, phi, depth = ([getattr(p, a) for p in s] for a in ("field_deg", "azimuth_deg", "depth_m"))
        self.patches = []  # (row0, col0, K×K×3 irradiance)
        self.landing_px: np.ndarray | None = None  # the first channel's landing points (x, y) px
        per_channel = {}
        for c in target.channels:
            land = chief_landing_px(lens, perturbation, theta, phi, depth, CHANNEL_NM[c] * 1e-3,
                                    geometry.centre_px, geometry.pitch_um)
            land = land + perturbation.psf_shift_rc
            if self.landing_px is None:
                self.landing_px = land
            centre = np.rint(self.landing_px)
            per_channel[c] = (centre, spot_kernels(lens, perturbation, theta, phi, depth, CHANNEL_NM[c] * 1e-3,
                                                   centre, k, geometry.centre_px, geometry.pitch_um).kernels)
        for i, src in enumerate(s):
            stack = np.zeros((k, k, 3))
            for c, (centre, kernels) in per_channel.items():
                stack[..., c] = target.rgb[c] * kernels[i]
            scale = src.peak_fill * (10000.0 / max(plan.exposures_us)) / stack.max()
            centre = per_channel[target.channels[0]][0][i]
            self.patches.append((int(centre[0]) - k // 2, int(centre[1]) - k // 2, (scale * stack).astype(np.float32)))
        self.lit = set(range(len(s)))

    def irradiance(self, row0: int, col0: int, height: int, width: int) -> np.ndarray:
        out = np.zeros((height, width, 3), np.float32)
        for i in self.lit:
            r0, c0, patch = self.patches[i]
            k = patch.shape[0]
            a0, a1 = max(r0, row0), min(r0 + k, row0 + height)
            b0, b1 = max(c0, col0), min(c0 + k, col0 + width)
            if a1 > a0 and b1 > b0:
                out[a0 - row0:a1 - row0, b0 - col0:b1 - col0] += patch[a0 - r0:a1 - r0, b0 - c0:b1 - c0]
        return out

    def metadata(self) -> dict:
        return {"source": self.name, "target": self.target.name, "lit": sorted(self.lit), "lens": self.lens_name}


@dataclass
class Captures:
    """Frames of a target following a plan: ``frames[i]`` lists (kind 'light'|'dark', exposure_us, RawFrame)."""

    target: Target
    plan: CapturePlan
    frames: list
    device: dict
    injected: Perturbation | None = None
    folder: Path | None = None
    extra: dict = field(default_factory=dict)

    def sha256(self) -> str:
        """Hash of what the calibration saw: target, plan and every frame's pixels, in order."""
        from devices.dng import pixel_sha256

        h = hashlib.sha256(json.dumps({"target": self.target.to_dict(), "plan": self.plan.to_dict()},
                                      sort_keys=True).encode())
        for spot in self.frames:
            for kind, exposure, frame in spot:
                h.update(f"{kind}:{exposure}:{pixel_sha256(frame.data)}".encode())
        return h.hexdigest()

    def save(self, folder, overwrite: bool = False) -> Path:
        """Write every frame as DNG + sidecar and ``captures.json`` (written last, atomically); a frame of the
        same name already in ``folder`` is refused (``FileExistsError``) unless ``overwrite``."""
        from devices.dng import pixel_sha256

        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        listing = []
        for i, spot in enumerate(self.frames):
            for j, (kind, exposure, frame) in enumerate(spot):
                name = f"src{i:02d}_{kind}_{exposure}us_{j:02d}.dng"
                frame.save_dng(folder / name, overwrite=overwrite)
                listing.append({"source": i, "kind": kind, "exposure_us": exposure, "file": name,
                                "pixel_sha256": pixel_sha256(frame.data)})
        write_json(folder / "captures.json", {
            "schema": CAPTURES_SCHEMA, "target": self.target.to_dict(), "plan": self.plan.to_dict(),
            "device": self.device, "frames": listing, "sha256": self.sha256(),
            "injected": None if self.injected is None else self.injected.to_dict()})
        self.folder = folder
        return folder


def load_captures(folder) -> Captures:
    """Read a captures folder, checking its schema and every frame's pixel hash."""
    from devices import load_raw
    from devices.dng import pixel_sha256

    folder = Path(folder)
    path = folder / "captures.json"
    if not path.exists():
        raise CalibrationError(f"{folder}: no captures.json (write captures with `bmi calibrate --simulate ... "
                               "--save-captures DIR` or follow CapturePlan.steps with the real camera)")
    meta = read_json_object(path, CalibrationError)
    if meta.get("schema") != CAPTURES_SCHEMA:
        raise CalibrationError(f"{path}: schema {meta.get('schema')!r}, expected {CAPTURES_SCHEMA!r}")
    for key, kind in (("target", dict), ("plan", dict), ("device", dict), ("frames", list)):
        if not isinstance(meta.get(key), kind):
            raise CalibrationError(f"{path}: {key!r} must be a JSON {'object' if kind is dict else 'array'}")
    target, plan = Target.from_dict(meta["target"]), CapturePlan.from_dict(meta["plan"])
    frames: list[list[tuple]] = [[] for _ in target.sources]  # per source: (kind, exposure_us, RawFrame)
    for item in meta["frames"]:
        if not isinstance(item, dict) or not {"file", "pixel_sha256", "source", "kind", "exposure_us"} <= set(item):
            raise CalibrationError(f"{path}: each entry of 'frames' is an object with file, pixel_sha256, "
                                   f"source, kind, exposure_us; got {item!r}"[:300])
        frame = load_raw(folder / item["file"])
        if pixel_sha256(frame.data) != item["pixel_sha256"]:
            raise CalibrationError(f"{folder / item['file']}: pixels do not match captures.json (file changed)")
        frames[item["source"]].append((item["kind"], int(item["exposure_us"]), frame))
    device = device_from_frames(path, meta["device"], [f for spot in frames for _, _, f in spot])
    injected = None if meta.get("injected") is None else Perturbation.from_dict(meta["injected"])
    return Captures(target, plan, frames, device, injected, folder)


def device_from_frames(listing_path, listed: dict, frames) -> dict:
    """The camera the captures come from, as the frames themselves record it (their DNG sidecars).

    ``captures.json`` is a listing a person may have copied or edited; the
    frames carry the serial the camera stamped. Frames from more than one
    camera, or a listing whose serial or model contradicts the frames, are
    refused: a calibration is only valid for the camera that took it.
    """
    serials = sorted({str(f.device.get("serial")) for f in frames})
    if len(serials) > 1:
        raise CalibrationError(f"{listing_path}: the frames come from several cameras ({', '.join(serials)}); "
                               "a calibration is for one camera")
    device = dict(listed)
    if frames:
        for key in ("model", "serial", "firmware_version"):
            from_frame = frames[0].device.get(key)
            if key in ("model", "serial") and listed.get(key) is not None and from_frame is not None \
                    and listed[key] != from_frame:
                raise CalibrationError(f"{listing_path} names {key} {listed[key]!r}, but the frames were taken "
                                       f"by {from_frame!r}")
            if from_frame is not None:
                device[key] = from_frame
    return device


def simulate_captures(target: Target, plan: CapturePlan, perturbation: Perturbation, seed: int,
                      serial: int = 1, lens_name: str = "bmi_monocentric", geometry=BMI_SENSOR) -> Captures:
    """Capture ``target`` with ``plan`` through a simulated camera whose lens has ``perturbation``.

    Goes through the whole device stack (``FirmwareDevice`` readout, in-process
    link, ``devices`` camera API); noise is seeded by ``seed``.
    """
    from devices import open_camera
    from devices.frame import Roi
    from firmware_sim import DarkFrame, FirmwareDevice

    scene = PointSourceScene(target, perturbation, plan, geometry, lens_name)
    rois = plan_rois(target, plan, geometry, lens_name)
    device = FirmwareDevice(source=scene, seed=seed, serial=serial, lens=lens_name)
    frames = []
    with open_camera("sim://calibration", device=device) as cam:
        cam.settings.analog_gain = plan.analog_gain
        for i, roi in enumerate(rois):
            cam.settings.roi = Roi(*roi)
            spot = []
            scene.lit = {i} if plan.one_lamp_at_a_time else set(range(len(target.sources)))
            for exposure in plan.exposures_us:
                cam.settings.exposure_us = int(exposure)
                device.load_source(scene)
                spot += [("light", int(exposure), cam.capture()) for _ in range(plan.n_repeats)]
                device.load_source(DarkFrame())
                spot += [("dark", int(exposure), cam.capture()) for _ in range(plan.n_dark)]
            frames.append(spot)
        info = cam.info
    dev = {k: info.get(k) for k in ("model", "serial", "firmware_version", "lens")}
    landing = None if scene.landing_px is None else scene.landing_px.tolist()
    return Captures(target, plan, frames, dev, perturbation, extra={"seed": seed, "true_landing_px": landing})
