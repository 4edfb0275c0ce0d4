"""Writing an inference result: images, depth files, a coloured point cloud and the JSON report.

Every file is written atomically (``bmi_sdk.io_atomic``): an interrupted run
never leaves half a file under its final name.

* ``aif.npy``      H×W×3 float32 linear RGB (the space of ``bmi simulate``'s input)
* ``aif.png``      16-bit sRGB-encoded, for viewing; ``aif_preview.png`` 8-bit, at most ``preview_px`` wide
* ``depth.npy``    H×W float32 range in metres along each pixel's chief ray, NaN where invalid
* ``depth_z.npy``  H×W float32 planar z-depth in metres (along the optical axis, as RGB-D tools assume), NaN where invalid
* ``depth_mm.png`` 16-bit range in millimetres, 0 where invalid (saturates at 65.535 m)
* ``depth_preview.png`` colourised inverse range with a colour bar labelled in metres (the frame's
  1st–99th percentile, or a fixed ``depth_range_m`` so that frames can be compared)
* ``points.ply``   binary PLY, x y z (metres, camera frame x right, y down, z forward) + RGB (sRGB 8-bit),
  one point per ``ply_step_px``-th valid pixel: range × that pixel's chief-ray direction
* ``report.json``  the report dict given
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..color import linear_to_srgb
from ..geometry import SensorGeometry
from ..io_atomic import atomic_path, save_npy, write_json
from ..parallel import map_threads


def _imwrite(path: Path, image: np.ndarray) -> None:
    import cv2

    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), image):
            raise OSError(f"OpenCV could not write {path}")


def _downscale(image: np.ndarray, max_px: int) -> np.ndarray:
    import cv2

    h, w = image.shape[:2]
    scale = max_px / max(h, w)
    if scale >= 1:
        return image
    return cv2.resize(image, (max(1, round(w * scale)), max(1, round(h * scale))), interpolation=cv2.INTER_AREA)


def depth_preview(depth_m: np.ndarray, max_px: int = 1500, near_m: float | None = None,
                  far_m: float | None = None) -> np.ndarray:
    """BGR uint8 image: inverse range through the turbo colour map, invalid pixels black, a labelled colour bar."""
    import cv2

    d = _downscale(np.nan_to_num(depth_m, nan=0.0).astype(np.float32), max_px)
    ok = d > 0
    finite = d[ok]
    near = near_m if near_m is not None else (float(np.percentile(finite, 1)) if finite.size else 0.7)
    far = far_m if far_m is not None else (float(np.percentile(finite, 99)) if finite.size else 10.0)
    far = max(far, near * 1.01)
    inv = np.where(ok, 1.0 / np.maximum(d, 1e-6), 0.0)
    t = np.clip((inv - 1 / far) / (1 / near - 1 / far), 0, 1)
    img = cv2.applyColorMap((t * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    img[~ok] = 0
    h = img.shape[0]
    bar_w, label_w = max(12, h // 40), 90
    ramp = np.linspace(1, 0, h)[:, None]  # top: near
    bar = cv2.applyColorMap((np.repeat(ramp, bar_w, 1) * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    labels = np.full((h, label_w, 3), 255, np.uint8)
    for frac in np.linspace(0, 1, 6):
        inv_v = 1 / near - frac * (1 / near - 1 / far)
        y = int(np.clip(frac * (h - 1), 10, h - 4))
        cv2.putText(labels, f"{1 / inv_v:.2f} m", (4, y), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([img, np.full((h, 6, 3), 255, np.uint8), bar, labels], axis=1)


def check_depth_range(depth_range_m) -> tuple[float, float]:
    """(near_m, far_m) of a fixed depth-colour range, refused unless 0 < near < far, both finite."""
    try:
        near, far = (float(v) for v in depth_range_m)
    except (TypeError, ValueError):
        raise ValueError(f"depth range must be two numbers NEAR,FAR in metres, got {depth_range_m!r}") from None
    if not (np.isfinite(near) and np.isfinite(far) and 0 < near < far):
        raise ValueError(f"depth range needs 0 < NEAR < FAR (metres, finite), got {near}, {far}")
    return near, far


def range_to_z_map(depth_m: np.ndarray, geometry: SensorGeometry, row0: int = 0, col0: int = 0,
                   rows_per_block: int = 256) -> np.ndarray:
    """Planar z-depth (m, float32) of a range map: range × cos θ of each pixel's chief ray (``SensorGeometry.range_to_z``)
    at its absolute sensor position (``row0``, ``col0``: the frame's ROI offset); NaN where the range is invalid
    or the pixel lies outside the image circle. Computed per block of rows to bound memory on a full frame."""
    z = np.full(depth_m.shape, np.nan, np.float32)
    cols = col0 + np.arange(depth_m.shape[1])
    for b0 in range(0, depth_m.shape[0], rows_per_block):
        rows = row0 + np.arange(b0, min(b0 + rows_per_block, depth_m.shape[0]))
        theta_deg, _ = geometry.field_angles(rows[:, None], cols[None, :])
        d = depth_m[b0:b0 + len(rows)]
        ok = np.isfinite(d) & (d > 0)
        z[b0:b0 + len(rows)] = np.where(ok, geometry.range_to_z(d, theta_deg), np.nan)
    return z


def write_ply(path: str | os.PathLike, depth_m: np.ndarray, aif: np.ndarray, geometry: SensorGeometry,
              row0: int = 0, col0: int = 0, step_px: int = 1, rows_per_block: int = 256,
              depth_sigma_m: np.ndarray | None = None) -> int:
    """Stream a binary little-endian PLY of every ``step_px``-th valid pixel; return the point count.

    Point = range × unit chief-ray direction of the pixel's absolute sensor
    position (``row0``, ``col0``: the frame's ROI offset). Rays are computed per
    block of rows, so memory stays bounded for a full frame. With ``depth_sigma_m``
    each point also carries ``sigma`` (float, metres): the 1σ of its range.
    """
    if step_px < 1:
        raise ValueError(f"ply step must be ≥ 1 px, got {step_px}")
    sub_d = depth_m[::step_px, ::step_px]
    count = int(np.count_nonzero(np.isfinite(sub_d) & (sub_d > 0)))
    header = ("ply\nformat binary_little_endian 1.0\ncomment bmi-sdk point cloud: range along chief rays, metres\n"
              f"element vertex {count}\nproperty float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\n"
              + ("property float sigma\n" if depth_sigma_m is not None else "") + "end_header\n").encode()
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
    dtype = np.dtype(fields + ([("sigma", "<f4")] if depth_sigma_m is not None else []))
    cols = np.arange(0, depth_m.shape[1], step_px)
    written = 0
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(header)
        for b0 in range(0, depth_m.shape[0], step_px * rows_per_block):
            rows = np.arange(b0, min(b0 + step_px * rows_per_block, depth_m.shape[0]), step_px)
            d = depth_m[np.ix_(rows, cols)]
            ok = np.isfinite(d) & (d > 0)
            if not ok.any():
                continue
            rr, cc = np.nonzero(ok)
            dirs = geometry.ray_directions(row0 + rows[rr], col0 + cols[cc])
            xyz = dirs * d[rr, cc][:, None]
            rgb = (linear_to_srgb(aif[rows[rr], cols[cc]]) * 255 + 0.5).astype(np.uint8)
            block = np.empty(len(rr), dtype)
            block["x"], block["y"], block["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
            block["red"], block["green"], block["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
            if depth_sigma_m is not None:
                block["sigma"] = depth_sigma_m[rows[rr], cols[cc]]
            f.write(block.tobytes())
            written += len(rr)
    if written != count:
        raise RuntimeError(f"PLY point count changed while writing ({written} != {count})")
    return count


def confidence_image(depth_m: np.ndarray, depth_sigma_m: np.ndarray) -> np.ndarray:
    """uint8 confidence 255 / (1 + 10 σ/d): 255 certain, ~128 at 10 % relative 1σ, 0 where invalid."""
    rel = depth_sigma_m / np.where(np.isfinite(depth_m) & (depth_m > 0), depth_m, np.nan)
    conf = 255.0 / (1.0 + 10.0 * rel)
    return np.where(np.isfinite(conf), np.round(conf), 0).astype(np.uint8)


def srgb_images(aif: np.ndarray, rows_per_block: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """(16-bit, 8-bit) BGR sRGB encodings of a linear H × W × 3 image, made per block of rows: the sRGB curve's
    float temporaries of a whole 6000×4500 frame took 1.6 GB at once."""
    h, w = aif.shape[:2]
    bgr16 = np.empty((h, w, 3), np.uint16)
    bgr8 = np.empty((h, w, 3), np.uint8)
    for b0 in range(0, h, rows_per_block):
        srgb = linear_to_srgb(aif[b0:b0 + rows_per_block])[..., ::-1]
        bgr16[b0:b0 + rows_per_block] = srgb * 65535 + 0.5
        bgr8[b0:b0 + rows_per_block] = srgb * 255 + 0.5
    return bgr16, bgr8


OUTPUT_NAMES = ("aif.npy", "aif.png", "aif_preview.png", "depth.npy", "depth_z.npy", "depth_mm.png",
                "depth_preview.png", "points.ply")
"""The files ``write_outputs`` always writes."""
SIGMA_OUTPUT_NAMES = ("depth_sigma.npy", "confidence.png")
"""The files it adds when the decoder reports a depth 1σ (the classical decoder)."""


WRITE_THREADS = 2
"""Output files written at once: a full frame's writing is 7 CPU-s (PNG encoding, the sRGB curve, z-depth), and two
threads keep the sRGB temporaries of the AiF (~250 MB) beside one other file's."""


def write_outputs(out_dir: str | os.PathLike, aif: np.ndarray, depth_m: np.ndarray, geometry: SensorGeometry,
                  row0: int = 0, col0: int = 0, *, ply_step_px: int = 1, preview_px: int = 1500,
                  depth_sigma_m: np.ndarray | None = None, depth_range_m: tuple[float, float] | None = None,
                  overwrite: bool = False) -> dict:
    """Write the image, depth and point-cloud files into ``out_dir``; return {name: path} and the point count.

    ``depth_range_m`` (near, far): the fixed range of ``depth_preview.png``'s colours (default: the
    frame's 1st–99th percentile, which differs from frame to frame).

    With ``depth_sigma_m`` (the decoder's 1σ of the range, metres) also ``depth_sigma.npy``,
    ``confidence.png`` (``confidence_image``) and a per-point ``sigma`` in the PLY.

    The files are one set, as ``bmi infer`` writes them (``output_set.OutputSet``): a folder holding an earlier
    run's results is refused (``FileExistsError``) unless ``overwrite``, which replaces that set whole (an
    earlier file this call does not write, such as another decoder's ``depth_sigma.npy`` or its
    ``report.json``, is removed); the folder changes only once every file is written.
    """
    from .output_set import OutputSet

    if depth_range_m is not None:
        check_depth_range(depth_range_m)
    with OutputSet(out_dir, overwrite=overwrite) as output_set:
        written = write_files(output_set.folder, aif, depth_m, geometry, row0, col0, ply_step_px=ply_step_px,
                              preview_px=preview_px, depth_sigma_m=depth_sigma_m, depth_range_m=depth_range_m)
        output_set.commit()
    return {**written, "files": {name: str(Path(out_dir) / name) for name in written["files"]}}


def write_files(out_dir: str | os.PathLike, aif: np.ndarray, depth_m: np.ndarray, geometry: SensorGeometry,
                row0: int = 0, col0: int = 0, *, ply_step_px: int = 1, preview_px: int = 1500,
                depth_sigma_m: np.ndarray | None = None, depth_range_m: tuple[float, float] | None = None) -> dict:
    """``write_outputs``' files written into ``out_dir`` as it is, each atomically but not as a set: for a folder
    that is already one run's own (an ``OutputSet``'s staging folder)."""
    near_m, far_m = check_depth_range(depth_range_m) if depth_range_m is not None else (None, None)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)

    def aif_images():
        bgr16, bgr8 = srgb_images(aif)
        _imwrite(out / "aif.png", bgr16)
        del bgr16
        _imwrite(out / "aif_preview.png", _downscale(bgr8, preview_px))

    def depth_files():
        save_npy(out / "depth.npy", np.asarray(depth_m, np.float32))
        save_npy(out / "depth_z.npy", range_to_z_map(depth_m, geometry, row0, col0))
        mm = np.where(np.isfinite(depth_m), np.clip(np.round(depth_m * 1000), 1, 65535), 0).astype(np.uint16)
        _imwrite(out / "depth_mm.png", mm)
        del mm
        _imwrite(out / "depth_preview.png", depth_preview(depth_m, preview_px, near_m, far_m))

    def sigma_files():
        save_npy(out / "depth_sigma.npy", np.where(np.isfinite(depth_m), depth_sigma_m, np.nan).astype(np.float32))
        _imwrite(out / "confidence.png", confidence_image(depth_m, depth_sigma_m))

    def point_cloud():
        return write_ply(out / "points.ply", depth_m, aif, geometry, row0, col0, ply_step_px,
                         depth_sigma_m=depth_sigma_m)

    # longest first; the files are independent, and numpy, OpenCV and file writes release the GIL
    jobs = [aif_images, depth_files, lambda: save_npy(out / "aif.npy", np.asarray(aif, np.float32)), point_cloud]
    names = list(OUTPUT_NAMES)
    if depth_sigma_m is not None:
        jobs.insert(2, sigma_files)
        names += list(SIGMA_OUTPUT_NAMES)
    # an error surfaces once the running writers have stopped and the queued ones are cancelled (map_threads)
    done = dict(map_threads(lambda job: job(), jobs, WRITE_THREADS, "write-outputs"))
    points = done[point_cloud]
    files = {name: str(out / name) for name in names}
    return {"files": files, "ply_points": points, "ply_step_px": ply_step_px}


def write_frame_outputs(out_dir: str | os.PathLike, result, frame, geometry: SensorGeometry | None = None,
                        **options) -> dict:
    """``write_outputs`` for a decoded frame: the ROI offset comes from ``frame`` (a ``devices.RawFrame``), the rays
    from ``geometry`` (default the frame's; a calibrated camera's traced rays), the AiF, range and (classical decoder)
    range 1σ from ``result``. ``options``: ``write_outputs``'s keywords (``overwrite=True`` replaces an earlier
    run's set)."""
    arrays, depth_sigma_m = _frame_arrays(result, frame, geometry)
    return write_outputs(out_dir, *arrays, depth_sigma_m=depth_sigma_m, **options)


def write_frame_files(out_dir: str | os.PathLike, result, frame, geometry: SensorGeometry | None = None,
                      **options) -> dict:
    """``write_files`` for a decoded frame (``write_frame_outputs``' arguments): into a run's own staging folder."""
    arrays, depth_sigma_m = _frame_arrays(result, frame, geometry)
    return write_files(out_dir, *arrays, depth_sigma_m=depth_sigma_m, **options)


def _frame_arrays(result, frame, geometry: SensorGeometry | None) -> tuple[tuple, np.ndarray | None]:
    """(``write_outputs``' positional arguments, ``depth_sigma_m``) of a decoded frame."""
    return ((result.aif, result.depth_m, geometry or frame.geometry, frame.roi.y_px, frame.roi.x_px),
            getattr(result, "depth_sigma_m", None))


def write_report(out_dir: str | os.PathLike, report: dict) -> Path:
    path = Path(out_dir) / "report.json"
    write_json(path, report)
    return path
