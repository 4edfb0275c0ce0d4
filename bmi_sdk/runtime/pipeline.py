"""Raw frame → all-in-focus RGB + range map, tile by tile, with bounded memory.

Per tile (see ``tiling``): gather the raw window with a 2-px demosaic margin
(mirror reflection past the frame edges keeps the Bayer phase), preprocess it
with the one contract path (``model_io.raw_to_rgb``: demosaic, black level,
normalisation; the simulated sensor applies no white balance, so neither does
this), append the field channels of the tile's *absolute* sensor position
(``model_io.network_input`` with the frame's ROI offset), run the network,
and add the weighted outputs into a band of ``tile_px`` rows. Rows no later
tile can touch are normalised by the weight sum and moved into the output
arrays, so the working memory is one band plus one tile whatever the frame
size. The learned refinement's extra input channels (``extra``: the classical
decoder's per-pixel channels, ``decode.features.FeatureTiles``) are made per
tile for the same reflected pixels, never for the whole frame at once (a full
frame's would be 1.4 GB), and its depth 1σ is blended like the depth. Tiles whose kept pixels all lie outside the image circle are skipped;
outside the circle the depth is NaN and the AiF image 0. The next tiles' inputs are made on a second thread while
the network runs the current one (``_TILES_AHEAD`` of them): both cores stay busy between network runs.
"""

from __future__ import annotations

import itertools
import os
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from ..geometry import SensorGeometry
from ..model_io import INPUT_CHANNELS, network_input, raw_to_rgb, reflect_indices, window_cfa
from .model import Model
from .tiling import TilePlan

_DEMOSAIC_MARGIN_PX = 2  # bilinear demosaic reads one neighbour; 2 keeps the window's phase
_TILES_AHEAD = 2  # tile inputs made ahead of the network: ~20 MB each for the learned refinement's 19 channels


@dataclass
class InferenceResult:
    aif: np.ndarray                  # H × W × 3 float32, linear RGB (0 outside the image circle)
    depth_m: np.ndarray              # H × W float32, range along each pixel's chief ray, NaN where invalid
    valid: np.ndarray                # H × W bool, inside the image circle
    plan: TilePlan
    tiles_run: int
    tiles_skipped: int
    timings_s: dict = field(default_factory=dict)
    depth_sigma_m: np.ndarray | None = None  # H × W float32 1σ of depth_m (learned refinement), NaN where invalid

    def summary(self) -> dict:
        return {"tiles_run": self.tiles_run, "tiles_skipped": self.tiles_skipped, "tiling": self.plan.to_dict(),
                "valid_fraction": float(self.valid.mean()), "timings_s": dict(self.timings_s)}


def frame_lens_name(frame) -> str | None:
    """The lens a frame was taken through (its metadata's ``lens.name``), or None when it does not say."""
    return (getattr(frame, "lens", None) or {}).get("name")


def check_decodable(frame, lens: str, lens_owner: str, reader: str) -> None:
    """Refuse a frame a decoder cannot read, naming why: foreign camera, incomplete frame, another lens than
    ``lens`` (what ``lens_owner`` expects), an odd ROI offset, another CFA than RGGB. ``reader`` names the
    decoder in the messages."""
    if not getattr(frame, "is_bmi", True):
        reason = (frame.source or {}).get("foreign_raw_reason", "not a BMI frame")
        raise ValueError(f"this raw frame is not from a BMI camera ({reason}); {reader} only decodes BMI captures")
    frame.check()
    frame_lens = frame_lens_name(frame)
    if frame_lens is not None and frame_lens != lens:
        raise ValueError(f"frame was taken through lens {frame_lens!r}; {lens_owner} {lens!r}")
    if frame.roi.x_px % 2 or frame.roi.y_px % 2:
        raise ValueError(f"ROI offset ({frame.roi.x_px}, {frame.roi.y_px}) is odd: not whole RGGB cells")
    if frame.cfa != "RGGB":
        raise ValueError(f"{reader} reads RGGB sensors, the frame says {frame.cfa!r}")


def check_frame(frame, model: Model) -> None:
    """Refuse a frame the model cannot decode, naming why (``check_decodable``)."""
    check_decodable(frame, model.manifest["lens"], f"model {model.path.name} was trained for", "the network")


def infer_frame(model: Model, frame, *, overlap_px: int | None = None, progress: bool = False) -> InferenceResult:
    """Decode a ``devices.RawFrame`` (camera capture or ``load_raw``), or the DNG a path names, after
    ``check_frame``."""
    if isinstance(frame, (str, os.PathLike)):
        from devices import load_raw

        frame = load_raw(frame)
    elif not all(hasattr(frame, name) for name in ("data", "roi", "geometry", "cfa")):
        raise TypeError(f"infer_frame takes a devices.RawFrame (camera.capture() or devices.load_raw(PATH)) or a "
                        f"DNG path, got {type(frame).__name__}")
    check_frame(frame, model)
    return infer_raw(model, frame.data, black_level_dn=frame.black_level_dn, white_level_dn=frame.white_level_dn,
                     cfa=frame.cfa, geometry=frame.geometry, row0=frame.roi.y_px, col0=frame.roi.x_px,
                     overlap_px=overlap_px, progress=progress)


def infer_raw(model: Model, raw: np.ndarray, *, black_level_dn: float, white_level_dn: float, cfa: str = "RGGB",
              geometry: SensorGeometry, row0: int = 0, col0: int = 0, overlap_px: int | None = None,
              progress: bool = False, extra=None) -> InferenceResult:
    """Decode an H × W Bayer window whose top-left pixel sits at (row0, col0) of the full sensor.

    ``extra``: a ``decode.features.FeatureTiles`` of this window, whose C channels are appended to every tile's
    input (a model with ``input_channels`` = 6 + C, the learned refinement); None for the end-to-end network.
    """
    if raw.ndim != 2:
        raise ValueError(f"a raw frame is H × W, got shape {raw.shape}")
    height, width = raw.shape
    if height % 2 or width % 2:
        raise ValueError(f"raw frame {height}×{width} is not whole RGGB cells (even sizes)")
    n_extra = 0 if extra is None else extra.count
    if model.input_channels != INPUT_CHANNELS + n_extra or (extra is not None and tuple(extra.shape) != raw.shape):
        raise ValueError(f"model {model.path.name} reads {model.input_channels} channels; the frame gives "
                         f"{INPUT_CHANNELS} + {n_extra}" + ("" if extra is None else f" of shape {extra.shape}"))
    with_sigma = len(model.output_names) == 3
    plan = TilePlan.for_model(height, width, model.tile_px, model.receptive_field_px, step_px=model.size_multiple,
                              overlap_px=overlap_px)
    tile = plan.tile_px
    timings = dict.fromkeys(("demosaic_s", "field_s", "network_s", "blend_s", "finalise_s"), 0.0)
    aif = np.zeros((height, width, 3), np.float32)
    depth = np.full((height, width), np.nan, np.float32)
    depth_sigma = np.full((height, width), np.nan, np.float32) if with_sigma else None
    valid = np.zeros((height, width), bool)
    band = np.zeros((6, tile, width), np.float32)  # Σ w·rgb, Σ w·depth, Σ w, Σ w·σ over the band's rows: planes,
    #                                                 so that every sum and quotient runs over contiguous rows
    band_top = 0                                    # frame row of band[:, 0]

    def finalise(stop_row: int) -> None:
        """Move frame rows [band_top, stop_row) from the band into the outputs."""
        n = stop_row - band_top
        if n <= 0:
            return
        t0 = time.perf_counter()
        acc = band[:, :n]
        wsum = acc[4]
        ok = geometry.valid_mask(row0 + band_top, col0, n, width) & (wsum > 0)
        safe = np.where(ok, wsum, 1.0)
        for ch in range(3):
            aif[band_top:stop_row, :, ch] = np.where(ok, acc[ch] / safe, 0.0)
        depth[band_top:stop_row] = np.where(ok, acc[3] / safe, np.nan)
        if depth_sigma is not None:
            depth_sigma[band_top:stop_row] = np.where(ok, acc[5] / safe, np.nan)
        valid[band_top:stop_row] = ok
        band[:, :tile - n] = band[:, n:].copy()
        band[:, tile - n:] = 0
        timings["finalise_s"] += time.perf_counter() - t0

    m = _DEMOSAIC_MARGIN_PX

    def prepare(r: int, c: int, weight: np.ndarray) -> tuple:
        """One tile's kept part and its network input (None where it keeps no pixel of the image circle), with the
        seconds its demosaic and its field and extra channels took."""
        fr0, fr1, fc0, fc1 = max(r, 0), min(r + tile, height), max(c, 0), min(c + tile, width)
        w = weight[fr0 - r:fr1 - r, fc0 - c:fc1 - c]
        kept = geometry.valid_mask(row0 + fr0, col0 + fc0, fr1 - fr0, fc1 - fc0) & (w > 0)
        if not kept.any():
            return r, c, w, None, 0.0, 0.0
        t0 = time.perf_counter()
        window = raw[np.ix_(reflect_indices(r - m, tile + 2 * m, height), reflect_indices(c - m, tile + 2 * m, width))]
        rgb = raw_to_rgb(window, black_level_dn, white_level_dn, window_cfa(cfa, r - m, c - m))[m:-m, m:-m]
        t1 = time.perf_counter()
        x = network_input(rgb, geometry, row0 + r, col0 + c)
        if extra is not None:
            rows, cols = reflect_indices(r, tile, height), reflect_indices(c, tile, width)
            x = np.concatenate([x, extra.gather(rows, cols)[None]], axis=1)
        return r, c, w, np.ascontiguousarray(x, np.float32), t1 - t0, time.perf_counter() - t1

    run = skipped = 0
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=plan.n_tiles, unit="tile", desc="infer")
    # the next tiles' inputs are made on a second thread while the network runs this one (numpy and onnxruntime
    # release the GIL): their demosaic and channels no longer leave a core idle between network runs
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="tile-inputs") as pool:
        tiles = plan.tiles()
        ahead = deque(pool.submit(prepare, *t) for t in itertools.islice(tiles, _TILES_AHEAD))
        try:
            while ahead:
                r, c, w, x, demosaic_s, field_s = ahead.popleft().result()
                ahead.extend(pool.submit(prepare, *t) for t in itertools.islice(tiles, 1))
                top = max(r, 0)
                if top > band_top:
                    finalise(top)
                    band_top = top
                if bar is not None:
                    bar.update(1)
                if x is None:
                    skipped += 1
                    continue
                timings["demosaic_s"] += demosaic_s
                timings["field_s"] += field_s
                t0 = time.perf_counter()
                out_rgb, out_depth, *out_sigma = model.run(x)
                t1 = time.perf_counter()
                fr0, fc0 = top, max(c, 0)
                fr1, fc1 = fr0 + w.shape[0], fc0 + w.shape[1]
                sl = (slice(fr0 - r, fr1 - r), slice(fc0 - c, fc1 - c))
                dst = band[:, fr0 - band_top:fr1 - band_top, fc0:fc1]
                dst[:3] += out_rgb[0][(slice(None), *sl)] * w
                dst[3] += out_depth[0, 0][sl] * w
                dst[4] += w
                if out_sigma:
                    dst[5] += out_sigma[0][0, 0][sl] * w
                timings["network_s"] += t1 - t0
                timings["blend_s"] += time.perf_counter() - t1
                run += 1
            finalise(height)
        finally:
            for future in ahead:  # an error stops the loop: drop the tiles made ahead of it
                future.cancel()
            if bar is not None:
                bar.close()
    return InferenceResult(aif, depth, valid, plan, run, skipped, timings, depth_sigma)
