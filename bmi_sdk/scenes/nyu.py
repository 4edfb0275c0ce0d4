"""NYU Depth V2 *labeled* subset (``nyu_depth_v2_labeled.mat``) as linear RGB + range along the ray.

The file is MATLAB v7.3 (HDF5). MATLAB stores arrays column-major, so h5py
sees them transposed: ``images`` is (N, 3, W, H) uint8 and ``depths`` is
(N, W, H) float32 metres of *planar* z (the in-painted Kinect depth registered
to the RGB camera). We transpose back to H×W, decode sRGB to linear, and turn z
into range along each pixel's ray with the Kinect RGB intrinsics from the NYU
Depth V2 toolbox, ``camera_params.m`` (fx_rgb, fy_rgb, cx_rgb, cy_rgb; Bouguet
calibration, whose pixel coordinates are 0-based like ours).

The official split, ``splits.mat`` (``trainNdxs`` 795, ``testNdxs`` 654,
1-based indices into the 1449 frames), is read when given; it is a MATLAB v5
file (scipy) on the NYU site, v7.3 copies (h5py) are accepted too.

h5py comes with the ``[train]`` extra and is imported on first use, so
``bmi_sdk.scenes`` (the procedural scenes of ``bmi simulate``) loads without it.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import scipy.io

from bmi_sdk.color import srgb_uint_to_linear
from bmi_sdk.extras import needs_extra
from bmi_sdk.scenes.scene import PinholeIntrinsics, Scene

NYU_RGB_INTRINSICS = PinholeIntrinsics(
    fx_px=5.1885790117450188e02, fy_px=5.1946961112127485e02,
    cx_px=3.2558244941119034e02, cy_px=2.5373616633400465e02,
    width_px=640, height_px=480,
)
"""Kinect RGB camera of NYU Depth V2 (toolbox ``camera_params.m``), 640×480."""


def _h5py():
    """h5py, or ``MissingExtraError`` naming the ``[train]`` extra."""
    with needs_extra("reading NYU Depth V2"):
        import h5py
    return h5py


def read_nyu_split(splits_path: str | os.PathLike, split: str) -> np.ndarray:
    """0-based frame indices of the official ``"train"`` or ``"test"`` split from ``splits.mat``."""
    key = {"train": "trainNdxs", "test": "testNdxs"}.get(split)
    if key is None:
        raise ValueError(f"split must be 'train' or 'test', got {split!r}")
    path = Path(splits_path)
    if not path.is_file():
        raise FileNotFoundError(f"NYU split file not found: {path}")
    h5py = _h5py()
    if h5py.is_hdf5(path):
        with h5py.File(path, "r") as f:
            if key not in f:
                raise ValueError(f"{path}: no {key!r} in split file (has {sorted(f.keys())})")
            raw = np.asarray(f[key])
    else:
        mat = scipy.io.loadmat(path)
        if key not in mat:
            raise ValueError(f"{path}: no {key!r} in split file (has {sorted(k for k in mat if not k.startswith('__'))})")
        raw = mat[key]
    ndx = np.asarray(raw).ravel()
    if ndx.size == 0 or np.any(ndx != np.round(ndx)) or ndx.min() < 1:
        raise ValueError(f"{path}: {key} must hold 1-based frame indices")
    return ndx.astype(np.int64) - 1


class NyuDepthV2:
    """Random access to the labeled frames: ``len()``, ``[i]`` and iteration give :class:`Scene`.

    With ``split`` ("train"/"test") and ``splits_path``, only that split's frames
    are visible, in the split file's order. Use as a context manager (or call
    :meth:`close`) to release the HDF5 file.
    """

    def __init__(self, mat_path: str | os.PathLike, split: str | None = None,
                 splits_path: str | os.PathLike | None = None):
        self.path = Path(mat_path)
        if not self.path.is_file():
            raise FileNotFoundError(f"NYU Depth V2 labeled file not found: {self.path}")
        h5py = _h5py()
        if not h5py.is_hdf5(self.path):
            raise ValueError(f"{self.path}: not a MATLAB v7.3 (HDF5) file")
        self._file = h5py.File(self.path, "r")
        try:
            for key in ("images", "depths"):
                if key not in self._file:
                    raise ValueError(f"{self.path}: dataset {key!r} missing (has {sorted(self._file.keys())})")
            self._images, self._depths = self._file["images"], self._file["depths"]
            k = NYU_RGB_INTRINSICS
            if self._depths.ndim != 3 or self._depths.shape[1:] != (k.width_px, k.height_px):
                raise ValueError(f"{self.path}: 'depths' must be (N, {k.width_px}, {k.height_px}) as stored by "
                                 f"MATLAB, got {self._depths.shape}")
            n, w, h = self._depths.shape
            if self._images.shape != (n, 3, w, h) or self._images.dtype != np.uint8:
                raise ValueError(f"{self.path}: 'images' must be uint8 (N, 3, {w}, {h}) matching 'depths', "
                                 f"got {self._images.dtype} {self._images.shape}")
            if split is None and splits_path is not None:
                raise ValueError("splits_path given without split ('train' or 'test')")
            if split is None:
                self.indices = np.arange(n)
            else:
                if splits_path is None:
                    raise ValueError(f"split={split!r} needs splits_path (the official splits.mat)")
                self.indices = read_nyu_split(splits_path, split)
                if self.indices.max() >= n:
                    raise ValueError(f"{splits_path}: split index {self.indices.max() + 1} exceeds the "
                                     f"{n} frames of {self.path}")
        except BaseException:
            self._file.close()
            raise

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, i: int) -> Scene:
        if not -len(self) <= i < len(self):
            raise IndexError(f"frame {i} out of range for {len(self)} frames")
        frame = int(self.indices[i])
        rgb = srgb_uint_to_linear(np.asarray(self._images[frame]).transpose(2, 1, 0))
        z_m = np.asarray(self._depths[frame], dtype=np.float32).T
        z_m = np.where(np.isfinite(z_m) & (z_m > 0), z_m, np.nan)
        return Scene(rgb=np.ascontiguousarray(rgb), range_m=NYU_RGB_INTRINSICS.z_to_range(z_m),
                     name=f"nyu_v2/{frame:04d}", intrinsics=NYU_RGB_INTRINSICS)

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]

    def close(self) -> None:
        self._file.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
