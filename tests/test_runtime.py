"""Runtime: tiling equals whole-frame inference, the contract preprocessing, ROI field positions, skipped
tiles, bad models and foreign files refused with clear errors, output files and the `bmi infer` CLI.

Models are exported here from small torch nets that follow the model_io contract: a U-Net-like net with
random weights (tiling/seam tests are about the tiling, not accuracy) and a pass-through net (aif = the
demosaiced RGB input, depth = 1 + θ/60°) that exposes exactly what the runtime fed the network.
"""

from __future__ import annotations

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest
import torch
from torch import nn

from bmi_sdk.geometry import BMI_SENSOR, SensorGeometry
from bmi_sdk.model_io import field_channels, raw_to_rgb
from bmi_sdk.model_manifest import ModelError, manifest_path, read_manifest, write_manifest
from bmi_sdk.runtime import (
    Model,
    TilePlan,
    count_macs,
    export_model,
    infer_raw,
    reflect_indices,
    run_job,
    select_model,
    write_ply,
)

SUBPROCESS_PATIENCE_S = 1800.0
"""A safety net against a hung command only (see tests/test_user_facing.py)."""

BLACK, WHITE = 64, 4095


class SmallUNet(nn.Module):
    """Two scales, a skip, a transposed-conv up-sampling: translation-equivariant on a 4-px grid."""

    def __init__(self):
        super().__init__()
        torch.manual_seed(0)
        self.a = nn.Conv2d(6, 8, 3, padding=1)
        self.d = nn.Conv2d(8, 16, 3, stride=2, padding=1)
        self.b = nn.Conv2d(16, 16, 3, padding=1)
        self.u = nn.ConvTranspose2d(16, 8, 2, stride=2)
        self.o = nn.Conv2d(8, 4, 3, padding=1)

    def forward(self, x):
        h = torch.relu(self.a(x))
        h = h + self.u(torch.relu(self.b(torch.relu(self.d(h)))))
        o = self.o(h)
        return x[:, :3] + 0.1 * o[:, :3], 0.7 + nn.functional.softplus(o[:, 3:])


@pytest.fixture(scope="module")
def unet(tmp_path_factory):
    return export_model(SmallUNet(), tmp_path_factory.mktemp("m") / "unet.onnx", preset="test-unet")


@pytest.fixture(scope="module")
def passthrough(passthrough_model):
    return passthrough_model


def _raw(h, w, seed=0):
    return np.random.default_rng(seed).integers(BLACK, WHITE + 1, (h, w)).astype(np.uint16)


def _infer(model, raw, row0=2000, col0=2800, geometry=BMI_SENSOR, **kw):
    return infer_raw(model, raw, black_level_dn=BLACK, white_level_dn=WHITE, geometry=geometry, row0=row0,
                     col0=col0, **kw)


def test_receptive_field_measured_and_in_manifest(unet, passthrough):
    # conv3 → conv3/2 → conv3 at ½ → convT2 → conv3: reach 1 + 1 + 2 + 2 + 1 (+ the stride grid) px per side
    assert read_manifest(unet)["receptive_field_px"] == 13
    assert read_manifest(passthrough)["receptive_field_px"] == 1


def test_tiled_equals_untiled_on_frame_not_multiple_of_tile(unet):
    raw = _raw(198, 302)  # neither a multiple of the tile nor of 4
    tiled = _infer(Model(unet, tile_px=64, threads=1), raw)
    whole = _infer(Model(unet, tile_px=336, threads=1), raw)
    # the default overlap is the receptive field alone: no cross-fade is needed where both tiles agree
    assert (tiled.plan.overlap_px, tiled.plan.ramp_px) == (16, 0)
    assert whole.tiles_run == 1 and tiled.tiles_run > 12
    assert np.abs(tiled.aif - whole.aif).mean() < 1e-6
    assert np.abs(tiled.depth_m - whole.depth_m).max() < 1e-5
    # an overlap below the receptive field leaves visible seams: the comparison can fail
    seamy = _infer(Model(unet, tile_px=64, threads=1), raw, overlap_px=0)
    assert np.abs(seamy.aif - whole.aif).mean() > 1e-4


def test_int8_copy_keeps_the_models_contract_and_stays_close_to_fp32(unet, tmp_path):
    """quantize_int8: a verified int8 model with the fp32 manifest's fields (quantization and source hash added)
    whose outputs follow the fp32 ones to within int8's resolution of the activations' range."""
    from bmi_sdk.runtime.quantize import quantize_int8

    rng = np.random.default_rng(0)
    raw = [_raw(64, 64, seed=k) for k in range(4)]
    fp32 = Model(unet, tile_px=64, threads=1)
    inputs = [np.concatenate([raw_to_rgb(r, BLACK, WHITE).transpose(2, 0, 1),
                              field_channels(BMI_SENSOR, 2000, 2800, 64, 64)])[None].astype(np.float32) for r in raw]
    dst = quantize_int8(unet, tmp_path / "unet_int8.onnx", inputs)
    source, copy = read_manifest(unet), read_manifest(dst)
    same = {k for k in source if k not in ("sha256", "file", "preset")}
    assert {k: copy[k] for k in same} == {k: source[k] for k in same}
    assert copy["preset"] == "test-unet-int8" and copy["source_sha256"] == source["sha256"]
    int8 = Model(dst, tile_px=64, threads=1)
    probe = inputs[0] + np.float32(0.01) * rng.standard_normal(inputs[0].shape).astype(np.float32)
    (aif32, depth32), (aif8, depth8) = fp32.run(probe), int8.run(probe)
    assert np.abs(aif8 - aif32).mean() < 0.01 and np.abs(depth8 - depth32).mean() < 0.01 * np.abs(depth32).mean()
    with pytest.raises(ValueError, match="reads 1 × 6 × H × W inputs"):
        quantize_int8(unet, tmp_path / "bad.onnx", [inputs[0][:, :3]])


def test_blend_weights_partition_unity_and_cover_frame():
    plan = TilePlan.for_model(300, 500, 96, receptive_field_px=13, overlap_px=2 * 8 + 24)  # a 24-px Hann ramp
    acc = np.zeros((300 + 2 * plan.pad_px + 200, 500 + 2 * plan.pad_px + 200))
    for r, c, w in plan.tiles():
        acc[r + plan.pad_px:r + plan.pad_px + 96, c + plan.pad_px:c + plan.pad_px + 96] += w
    frame = acc[plan.pad_px:plan.pad_px + 300, plan.pad_px:plan.pad_px + 500]
    assert frame.min() > 0.49  # every pixel is covered
    assert np.allclose(frame[:150, :300], 1.0, atol=1e-6)  # uniform interior tiles cross-fade to exactly 1
    assert plan.ramp_px == 24 and all(o % 4 == 0 for o in plan.row_origins + plan.col_origins)


def test_reflect_indices_keep_bayer_phase_any_extent():
    for size in (2, 4, 6, 100):
        idx = reflect_indices(-37, 200, size)
        assert idx.min() >= 0 and idx.max() < size
        assert np.array_equal(idx % 2, np.arange(-37, 163) % 2)


def test_network_sees_contract_preprocessing_and_roi_field(passthrough):
    raw = _raw(130, 250, seed=3)
    res = _infer(Model(passthrough, tile_px=64, threads=1), raw, row0=1000, col0=4002)
    expected_rgb = raw_to_rgb(raw, BLACK, WHITE, "RGGB")  # the whole window demosaiced at once
    assert np.abs(res.aif - expected_rgb)[2:-2, 2:-2].max() < 1e-6  # tile seams invisible to the demosaic
    theta = field_channels(BMI_SENSOR, 1000, 4002, 130, 250)[0]
    assert np.abs(res.depth_m - (1 + theta)).max() < 1e-6  # field position from the ROI offset


def test_black_saturated_and_tiny_frames(passthrough, unet):
    model = Model(passthrough, tile_px=64, threads=1)
    black = _infer(model, np.full((64, 96), BLACK, np.uint16))
    sat = _infer(model, np.full((64, 96), WHITE, np.uint16))
    assert black.aif.max() == 0 and sat.aif.min() == 1.0
    for shape in [(2, 2), (4, 6), (10, 8)]:
        res = _infer(Model(unet, tile_px=64, threads=1, warmup=False), _raw(*shape))
        assert res.aif.shape == (*shape, 3) and res.depth_m.shape == shape and res.tiles_run == 1
        assert np.isfinite(res.depth_m).all() and np.isfinite(res.aif).all()
    with pytest.raises(ValueError, match="even sizes"):
        _infer(model, _raw(9, 8))


def test_tiles_outside_image_circle_are_skipped(unet):
    small_circle = SensorGeometry(width_px=480, height_px=320, max_field_deg=1.5)  # radius ≈ 94 px
    res = _infer(Model(unet, tile_px=64, threads=1), _raw(320, 480), row0=0, col0=0, geometry=small_circle)
    assert res.tiles_skipped > 0 and res.tiles_run > 0
    inside = small_circle.valid_mask()
    assert np.array_equal(res.valid, inside)
    assert np.isnan(res.depth_m[~inside]).all() and np.isfinite(res.depth_m[inside]).all()
    assert (res.aif[~inside] == 0).all()


def test_bad_models_refused_clearly(unet, tmp_path):
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(unet.read_bytes())
    with pytest.raises(ModelError, match="unknown model .*no manifest"):
        Model(bad)
    meta = read_manifest(unet)
    write_manifest(bad, **{k: meta[k] for k in ("preset", "receptive_field_px", "lens", "psf_tensor_key")})
    Model(bad, tile_px=32, warmup=False)  # intact copy with its own manifest loads
    data = bytearray(bad.read_bytes())
    data[len(data) // 2] ^= 0xFF
    bad.write_bytes(bytes(data))
    with pytest.raises(ModelError, match="does not match its manifest"):
        Model(bad)
    bad.write_bytes(b"not an onnx graph at all")
    write_manifest(bad, **{k: meta[k] for k in ("preset", "receptive_field_px", "lens", "psf_tensor_key")})
    with pytest.raises(ModelError, match="onnxruntime cannot load"):
        Model(bad)
    other = json.loads(manifest_path(unet).read_text()) | {"input_name": "image"}
    manifest_path(bad).write_text(json.dumps(other | {"file": "bad.onnx"}))
    bad.write_bytes(unet.read_bytes())
    with pytest.raises(ModelError):  # hash now matches the unet, but the manifest claims another contract
        Model(bad)
    with pytest.raises(ValueError, match="multiple of 4"):
        Model(unet, tile_px=30)


def test_model_selection_by_lens(unet, tmp_path):
    meta = read_manifest(unet)
    for name, lens in (("default", meta["lens"]), ("b_other", meta["lens"]),
                       ("a_fisheye", "fisheye")):  # sorts first: must still never be chosen for BMI
        path = tmp_path / f"{name}.onnx"
        path.write_bytes(unet.read_bytes())
        write_manifest(path, **{k: meta[k] for k in ("preset", "receptive_field_px", "psf_tensor_key")}, lens=lens)
    assert select_model(meta["lens"], "cnn", tmp_path) == tmp_path / "default.onnx"  # the packaged name first
    (tmp_path / "default.onnx").unlink()
    assert select_model(meta["lens"], "cnn", tmp_path) == tmp_path / "b_other.onnx"
    (tmp_path / "b_other.onnx").unlink()
    with pytest.raises(ModelError, match="no cnn model"):  # the fisheye's model is not a fallback
        select_model(meta["lens"], "cnn", tmp_path)
    assert select_model("fisheye", "cnn", tmp_path) == tmp_path / "a_fisheye.onnx"
    with pytest.raises(ModelError, match="no cnn model"):
        select_model(meta["lens"], "cnn", tmp_path / "empty")


def test_ply_points_lie_on_chief_rays(tmp_path):
    depth = np.full((6, 8), 2.5, np.float32)
    depth[0, 0] = np.nan
    aif = np.full((6, 8, 3), 0.5, np.float32)
    n = write_ply(tmp_path / "p.ply", depth, aif, BMI_SENSOR, row0=100, col0=200)
    raw = (tmp_path / "p.ply").read_bytes()
    head, body = raw.split(b"end_header\n")
    assert n == 47 and b"element vertex 47" in head
    pts = np.frombuffer(body, dtype=[("xyz", "<f4", 3), ("rgb", "u1", 3)])
    assert np.allclose(np.linalg.norm(pts["xyz"], axis=1), 2.5, atol=1e-5)
    expected = BMI_SENSOR.ray_directions(100, 201) * 2.5  # first valid pixel: (0, 1)
    assert np.allclose(pts["xyz"][0], expected, atol=1e-5)
    assert (pts["rgb"] == 188).all()  # sRGB(0.5) = 0.735 → 188


def test_count_macs_matches_layer_arithmetic(unet):
    t = 64
    expected = t * t * (8 * 6 * 9) + (t // 2) ** 2 * (16 * 8 * 9 + 16 * 16 * 9) + (t // 2) ** 2 * 16 * (8 * 4) \
        + t * t * (4 * 8 * 9)
    assert count_macs(unet, t) == expected


@pytest.fixture(scope="module")
def dng(tmp_path_factory):
    from devices import Roi, open_camera

    path = tmp_path_factory.mktemp("raw") / "frame.dng"
    with open_camera("sim://rt-test?scene=chart&seed=1") as cam:
        cam.settings.roi = Roi(2980, 2240, 96, 64)
        cam.capture().save_dng(path)
    return path


def test_run_job_writes_all_outputs_and_refuses_foreign_dng(unet, dng, tmp_path):
    from devices import RawFileError, load_raw

    result, report = run_job(dng, tmp_path / "out", model_path=unet, tile_px=64, threads=1)
    for name in ("aif.png", "aif_preview.png", "aif.npy", "depth.npy", "depth_mm.png", "depth_preview.png",
                 "points.ply", "report.json"):
        assert (tmp_path / "out" / name).is_file(), name
    png = cv2.imread(str(tmp_path / "out" / "aif.png"), cv2.IMREAD_UNCHANGED)
    assert png.dtype == np.uint16 and png.shape == (64, 96, 3)
    mm = cv2.imread(str(tmp_path / "out" / "depth_mm.png"), cv2.IMREAD_UNCHANGED)
    assert mm.dtype == np.uint16 and np.abs(mm / 1000 - np.load(tmp_path / "out" / "depth.npy")).max() <= 5e-4
    on_disk = json.loads((tmp_path / "out" / "report.json").read_text())
    assert on_disk["model"]["sha256"] == read_manifest(unet)["sha256"] and on_disk["frame"]["roi"]["x_px"] == 2980
    assert on_disk["tiles_run"] == result.report["tiles_run"] and "network_s" in on_disk["timings_s"]

    frame = load_raw(dng)
    frame.is_bmi = False
    foreign = tmp_path / "foreign.dng"
    frame.save_dng(foreign)
    with pytest.raises(RawFileError, match="another camera"):
        run_job(foreign, tmp_path / "f", model_path=unet, tile_px=64)
    with pytest.raises(ValueError, match="not from a BMI camera"):
        run_job(load_raw(foreign, require_bmi=False), tmp_path / "f", model_path=unet, tile_px=64)
    assert not (tmp_path / "f" / "report.json").exists()


def test_lens_mismatch_refused(unet, dng, tmp_path):
    from devices import load_raw

    frame = load_raw(dng)
    frame.lens = {"name": "fisheye"}
    with pytest.raises(ValueError, match="trained for 'bmi_monocentric'"):
        run_job(frame, tmp_path, model_path=unet, tile_px=64)


def test_cli_infer(unet, dng, tmp_path):
    run = subprocess.run([sys.executable, "-m", "bmi_sdk.cli", "infer", str(dng), "--out", str(tmp_path),
                          "--model", str(unet), "--tile-px", "64", "--threads", "1"],
                         capture_output=True, text=True, timeout=SUBPROCESS_PATIENCE_S)
    assert run.returncode == 0, run.stderr
    assert "decoded with the" in run.stdout and (tmp_path / "points.ply").is_file()
    bad = subprocess.run([sys.executable, "-m", "bmi_sdk.cli", "infer", str(dng), "--out", str(tmp_path / "x"),
                          "--model", str(tmp_path / "missing.onnx")], capture_output=True, text=True, timeout=SUBPROCESS_PATIENCE_S)
    assert bad.returncode == 1 and "no model file" in bad.stderr


def test_packaged_models_match_their_manifests_and_serve_their_own_lens():
    """Every shipped ONNX file is the one its manifest hashes; a BMI frame gets default.onnx, never the
    fisheye baseline (which sorts after it but is also nominal), and the fisheye lens gets its own model."""
    from bmi_sdk.model_manifest import verify_model
    from bmi_sdk.runtime import MODELS_DIR

    shipped = {p.name: verify_model(p) for p in sorted(MODELS_DIR.glob("*.onnx"))}
    assert {"default.onnx", "fisheye.onnx"} <= set(shipped)
    assert shipped["default.onnx"]["lens"] == "bmi_monocentric" and shipped["fisheye.onnx"]["lens"] == "fisheye"
    assert select_model("bmi_monocentric", "cnn") == MODELS_DIR / "default.onnx"
    assert select_model("fisheye", "cnn") == MODELS_DIR / "fisheye.onnx"


def test_export_records_the_lens_profiles_tensor_key_and_kernel(tmp_path):
    """A fisheye export records the fisheye's nominal tensor (161-px kernels) and 161 px as its largest PSF,
    not the monocentric defaults."""
    from bmi_sdk.lenses import lens_tensor

    class PassThrough(nn.Module):
        def forward(self, x):
            return x[:, :3] * 1.0, 1.0 + x[:, 3:4]

    manifest = read_manifest(export_model(PassThrough(), tmp_path / "fish.onnx", preset="test", lens="fisheye"))
    fisheye = lens_tensor("fisheye")
    assert manifest["largest_psf_px"] == 161
    assert manifest["psf_tensor_key"] == fisheye.spec.cache_key(fisheye.lens)


def test_an_export_onnxruntime_disagrees_with_is_refused_and_leaves_no_file(tmp_path):
    """A Python branch on the batch size: tracing keeps the 1-batch example's branch, so at the check's batch of 2
    the ONNX graph and torch disagree; the export is refused and writes neither model nor manifest."""

    class BatchBranch(nn.Module):
        def forward(self, x):
            gain = 1.0 if x.shape[0] == 1 else 2.0
            return x[:, :3] * gain, 1.0 + x[:, 3:4] * gain

    with pytest.raises(RuntimeError, match="differs from torch"):
        export_model(BatchBranch(), tmp_path / "branch.onnx", preset="test")
    assert list(tmp_path.iterdir()) == []
