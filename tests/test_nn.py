"""Network, losses, export, training resume and data augmentation (bmi_sdk.nn), on small inputs."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from bmi_sdk.geometry import BMI_SENSOR, SensorGeometry
from bmi_sdk.model_io import field_channels
from bmi_sdk.nn.data import CACHE_SCHEMA, SHARD_SAMPLES, CacheSpec, dihedral, dihedral_field, simulate_sensor
from bmi_sdk.nn.losses import content_loss, fft_loss, silog_loss
from bmi_sdk.nn.model import DualHeadMimoUNet, parameter_count, preset_config

# -- network ------------------------------------------------------------------------------------------

def test_paper_preset_has_the_papers_parameter_count():
    assert parameter_count(DualHeadMimoUNet(preset_config("paper"))) / 1e6 == pytest.approx(10.08, abs=0.005)


def test_output_shapes_and_positive_depth():
    torch.manual_seed(0)
    net = DualHeadMimoUNet(preset_config("tiny")).eval()
    with torch.no_grad():
        aif, depth_m = net(torch.rand(2, 6, 32, 48))
    assert [tuple(a.shape) for a in aif] == [(2, 3, 8, 12), (2, 3, 16, 24), (2, 3, 32, 48)]
    assert depth_m.shape == (2, 1, 32, 48) and bool((depth_m > 0).all())


def test_no_field_ablation_ignores_the_field_channels_and_full_model_does_not():
    torch.manual_seed(0)
    x = torch.rand(1, 6, 32, 32)
    y = x.clone()
    y[:, 3:] = torch.rand(1, 3, 32, 32)
    for name, same in (("tiny-no_field", True), ("tiny", False)):
        net = DualHeadMimoUNet(preset_config(name)).eval()
        with torch.no_grad():
            a, b = net(x)[1], net(y)[1]
        assert torch.equal(a, b) is same


def test_single_scale_ablation_has_no_coarse_input_branches():
    full = DualHeadMimoUNet(preset_config("small"))
    single = DualHeadMimoUNet(preset_config("small-single_scale"))
    assert hasattr(full, "scm") and not hasattr(single, "scm")
    assert parameter_count(single) < parameter_count(full)


# -- losses --------------------------------------------------------------------------------------------

def _preds(value, n=1, c=3, h=16, w=16):
    return [torch.full((n, c, h // 4, w // 4), value), torch.full((n, c, h // 2, w // 2), value),
            torch.full((n, c, h, w), value)]


def test_content_loss_is_sum_of_per_scale_mean_abs_error_on_valid_pixels():
    target = torch.ones(1, 3, 16, 16)
    mask = torch.ones(1, 1, 16, 16)
    assert float(content_loss(_preds(0.25), target, mask)) == pytest.approx(3 * 0.75)
    # garbage in the masked half must not count
    preds = _preds(0.25)
    preds[-1][..., 8:] = 100.0
    mask[..., 8:] = 0
    assert float(content_loss(preds, target, mask)) == pytest.approx(3 * 0.75)


def test_fft_loss_of_a_constant_error_is_half_the_error_per_scale():
    # F(d·1)[0,0] = d·H·W, all other bins 0 → Σ|Re|+|Im| = d·H·W over 2·C·H·W values → d / (2C) · C = d/2
    target = torch.zeros(1, 3, 16, 16)
    loss = fft_loss(_preds(0.4), target, torch.ones(1, 1, 16, 16))
    assert float(loss) == pytest.approx(3 * 0.4 / 2, rel=1e-6)


def test_fft_loss_hand_computed_single_frequency():
    # d = cos(2π x / 4) on 4×4 (one channel): DFT has two bins of value 8 (real) → Σ = 16 over 2·16 values = 0.5
    x = torch.arange(4.0)
    d = torch.cos(2 * math.pi * x / 4)[None, None, None, :].expand(1, 1, 4, 4)
    loss = fft_loss([d], torch.zeros(1, 1, 4, 4), torch.ones(1, 1, 4, 4))
    assert float(loss) == pytest.approx(0.5, abs=1e-6)


@pytest.mark.parametrize("scale", [0.5, 1.0, 2.0, 3.7])
def test_silog_scale_behaviour(scale):
    torch.manual_seed(1)
    target = 0.7 + 9.3 * torch.rand(2, 1, 8, 8)
    mask = torch.ones_like(target)
    pred = scale * target
    assert float(silog_loss(pred, target, mask, lam=1.0)) == pytest.approx(0.0, abs=1e-6)  # the paper's printed form
    expected = (1 - 0.85) * math.log(scale) ** 2  # the variance-weighted form keeps a scale term
    assert float(silog_loss(pred, target, mask)) == pytest.approx(expected, abs=1e-6)


def test_silog_hand_computed_two_pixels_and_mask():
    target = torch.tensor([[[[1.0, 1.0, 5.0]]]])
    pred = torch.tensor([[[[math.e, 1.0, 123.0]]]])
    mask = torch.tensor([[[[1.0, 1.0, 0.0]]]])
    # g = (1, 0): mean g² = 0.5, mean g = 0.5 → 0.5 − 0.85·0.25
    assert float(silog_loss(pred, target, mask)) == pytest.approx(0.5 - 0.85 * 0.25, abs=1e-6)


# -- export ---------------------------------------------------------------------------------------------

def test_onnx_export_matches_torch(tmp_path):
    import onnxruntime as ort

    from bmi_sdk.nn.export import export_onnx
    from bmi_sdk.nn.model import InferenceWrapper

    torch.manual_seed(0)
    net = DualHeadMimoUNet(preset_config("tiny")).eval()
    path = tmp_path / "m.onnx"
    assert export_onnx(net, path) <= 1e-4
    x = torch.rand(1, 6, 40, 52)  # a size the exporter never saw
    got = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(None, {"coded": x.numpy()})
    with torch.no_grad():
        ref = InferenceWrapper(net)(x)
    for g, r in zip(got, ref):
        assert g.shape == tuple(r.shape)
        assert np.max(np.abs(g - r.numpy())) <= 1e-4


def test_a_trained_network_export_is_verified_and_records_its_lens_kernel(tmp_path):
    """``bmi train``'s export goes through the runtime's exporter: the manifest verifies, says the
    monocentric profile's 41-px kernel is the largest PSF and records the check against torch."""
    from bmi_sdk.model_manifest import verify_model
    from bmi_sdk.nn.export import export_with_manifest

    torch.manual_seed(0)
    net = DualHeadMimoUNet(preset_config("tiny"))
    export_with_manifest(net, tmp_path / "m.onnx", preset="tiny", lens="bmi_monocentric",
                         training={"command": "bmi train --steps 0"})
    manifest = verify_model(tmp_path / "m.onnx")
    assert manifest["largest_psf_px"] == 41
    assert manifest["onnx_opset"] == 17 and 0 <= manifest["onnx_max_abs_diff_vs_torch"] <= 1e-4
    assert manifest["training"] == {"command": "bmi train --steps 0"} and "decoder" not in manifest


def test_a_trained_network_export_above_the_tolerance_is_refused(tmp_path, monkeypatch):
    """No export can match torch better than a negative tolerance: the check refuses and no file is left."""
    from bmi_sdk.nn.export import export_onnx
    from bmi_sdk.runtime import export as runtime_export

    monkeypatch.setattr(runtime_export, "TOLERANCE", -1.0)
    torch.manual_seed(0)
    with pytest.raises(RuntimeError, match="differs from torch"):
        export_onnx(DualHeadMimoUNet(preset_config("tiny")), tmp_path / "m.onnx")
    assert list(tmp_path.iterdir()) == []


# -- data -----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("k", [1, 2, 3])
def test_flips_give_the_field_channels_of_the_mirrored_window(k):
    g = BMI_SENSOR
    row0, col0, h, w = 700, 2300, 24, 40
    field = field_channels(g, row0, col0, h, w)
    mrow0 = g.height_px - row0 - h if k & 2 else row0
    mcol0 = g.width_px - col0 - w if k & 1 else col0
    expected = field_channels(g, mrow0, mcol0, h, w)
    got = dihedral_field(field, k)
    np.testing.assert_allclose(got, expected, atol=1e-6)


def test_transpose_gives_the_field_channels_of_the_transposed_window():
    g = SensorGeometry(width_px=3000, height_px=3000)
    field = field_channels(g, 400, 1100, 32, 32)
    np.testing.assert_allclose(dihedral_field(field, 4), field_channels(g, 1100, 400, 32, 32), atol=1e-6)


def test_sensor_chain_is_unbiased_and_quantised():
    rng = np.random.default_rng(0)
    optical = np.full((32, 32, 3), 0.4, np.float32)
    clean = simulate_sensor(optical, 0.0, rng)
    assert np.max(np.abs(clean - 0.4)) <= 0.5 / (4095 - 256) + 1e-6
    noisy = simulate_sensor(optical, 0.02, rng)
    assert abs(float(noisy.mean()) - 0.4) < 2e-3 and 0.005 < float(noisy.std()) < 0.03


def test_noise_range_draws_log_uniform_sigma_and_a_fixed_sigma_draws_nothing():
    from bmi_sdk.nn.data import noise_sigma
    from bmi_sdk.nn.train import TrainConfig

    rng = np.random.default_rng(3)
    before = rng.bit_generator.state
    assert noise_sigma(rng, 0.005, None) == 0.005
    assert rng.bit_generator.state == before  # fixed-σ runs keep the random stream they always had
    sigmas = np.array([noise_sigma(rng, 0.002, 0.05) for _ in range(20000)])
    assert sigmas.min() >= 0.002 and sigmas.max() <= 0.05
    # log-uniform: half the draws below the geometric mean (a uniform draw would put 17 % there),
    # and each of the range's two log-halves split again evenly
    assert abs(np.mean(sigmas < math.sqrt(0.002 * 0.05)) - 0.5) < 0.015
    assert abs(np.mean(sigmas < 0.002 * (0.05 / 0.002) ** 0.25) - 0.25) < 0.015
    for lo, hi in ((0.0, 0.05), (0.05, 0.01), (-0.01, 0.05)):
        with pytest.raises(ValueError, match="sigma_max"):
            noise_sigma(rng, lo, hi)
        with pytest.raises(ValueError, match="sigma_max"):  # refused when the run is configured, not at step 1
            TrainConfig(sigma=lo, sigma_max=hi)


def test_a_config_saved_before_noise_ranges_reads_as_fixed_sigma():
    """Shipped manifests and old checkpoints carry no ``sigma_max``: they mean one σ for every pair."""
    from bmi_sdk.nn.train import TrainConfig

    old = TrainConfig().to_dict()
    del old["sigma_max"]
    assert TrainConfig.from_dict(old) == TrainConfig()
    assert TrainConfig.from_dict(old).sigma_max is None


def _synthetic_cache(path, spec):
    """A cache in the on-disk format with random content (the renderer is tested elsewhere)."""
    path.mkdir()
    (path / "cache.json").write_text(json.dumps({"schema": CACHE_SCHEMA, "spec": spec.to_dict()}))
    rng = np.random.default_rng(0)
    n, s = spec.samples, spec.stored_px
    np.savez(path / "shard_00000.npz", optical=rng.random((n, s, s, 3)).astype(np.float16),
             rgb=rng.random((n, s, s, 3)).astype(np.float16),
             range_m=(0.7 + 9 * rng.random((n, s, s))).astype(np.float32),
             origin=np.array([[1000 + 2 * i, 1500] for i in range(n)], dtype=np.int32))
    assert n <= SHARD_SAMPLES


def test_checkpoint_resume_reproduces_the_next_step(tmp_path):
    from bmi_sdk.nn.train import TrainConfig, Trainer

    spec = CacheSpec(samples=4, crop_px=16, jitter_px=2)
    _synthetic_cache(tmp_path / "cache", spec)
    config = TrainConfig(preset="tiny", steps=3, batch_size=2, cache=spec)
    straight = Trainer(config, tmp_path / "cache")
    straight.step()
    straight.save(tmp_path / "ckpt.pt")
    expected = straight.step()
    resumed = Trainer(config, tmp_path / "cache")
    resumed.load(tmp_path / "ckpt.pt")
    got = resumed.step()
    assert got == expected
    for a, b in zip(straight.net.state_dict().values(), resumed.net.state_dict().values()):
        assert torch.equal(a, b)
    with pytest.raises(ValueError, match="trained with"):
        Trainer(TrainConfig(preset="tiny", steps=4, batch_size=2, cache=spec), tmp_path / "cache").load(
            tmp_path / "ckpt.pt")
    # `bmi train` with a changed command line into that run folder is refused before its render cache is built
    from bmi_sdk.nn.train import CHECKPOINT, train

    run = tmp_path / "run"
    run.mkdir()
    (tmp_path / "ckpt.pt").rename(run / CHECKPOINT)
    changed = TrainConfig(preset="tiny", steps=4, batch_size=2, cache=CacheSpec(samples=8, crop_px=16, jitter_px=2))
    with pytest.raises(ValueError, match="trained with"):
        train(changed, run, tmp_path / "another cache", progress=False)
    assert not (tmp_path / "another cache").exists()


def test_a_cache_rendered_through_another_geometry_is_refused(tmp_path):
    """cache.json records the sensor mapping and PSF tensor; a stale cache (e.g. ideal R·θ) is not reused."""
    from bmi_sdk.nn.data import build_cache, render_identity

    spec = CacheSpec(samples=4, crop_px=16, jitter_px=2)
    stale = {**render_identity(spec.lens), "geometry_sha256": "ideal-r-theta"}
    (tmp_path / "cache").mkdir()
    (tmp_path / "cache" / "cache.json").write_text(json.dumps({"schema": CACHE_SCHEMA, "spec": spec.to_dict(),
                                                               "renderer": stale}))
    with pytest.raises(ValueError, match="ideal-r-theta"):
        build_cache(tmp_path / "cache", spec, progress=False)


def test_a_small_cache_builds_only_the_psf_field_angles_its_renders_touch(tmp_path, monkeypatch):
    """A cache of one pair traces the tensor's field angles its window renders through, every depth of each,
    before rendering: the renders then trace nothing more (the PSF cache holds exactly those shards), and the
    whole tensor (101 field angles, minutes on one core) is not built."""
    from bmi_sdk.lenses import lens_tensor
    from bmi_sdk.nn.data import build_cache, tensor_fields

    monkeypatch.setenv("BMI_CACHE_DIR", str(tmp_path / "psf cache"))
    spec = CacheSpec(samples=1, crop_px=16, jitter_px=2, seed=3)
    fields = tensor_fields(spec, [0])
    build_cache(tmp_path / "cache", spec, progress=False)
    tensor = lens_tensor(spec.lens)
    shards = sorted(int(p.stem.removeprefix("theta_")) for p in tensor.cache_dir.glob("theta_*.npz"))
    assert shards == fields and 1 <= len(fields) < len(tensor.field_deg) / 10
    for i in fields:  # every depth of each field angle, as the whole tensor's build makes it
        tensor._load_shard(i)
        assert tensor.filled[:, i].all()


def test_dihedral_roundtrip():
    a = np.arange(12).reshape(3, 4)
    assert np.array_equal(dihedral(dihedral(a, 3), 3), a)
    assert dihedral(a, 4).shape == (4, 3)


def test_hardware_conditions_are_the_calibrated_error_model():
    """Every bmi eval hardware row is an optics.perturb.Perturbation (the model bmi calibrate fits), rendered
    from the built lens's own tensor: the shift moves each kernel's centroid by 0.5 px along +col, the scale
    magnifies it, and the glare is exactly (1 − f)·PSF + f·G with the calibration's glare kernel."""
    from bmi_sdk.nn.evaluate import EXACT, HARDWARE
    from bmi_sdk.optics import PsfTensor, TensorSpec
    from bmi_sdk.optics.perturb import Perturbation, glare_kernel

    assert all(isinstance(p, Perturbation) for p in (*HARDWARE.values(), *EXACT.values()))
    assert EXACT["joint"].decenter_um == (10.0, 0.0) and EXACT["joint"].tilt_arcmin == (1.0, 0.0)  # the paper's joint
    spec = TensorSpec(field_deg=(30.0,), depth_m=(2.0,), kernel_px=41)

    def kernels(p=None):
        tensor = PsfTensor("bmi_monocentric", spec, use_cache=False, perturbation=p)
        tensor.ensure([0], [0])
        return tensor.data[:, 0, 0].astype(np.float64)

    yy, xx = np.mgrid[-20:21, -20:21].astype(float)

    def centroid(k):
        return np.array([(k * xx).sum(), (k * yy).sum()])

    def rms_radius(k):
        cx, cy = centroid(k)
        return float(np.sqrt((((xx - cx) ** 2 + (yy - cy) ** 2) * k).sum()))

    nominal = kernels()
    shifted = kernels(HARDWARE["psf_shift_0.5px"])
    for c in range(3):
        assert centroid(shifted[c]) - centroid(nominal[c]) == pytest.approx([0.5, 0.0], abs=0.01)
    scaled = kernels(HARDWARE["psf_scale_5pct"])
    assert all(1.02 < rms_radius(scaled[c]) / rms_radius(nominal[c]) < 1.06 for c in range(3))
    glare = glare_kernel(41, (0.0, 0.0), Perturbation().stray_light_spread_px)
    np.testing.assert_allclose(kernels(HARDWARE["stray_light_3pct"]), 0.97 * nominal + 0.03 * glare, atol=1e-6)


def test_eval_exact_conditions_are_known_and_hold_the_perturbed_lens():
    """decenter/tilt and their exact-mode reference are default conditions (rendered and read: tests/test_eval.py)."""
    from bmi_sdk.nn import evaluate

    for name in ("nominal_exact", "decenter_10um", "tilt_1arcmin"):
        assert name in evaluate.known_conditions() and name in evaluate.EXACT
    assert evaluate.EXACT["decenter_10um"].decenter_um == (10.0, 0.0)
    assert evaluate.EXACT["tilt_1arcmin"].tilt_arcmin == (1.0, 0.0)


def test_fisheye_benchmark_scores_the_same_scene_content_as_the_bmi_benchmark():
    """The system comparison is paired: each tile's scored content is identical for both lenses, the fisheye's
    wider margin is the mirror continuation of the BMI window, and the BMI scenes are the plain draws."""
    from bmi_sdk.nn.data import SCENE_MARGIN_PX, mirror_extend
    from bmi_sdk.nn.evaluate import Benchmark
    from bmi_sdk.scenes import generate_scene

    bmi, fish = Benchmark(tile_px=32), Benchmark(lens="fisheye", tile_px=32)
    assert bmi.margin_px == SCENE_MARGIN_PX < fish.margin_px
    for region, i in (("centre", 0), ("edge", 5)):
        (rgb_b, range_b), (rgb_f, range_f) = bmi.scene(region, i), fish.scene(region, i)
        assert rgb_f.shape[:2] == range_f.shape == (32 + 2 * fish.margin_px,) * 2
        mb, mf = bmi.margin_px, fish.margin_px
        np.testing.assert_array_equal(rgb_b[mb:-mb, mb:-mb], rgb_f[mf:-mf, mf:-mf])
        np.testing.assert_array_equal(range_b[mb:-mb, mb:-mb], range_f[mf:-mf, mf:-mf])
        pad = mf - mb  # mirror continuation: the row just outside the drawn scene repeats the one inside
        np.testing.assert_array_equal(range_f[pad - 1], range_f[pad + 1])
    direct = generate_scene(32 + 2 * SCENE_MARGIN_PX, 32 + 2 * SCENE_MARGIN_PX, np.random.default_rng([20260, 7, 1, 5]))
    np.testing.assert_array_equal(bmi.scene("edge", 5)[1], direct.range_m)
    with pytest.raises(ValueError, match="less margin"):
        mirror_extend(direct.rgb, direct.range_m, -2)


# -- bmi train's recorded command ------------------------------------------------------------------------

def test_the_recorded_train_command_parses_back_to_the_run_it_records():
    """The manifest's ``training.command`` is the run's full command line: parsed again it gives the same
    arguments, --cache (which names the cache the run trained on) included."""
    import shlex

    from bmi_sdk.cli import build_parser
    from bmi_sdk.cli.train import _argv

    argv = ["train", "--decoder", "learned", "--preset", "tiny", "--steps", "4000", "--samples", "1024", "--seed",
            "1", "--lr", "2e-4", "--cache", ".bmi_cache/train/refine 1024", "--out", "out/learned",
            "--render-workers", "3", "--refine-sigma", "0.002", "0.01", "--no-export", "--threads", "2"]
    args = build_parser().parse_args(argv)
    recorded = _argv(args)
    assert "--cache '.bmi_cache/train/refine 1024'" in recorded and "--threads 2" in recorded
    again = build_parser().parse_args(["train", *shlex.split(" ".join(recorded))])
    assert vars(again) == vars(args) and again.refine_sigma == [0.002, 0.01]
    defaults = _argv(build_parser().parse_args(["train", "--out", "o"]))
    assert defaults == ["--out o", "--threads 2"]


def test_shipped_manifests_record_their_architecture_s_measured_receptive_field():
    """The runtime sizes tile overlaps from a manifest's receptive_field_px: for every shipped model it must be what
    the one probe (runtime.export.measure_receptive_field) measures on its preset's architecture."""
    from dataclasses import replace

    from bmi_sdk.model_io import INPUT_CHANNELS
    from bmi_sdk.model_manifest import verify_model
    from bmi_sdk.nn.model import DualHeadMimoUNet, InferenceWrapper, preset_config
    from bmi_sdk.runtime.export import measure_receptive_field

    models = sorted((Path(__file__).resolve().parents[1] / "bmi_sdk" / "models").glob("*.onnx"))
    assert models
    for path in models:
        manifest = verify_model(path)
        if manifest.get("decoder", "cnn") == "evidence":  # not an image network: tests/test_evidence_volume.py
            continue
        extra = manifest["input_channels"] - INPUT_CHANNELS
        config = replace(preset_config(manifest["preset"]), extra_channels=extra, sigma_head=bool(extra))
        net = InferenceWrapper(DualHeadMimoUNet(config)).eval()
        assert manifest["receptive_field_px"] == measure_receptive_field(net, 256, channels=manifest["input_channels"])


def test_the_sigma_likelihood_is_minimised_by_the_rms_error_in_metres():
    """The σ head's loss at one relative σ s shared by every pixel is minimal where s·d̂ is the RMS of the depth
    error in metres relative to the read depth (the quantity the runtime's depth_sigma is judged on), not the
    RMS of the log-depth error: with reads at half and twice the truth the two differ by 14 %."""
    import torch

    from bmi_sdk.nn.losses import sigma_nll_loss

    truth = torch.tensor([[[[2.0, 2.0, 4.0, 4.0]]]])
    read = torch.tensor([[[[1.0, 4.0, 2.0, 8.0]]]])  # half and twice the truth
    mask = torch.ones_like(truth, dtype=torch.bool)
    rel = (read - truth) / read
    expected = float(torch.sqrt(torch.mean(rel ** 2)))
    log_s = np.linspace(np.log(0.1), np.log(3.0), 2001)
    losses = [float(sigma_nll_loss(read, read * math.exp(v), truth, mask)) for v in log_s]
    best = math.exp(log_s[int(np.argmin(losses))])
    assert best == pytest.approx(expected, rel=2e-3)
    assert expected / float(torch.sqrt(torch.mean(torch.log(read / truth) ** 2))) == pytest.approx(1.14, abs=0.01)


def test_scene_scale_one_draws_the_scenes_of_the_caches_before_it():
    """``draw_scene`` at scale 1 takes nothing more from the sample's random stream: caches rendered before the
    scale existed are the ones a scale-1 spec renders, bit for bit."""
    from bmi_sdk.nn.data import draw_scene
    from bmi_sdk.scenes import generate_scene

    rgb, range_m = draw_scene(96, 1.0, np.random.default_rng([4, 7]))
    scene = generate_scene(96, 96, np.random.default_rng([4, 7]))
    assert np.array_equal(rgb, scene.rgb) and np.array_equal(range_m, scene.range_m)


def test_a_larger_scene_scale_gives_crops_with_fewer_depth_edges():
    """Scenes drawn up to 8× larger (log-uniform) and cropped hold objects that much larger against the crop: about
    half as many pixels lie on a depth step (the benchmark's scenes are drawn at the crop's scale; a frame's
    objects are larger still)."""
    from bmi_sdk.nn.data import draw_scene

    def edge_share(scale):
        shares = []
        for i in range(12):
            rgb, range_m = draw_scene(64, scale, np.random.default_rng([11, i]))
            assert rgb.shape == (64, 64, 3) and range_m.shape == (64, 64) and np.isfinite(range_m).all()
            steps = np.hypot(*np.gradient(np.log(range_m))) > 0.05
            shares.append(steps.mean())
        return np.mean(shares)

    assert edge_share(8.0) < 0.6 * edge_share(1.0)
    with pytest.raises(ValueError, match="scene_scale_max"):
        CacheSpec(scene_scale_max=0.5)


def test_a_cache_from_before_a_spec_field_is_reused_not_refused(tmp_path):
    """cache.json written before ``scene_scale_max`` existed names no scale; it was rendered at scale 1, so a
    scale-1 spec reuses it (nothing is rendered: its shard is there) and another scale is refused."""
    from bmi_sdk.nn.data import build_cache, render_identity, shard_path

    spec = CacheSpec(samples=4, crop_px=16, jitter_px=2)
    old_spec = {k: v for k, v in spec.to_dict().items() if k != "scene_scale_max"}
    cache = tmp_path / "cache"
    cache.mkdir()
    (cache / "cache.json").write_text(json.dumps({"schema": CACHE_SCHEMA, "spec": old_spec,
                                                  "renderer": render_identity(spec.lens)}))
    shard_path(cache, 0).write_bytes(b"")
    build_cache(cache, spec, progress=False)
    with pytest.raises(ValueError, match="another cache"):
        build_cache(cache, CacheSpec(samples=4, crop_px=16, jitter_px=2, scene_scale_max=4.0), progress=False)


def test_the_benchmark_at_scene_scale_one_is_the_benchmark_and_larger_scales_crop_larger_scenes():
    """``Benchmark(scene_scale=1)`` draws the tiles it always drew (bit for bit); at 4 each tile is the centre of a
    scene drawn 4× larger, the same seed's scene content at the objects' larger size, with fewer depth steps."""
    from bmi_sdk.nn.data import SCENE_MARGIN_PX, mirror_extend
    from bmi_sdk.nn.evaluate import Benchmark
    from bmi_sdk.scenes import generate_scene

    bench = Benchmark(tiles=1, tile_px=64)
    draw_px = bench.tile_px + 2 * SCENE_MARGIN_PX
    before = generate_scene(draw_px, draw_px, np.random.default_rng([bench.seed, 7, 0, 0]))
    want = mirror_extend(before.rgb, before.range_m, bench.margin_px - SCENE_MARGIN_PX)
    got = bench.scene("centre", 0)
    assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])

    def steps(b):
        return np.mean([(np.hypot(*np.gradient(np.log(b.scene(region, 0)[1]))) > 0.05).mean()
                        for region in ("centre", "edge")])

    large = Benchmark(tiles=1, tile_px=64, scene_scale=4.0)
    assert large.scene("centre", 0)[1].shape == got[1].shape
    assert steps(large) < steps(bench)
    with pytest.raises(ValueError, match="scene_scale"):
        Benchmark(scene_scale=0.9)
