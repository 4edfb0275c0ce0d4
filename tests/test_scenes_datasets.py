"""Dataset loaders on small fixtures written in each dataset's real on-disk format (h5py, scipy.io, cv2, PFM)."""

import math

import cv2
import h5py
import numpy as np
import pytest
import scipy.io

from bmi_sdk.color import srgb_to_linear
from bmi_sdk.scenes import (
    NYU_RGB_INTRINSICS,
    FlyingThings3D,
    Middlebury2014,
    NyuDepthV2,
    disparity_to_z_m,
    load_middlebury_scene,
    read_nyu_split,
    write_pfm,
)


def ray_factor(fx, fy, cx, cy, row, col):
    """range / z for one pixel of a pinhole camera, written out independently of the SDK."""
    return math.sqrt(1 + ((col - cx) / fx) ** 2 + ((row - cy) / fy) ** 2)


# -- NYU Depth V2 -------------------------------------------------------------

def write_nyu_mat(path, images_hwc, depths_hw):
    """Store frames as MATLAB v7.3 does: column-major, so HDF5 sees (N, 3, W, H) and (N, W, H)."""
    with h5py.File(path, "w") as f:
        f.create_dataset("images", data=np.stack([im.transpose(2, 1, 0) for im in images_hwc]))
        f.create_dataset("depths", data=np.stack([d.T for d in depths_hw]).astype(np.float32))
        f.create_dataset("labels", data=np.zeros((len(images_hwc), 640, 480), dtype=np.uint16))


@pytest.fixture
def nyu_file(tmp_path):
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, size=(480, 640, 3), dtype=np.uint8) for _ in range(3)]
    images[1][0, 0] = (255, 0, 0)  # a red top-left pixel: checks the transpose
    images[1][479, 0] = (0, 0, 255)  # a blue bottom-left pixel
    depths = [np.full((480, 640), 2.0 + i, dtype=np.float32) for i in range(3)]
    depths[2][100:200, 300:400] = 0.0  # no depth
    write_nyu_mat(tmp_path / "nyu_depth_v2_labeled.mat", images, depths)
    return tmp_path / "nyu_depth_v2_labeled.mat", images, depths


def test_nyu_reads_frames_upright_linear_and_as_range(nyu_file):
    path, images, depths = nyu_file
    with NyuDepthV2(path) as nyu:
        assert len(nyu) == 3
        scene = nyu[1]
        assert scene.rgb.shape == (480, 640, 3) and scene.range_m.shape == (480, 640)
        assert scene.intrinsics == NYU_RGB_INTRINSICS and scene.name == "nyu_v2/0001"
        np.testing.assert_array_equal(scene.rgb[0, 0], [1, 0, 0])
        np.testing.assert_array_equal(scene.rgb[479, 0], [0, 0, 1])
        np.testing.assert_allclose(scene.rgb, srgb_to_linear(images[1] / 255.0), atol=1e-6)
        # a flat fronto-parallel wall at z = 3 m: range = z·√(1 + x² + y²) with camera_params.m
        fx, fy, cx, cy = 518.8579, 519.4696, 325.5824, 253.7362
        for row, col in [(0, 0), (479, 639), (254, 326), (10, 600)]:
            assert scene.range_m[row, col] == pytest.approx(3.0 * ray_factor(fx, fy, cx, cy, row, col), rel=1e-5)
        assert float(scene.range_m.min()) == pytest.approx(3.0, rel=1e-5)
        holes = nyu[2].range_m
        assert np.isnan(holes[100:200, 300:400]).all() and np.isfinite(holes[:100]).all()
        assert [s.name for s in nyu] == ["nyu_v2/0000", "nyu_v2/0001", "nyu_v2/0002"]


@pytest.mark.parametrize("v73", [False, True])
def test_nyu_official_split(nyu_file, tmp_path, v73):
    path, _, _ = nyu_file
    splits = tmp_path / "splits.mat"
    if v73:
        with h5py.File(splits, "w") as f:
            f["trainNdxs"] = np.array([[1.0, 3.0]])
            f["testNdxs"] = np.array([[2.0]])
    else:
        scipy.io.savemat(splits, {"trainNdxs": np.array([[1], [3]]), "testNdxs": np.array([[2]])})
    np.testing.assert_array_equal(read_nyu_split(splits, "train"), [0, 2])
    with NyuDepthV2(path, split="test", splits_path=splits) as test:
        assert len(test) == 1 and test[0].name == "nyu_v2/0001"
    with NyuDepthV2(path, split="train", splits_path=splits) as train:
        assert [s.name for s in train] == ["nyu_v2/0000", "nyu_v2/0002"]
        with pytest.raises(IndexError):
            train[2]


def test_nyu_errors(nyu_file, tmp_path):
    path, _, _ = nyu_file
    with pytest.raises(FileNotFoundError, match="nope.mat"):
        NyuDepthV2(tmp_path / "nope.mat")
    with pytest.raises(ValueError, match="needs splits_path"):
        NyuDepthV2(path, split="train")
    with pytest.raises(ValueError, match="'train' or 'test'"):
        read_nyu_split(path, "val")
    bad = tmp_path / "bad.mat"
    with h5py.File(bad, "w") as f:
        f["images"] = np.zeros((1, 3, 480, 640), dtype=np.uint8)  # not transposed: wrong for MATLAB storage
        f["depths"] = np.zeros((1, 480, 640), dtype=np.float32)
    with pytest.raises(ValueError, match="'depths' must be"):
        NyuDepthV2(bad)
    scipy.io.savemat(tmp_path / "v5.mat", {"images": np.zeros(3)})
    with pytest.raises(ValueError, match="v7.3"):
        NyuDepthV2(tmp_path / "v5.mat")
    splits = tmp_path / "s.mat"
    scipy.io.savemat(splits, {"trainNdxs": np.array([[5]]), "testNdxs": np.array([[1]])})
    with pytest.raises(ValueError, match="exceeds"):
        NyuDepthV2(path, split="train", splits_path=splits)


# -- FlyingThings3D -------------------------------------------------------------

def write_png_rgb(path, rgb_uint8):
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), rgb_uint8[:, :, ::-1])


@pytest.fixture
def flyingthings_root(tmp_path):
    h, w = 54, 96  # a 1/10 scale frame: f scales to 105 px
    rgb = np.zeros((h, w, 3), dtype=np.uint8)
    rgb[:, :, 0] = 200
    col = np.arange(w, dtype=np.float32)[None, :]
    disparity = np.broadcast_to(10.0 + 0.3 * col, (h, w)).astype(np.float32).copy()  # a slanted plane
    disparity[20:30, 40:60] = 80.0  # a near box
    disparity[0, 0] = np.inf
    for seq in ("0000", "0001"):
        for cam in ("left", "right"):
            write_png_rgb(tmp_path / "frames_cleanpass" / "TRAIN" / "A" / seq / cam / "0006.png", rgb)
            d = tmp_path / "disparity" / "TRAIN" / "A" / seq / cam
            d.mkdir(parents=True, exist_ok=True)
            write_pfm(d / "0006.pfm", disparity)
    return tmp_path, disparity


def test_disparity_rule_maps_range_affinely_in_inverse_depth():
    d = np.array([[5.0, 10.0, 20.0, 0.0, np.nan]])
    z = disparity_to_z_m(d, 0.7, 10.0, percentiles=(0, 100))
    assert z[0, 0] == pytest.approx(10.0) and z[0, 2] == pytest.approx(0.7)
    # middle disparity → inverse-depth midpoint
    assert 1 / z[0, 1] == pytest.approx(0.5 * (1 / 0.7 + 1 / 10.0) - (1 / 0.7 - 1 / 10.0) / 6, rel=1e-6)
    assert np.isnan(z[0, 3]) and np.isnan(z[0, 4])
    assert disparity_to_z_m(np.full((2, 2), 7.0))[0, 0] == pytest.approx(1 / (0.5 * (1 / 0.7 + 0.1)))


def test_flyingthings_loader_planes_stay_planes(flyingthings_root):
    root, disparity = flyingthings_root
    data = FlyingThings3D(root)
    assert len(data) == 2 and data[0].name == "flyingthings3d/A/0000/left/0006"
    scene = data[0]
    k = scene.intrinsics
    assert (k.fx_px, k.cx_px, k.cy_px) == (105.0, 47.5, 26.5)
    np.testing.assert_allclose(scene.rgb[..., 0], srgb_to_linear(200 / 255), rtol=1e-6)
    assert np.isnan(scene.range_m[0, 0])
    valid = np.isfinite(scene.range_m)
    assert np.nanmin(scene.range_m) >= 0.7 - 1e-5
    # back-project: the slanted-plane pixels must lie on one 3D plane (the rule is projective)
    rows, cols = np.nonzero(valid & (disparity < 80))
    z = scene.range_m[rows, cols] / np.sqrt(1 + ((cols - 47.5) / 105) ** 2 + ((rows - 26.5) / 105) ** 2)
    points = np.stack([(cols - 47.5) / 105 * z, (rows - 26.5) / 105 * z, z], axis=1)
    centred = points - points.mean(axis=0)
    singular = np.linalg.svd(centred, compute_uv=False)
    assert singular[-1] < 1e-4 * singular[0]
    # the near box is nearer than the plane behind it
    assert np.nanmax(scene.range_m[20:30, 40:60]) < np.nanmin(scene.range_m[20:30, :40])


def test_flyingthings_errors(flyingthings_root, tmp_path):
    root, _ = flyingthings_root
    with pytest.raises(FileNotFoundError, match="frames_finalpass"):
        FlyingThings3D(root, pass_name="finalpass")
    with pytest.raises(ValueError, match="pass_name"):
        FlyingThings3D(root, pass_name="dirty")
    (root / "disparity" / "TRAIN" / "A" / "0001" / "left" / "0006.pfm").unlink()
    with pytest.raises(FileNotFoundError, match="disparity for"):
        FlyingThings3D(root)[1]
    write_pfm(root / "disparity" / "TRAIN" / "A" / "0001" / "left" / "0006.pfm", np.ones((5, 5), np.float32))
    with pytest.raises(ValueError, match="does not match image"):
        FlyingThings3D(root)[1]
    write_pfm(root / "disparity" / "TRAIN" / "A" / "0001" / "left" / "0006.pfm", np.ones((54, 96, 3), np.float32))
    with pytest.raises(ValueError, match="single-channel"):
        FlyingThings3D(root)[1]


# -- Middlebury 2014 ------------------------------------------------------------

CALIB = """cam0=[{f} 0 {cx}; 0 {f} {cy}; 0 0 1]
cam1=[{f} 0 {cx1}; 0 {f} {cy}; 0 0 1]
doffs={doffs}
baseline={baseline}
width={w}
height={h}
ndisp=280
isint=0
vmin=31
vmax=257
dyavg=0.918
dymax=1.516
"""


def write_middlebury(folder, h=40, w=60, f=399.7684, cx=29.1, cy=20.3, doffs=13.111, baseline=193.001):
    folder.mkdir(parents=True)
    (folder / "calib.txt").write_text(CALIB.format(f=f, cx=cx, cy=cy, cx1=cx + doffs, doffs=doffs,
                                                   baseline=baseline, w=w, h=h))
    write_png_rgb(folder / "im0.png", np.full((h, w, 3), (10, 128, 250), dtype=np.uint8))
    disparity = np.full((h, w), 25.0, dtype=np.float32)
    disparity[5:10, 5:10] = np.inf
    write_pfm(folder / "disp0.pfm", disparity)


def test_middlebury_depth_from_calib(tmp_path):
    write_middlebury(tmp_path / "Adirondack-perfect")
    write_middlebury(tmp_path / "Jadeplant-perfect")
    data = Middlebury2014(tmp_path)
    assert len(data) == 2 and [s.name for s in data] == ["middlebury2014/Adirondack-perfect",
                                                         "middlebury2014/Jadeplant-perfect"]
    scene = data[0]
    z_m = 193.001 * 399.7684 / (25.0 + 13.111) / 1000.0  # Z[mm] = baseline·f/(d + doffs)
    for row, col in [(0, 0), (20, 29), (39, 59)]:
        expected = z_m * ray_factor(399.7684, 399.7684, 29.1, 20.3, row, col)
        assert scene.range_m[row, col] == pytest.approx(expected, rel=1e-5)
    assert np.isnan(scene.range_m[5:10, 5:10]).all()
    np.testing.assert_allclose(scene.rgb[0, 0], srgb_to_linear(np.array([10, 128, 250]) / 255), rtol=1e-6)
    assert load_middlebury_scene(tmp_path / "Jadeplant-perfect").name.endswith("Jadeplant-perfect")


def test_middlebury_errors(tmp_path):
    write_middlebury(tmp_path / "s", w=60)
    (tmp_path / "s" / "calib.txt").write_text(CALIB.format(f=1, cx=1, cy=1, cx1=1, doffs=1, baseline=1, w=120, h=40))
    with pytest.raises(ValueError, match="another resolution"):
        load_middlebury_scene(tmp_path / "s")
    (tmp_path / "s" / "calib.txt").write_text("cam0=[1 0 1; 0 1 1]\ndoffs=1\nbaseline=1\n")
    with pytest.raises(ValueError, match="3×3 matrix"):
        load_middlebury_scene(tmp_path / "s")
    (tmp_path / "s" / "calib.txt").write_text("cam0=[1 0 1; 0 1 1; 0 0 1]\ndoffs=1\n")
    with pytest.raises(ValueError, match="missing baseline"):
        load_middlebury_scene(tmp_path / "s")
    (tmp_path / "s" / "disp0.pfm").unlink()
    with pytest.raises(FileNotFoundError):
        Middlebury2014(tmp_path / "nothing-here")
    (tmp_path / "s" / "calib.txt").write_text("cam0=[1 0 1; 0 1 1; 0 0 1]\ndoffs=1\nbaseline=1\n")
    with pytest.raises(FileNotFoundError, match="disp0.pfm"):
        load_middlebury_scene(tmp_path / "s")
