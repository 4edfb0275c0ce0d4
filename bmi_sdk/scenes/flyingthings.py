"""FlyingThings3D (Mayer et al., CVPR 2016): RGB PNG + disparity PFM, mapped to metric range.

Layout (as distributed): ``<root>/frames_cleanpass/<SPLIT>/<A|B|C>/<seq>/<left|right>/<frame>.png``
(or ``frames_finalpass``) and ``<root>/disparity/<SPLIT>/<A|B|C>/<seq>/<left|right>/<frame>.pfm``.

The renders come from a virtual camera with f = 1050 px and the principal
point at the image centre (479.5, 269.5) for 960×540 (dataset page: 32 mm
sensor width, 35 mm focal length → 35/32·960 = 1050 px), but the scenes have no
metric scale. Our rule to metres — the *disparity-affine* rule:

    1/z = 1/far + (d − d_lo)/(d_hi − d_lo) · (1/near − 1/far),  clipped to [near, far]

with d_lo, d_hi the 0.5 and 99.5 percentiles of the frame's valid disparity and
[near, far] = [0.7, 10] m by default. It is exactly a virtual stereo rig
z = f·B'/(d + d_off) (Middlebury's form, with a per-frame baseline B' and
offset d_off), so it keeps occlusion order, and since 1/z stays affine in image
coordinates on a plane, planes stay planes. The percentile clip keeps a few
outlier disparities from squeezing the frame; those pixels saturate at near/far.
Range along the ray then uses the virtual intrinsics.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from bmi_sdk.scenes._image_io import read_srgb_png_linear
from bmi_sdk.scenes.pfm import read_pfm
from bmi_sdk.scenes.scene import PinholeIntrinsics, Scene

FLYINGTHINGS_FOCAL_PX = 1050.0
"""Virtual focal length of FlyingThings3D renders at 960×540 (dataset documentation)."""


def flyingthings_intrinsics(width_px: int, height_px: int) -> PinholeIntrinsics:
    """The virtual camera: f = 1050 px (scaled with width from 960), principal point at the image centre."""
    f = FLYINGTHINGS_FOCAL_PX * width_px / 960.0
    return PinholeIntrinsics(f, f, (width_px - 1) / 2, (height_px - 1) / 2, width_px, height_px)


def disparity_to_z_m(disparity_px: np.ndarray, near_m: float = 0.7, far_m: float = 10.0,
                     percentiles: tuple[float, float] = (0.5, 99.5)) -> np.ndarray:
    """Planar z in metres from a scale-free disparity map by the disparity-affine rule (module doc).

    Non-finite or non-positive disparities become NaN. A frame whose robust
    disparity range is empty (a single plane facing the camera) lands at the
    inverse-depth midpoint of [near, far].
    """
    if not 0 < near_m < far_m:
        raise ValueError(f"need 0 < near_m < far_m, got {near_m}, {far_m}")
    d = np.asarray(disparity_px, dtype=np.float64)
    valid = np.isfinite(d) & (d > 0)
    z = np.full(d.shape, np.nan, dtype=np.float32)
    if not valid.any():
        return z
    d_lo, d_hi = np.percentile(d[valid], percentiles)
    inv_near, inv_far = 1.0 / near_m, 1.0 / far_m
    if d_hi > d_lo:
        t = np.clip((d[valid] - d_lo) / (d_hi - d_lo), 0.0, 1.0)
    else:
        t = np.full(int(valid.sum()), 0.5)
    z[valid] = 1.0 / (inv_far + t * (inv_near - inv_far))
    return z


class FlyingThings3D:
    """Frames of one pass/split/camera: ``len()``, ``[i]`` and iteration give :class:`Scene`."""

    def __init__(self, root: str | os.PathLike, pass_name: str = "cleanpass", split: str = "TRAIN",
                 camera: str = "left", near_m: float = 0.7, far_m: float = 10.0):
        if pass_name not in ("cleanpass", "finalpass"):
            raise ValueError(f"pass_name must be 'cleanpass' or 'finalpass', got {pass_name!r}")
        if camera not in ("left", "right"):
            raise ValueError(f"camera must be 'left' or 'right', got {camera!r}")
        self.root = Path(root)
        self.frames_dir = self.root / f"frames_{pass_name}" / split
        self.disparity_dir = self.root / "disparity" / split
        for d in (self.frames_dir, self.disparity_dir):
            if not d.is_dir():
                raise FileNotFoundError(f"FlyingThings3D folder not found: {d}")
        self.near_m, self.far_m = near_m, far_m
        self.images = sorted(p for p in self.frames_dir.rglob("*.png") if p.parent.name == camera)
        if not self.images:
            raise FileNotFoundError(f"no {camera}/*.png frames under {self.frames_dir}")

    def __len__(self) -> int:
        return len(self.images)

    def __getitem__(self, i: int) -> Scene:
        image_path = self.images[i]
        rel = image_path.relative_to(self.frames_dir)
        disparity_path = (self.disparity_dir / rel).with_suffix(".pfm")
        if not disparity_path.is_file():
            raise FileNotFoundError(f"disparity for {image_path} not found: {disparity_path}")
        rgb = read_srgb_png_linear(image_path)
        disparity = read_pfm(disparity_path)
        if disparity.ndim != 2:
            raise ValueError(f"{disparity_path}: expected a single-channel ('Pf') disparity PFM, got "
                             f"shape {disparity.shape}")
        if disparity.shape != rgb.shape[:2]:
            raise ValueError(f"{disparity_path}: disparity {disparity.shape} does not match image "
                             f"{rgb.shape[:2]} of {image_path}")
        intrinsics = flyingthings_intrinsics(rgb.shape[1], rgb.shape[0])
        z_m = disparity_to_z_m(disparity, self.near_m, self.far_m)
        return Scene(rgb=rgb, range_m=intrinsics.z_to_range(z_m),
                     name=f"flyingthings3d/{rel.with_suffix('').as_posix()}", intrinsics=intrinsics)

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]
