"""Middlebury 2014 stereo scenes (Scharstein et al., GCPR 2014): ``im0.png`` + ``disp0.pfm`` + ``calib.txt``.

``calib.txt`` gives ``cam0=[f 0 cx; 0 f cy; 0 0 1]`` (pixels), ``doffs`` (the
x-difference of the principal points, pixels) and ``baseline`` (mm); the
dataset page's rule is Z[mm] = baseline · f / (d + doffs). ``disp0.pfm`` holds
``inf`` where the disparity is unknown (→ NaN). Range along each ray then uses
cam0. The image is read as sRGB.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from bmi_sdk.scenes._image_io import read_srgb_png_linear
from bmi_sdk.scenes.pfm import read_pfm
from bmi_sdk.scenes.scene import PinholeIntrinsics, Scene

_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"


def read_middlebury_calib(path: str | os.PathLike) -> dict:
    """``calib.txt`` as a dict; ``cam0``/``cam1`` become 3×3 float arrays, other values floats."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"Middlebury calibration not found: {path}")
    calib = {}
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        key, sep, value = line.partition("=")
        if not sep:
            raise ValueError(f"{path}:{n}: expected key=value, got {line!r}")
        key, value = key.strip(), value.strip()
        if key.startswith("cam"):
            numbers = re.findall(_NUMBER, value)
            if not (value.startswith("[") and value.endswith("]")) or len(numbers) != 9:
                raise ValueError(f"{path}:{n}: {key} must be a 3×3 matrix [a b c; d e f; g h i], got {value!r}")
            calib[key] = np.array(numbers, dtype=np.float64).reshape(3, 3)
        else:
            try:
                calib[key] = float(value)
            except ValueError:
                raise ValueError(f"{path}:{n}: {key} must be a number, got {value!r}") from None
    missing = [k for k in ("cam0", "doffs", "baseline") if k not in calib]
    if missing:
        raise ValueError(f"{path}: missing {', '.join(missing)}")
    return calib


def load_middlebury_scene(folder: str | os.PathLike) -> Scene:
    """One scene folder → :class:`Scene` (linear RGB of im0, range along cam0's rays)."""
    folder = Path(folder)
    calib = read_middlebury_calib(folder / "calib.txt")
    rgb = read_srgb_png_linear(folder / "im0.png")
    disparity = read_pfm(folder / "disp0.pfm")
    h, w = rgb.shape[:2]
    if disparity.shape != (h, w):
        raise ValueError(f"{folder}: disp0.pfm is {disparity.shape}, im0.png is {(h, w)}")
    if ("width" in calib and int(calib["width"]) != w) or ("height" in calib and int(calib["height"]) != h):
        raise ValueError(f"{folder}: calib.txt is for {calib.get('width')}×{calib.get('height')}, "
                         f"im0.png is {w}×{h} (a calib of another resolution?)")
    k = calib["cam0"]
    if k[0, 1] != 0 or k[1, 0] != 0 or np.any(k[2] != (0, 0, 1)):
        raise ValueError(f"{folder}: cam0 is not an upper-triangular pinhole matrix: {k.tolist()}")
    intrinsics = PinholeIntrinsics(k[0, 0], k[1, 1], k[0, 2], k[1, 2], w, h)
    d = disparity.astype(np.float64)
    denom = d + calib["doffs"]
    valid = np.isfinite(d) & (denom > 0)
    z_m = np.full((h, w), np.nan, dtype=np.float32)
    z_m[valid] = calib["baseline"] * k[0, 0] / denom[valid] * 1e-3
    return Scene(rgb=rgb, range_m=intrinsics.z_to_range(z_m), name=f"middlebury2014/{folder.name}",
                 intrinsics=intrinsics)


class Middlebury2014:
    """Scene folders under ``root`` (or ``root`` itself if it is one); iteration gives :class:`Scene`."""

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)
        if not self.root.is_dir():
            raise FileNotFoundError(f"Middlebury folder not found: {self.root}")
        if (self.root / "calib.txt").is_file():
            self.folders = [self.root]
        else:
            self.folders = sorted(p.parent for p in self.root.glob("*/calib.txt"))
        if not self.folders:
            raise FileNotFoundError(f"no Middlebury scene (a folder with calib.txt) in {self.root}")

    def __len__(self) -> int:
        return len(self.folders)

    def __getitem__(self, i: int) -> Scene:
        return load_middlebury_scene(self.folders[i])

    def __iter__(self):
        for folder in self.folders:
            yield load_middlebury_scene(folder)
