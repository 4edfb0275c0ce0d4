"""The learned refinement (``--decoder learned``): its warm start reproduces the shipped network, the runtime
feeds it the classical decoder's channels tile by tile exactly (an identity refinement must return the
classical decoder's depth, 1σ and AiF) and returns the network's depth fused with the classical one (with the
weights ``bmi fit-fusion`` writes into the manifest, else by their σs), a training run goes from renders to a
verified ONNX model, and the manifests keep the two kinds of model apart."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch
from torch import nn

from bmi_sdk.decode import ClassicalConfig, ClassicalDecoder
from bmi_sdk.decode.features import FEATURE_DEPTH_REF_M, extra_channels
from bmi_sdk.lenses import lens_geometry, lens_tensor
from bmi_sdk.model_manifest import ModelError, verify_model
from bmi_sdk.render import PsfMap

CONFIG = ClassicalConfig(candidates=12)


def _channels(config: ClassicalConfig = CONFIG) -> int:
    psf_map = PsfMap(lens_tensor("bmi_monocentric"), lens_geometry("bmi_monocentric"), mode="tensor")
    return extra_channels(ClassicalDecoder.for_psf_map(psf_map, config))


class IdentityRefinement(nn.Module):
    """Returns what it is given: depth and 1σ from the classical channels, AiF = the classical AiF channels."""

    def forward(self, x):
        depth = FEATURE_DEPTH_REF_M * torch.exp(x[:, 6:7])
        return x[:, -3:] * 1.0, depth, depth * torch.exp(x[:, 7:8])


@pytest.fixture(scope="module")
def identity_model(tmp_path_factory):
    from bmi_sdk.runtime import export_model

    return export_model(IdentityRefinement(), tmp_path_factory.mktemp("identity") / "identity.onnx",
                        preset="test-identity", extra_channels=_channels(), classical_config=CONFIG.to_dict())


def test_a_warm_started_refinement_computes_the_shipped_network():
    """New input channels and the σ output start at zero: the refinement's depth and AiF are the shipped
    model's (run by onnxruntime), whatever the classical channels hold."""
    import onnxruntime as ort

    from bmi_sdk.nn.model import DualHeadMimoUNet, ModelConfig, preset_config
    from bmi_sdk.nn.train import init_from_onnx
    from bmi_sdk.runtime.model import DEFAULT_MODEL

    config = ModelConfig(**{**preset_config("tiny").to_dict(), "extra_channels": 9, "sigma_head": True})
    net = DualHeadMimoUNet(config).eval()
    assert init_from_onnx(net, DEFAULT_MODEL) == 94
    x = torch.rand(1, 15, 64, 96, generator=torch.Generator().manual_seed(1))
    x[:, 6:] *= 5.0
    with torch.no_grad():
        aif, depth, sigma = net(x)
    session = ort.InferenceSession(str(DEFAULT_MODEL), providers=["CPUExecutionProvider"])
    ref_aif, ref_depth = session.run(None, {"coded": x[:, :6].numpy()})
    np.testing.assert_allclose(aif[-1].numpy(), ref_aif, atol=1e-4)
    np.testing.assert_allclose(depth.numpy(), ref_depth, rtol=1e-4)
    np.testing.assert_allclose((sigma / depth).numpy(), 0.2, rtol=1e-5)


def test_a_refinement_warm_started_from_a_refinement_keeps_its_trained_sigma_head():
    """Warm-starting from the shipped refinement copies its σ head too (it was reset to log 0.2, so a
    continued training run began with an untrained σ): with the input statistics set as the export's, the
    network computes the shipped model's depth, AiF and 1σ."""
    import onnx
    import onnxruntime as ort
    from onnx import numpy_helper

    from bmi_sdk.nn.model import DualHeadMimoUNet, ModelConfig, preset_config
    from bmi_sdk.nn.train import init_from_onnx
    from bmi_sdk.runtime.model import DEFAULT_MODEL

    shipped = DEFAULT_MODEL.parent / "learned.onnx"
    config = ModelConfig(**{**preset_config("tiny").to_dict(), "extra_channels": 13, "sigma_head": True})
    net = DualHeadMimoUNet(config).eval()
    init_from_onnx(net, shipped)
    stats = {t.name: numpy_helper.to_array(t) for t in onnx.load(str(shipped)).graph.initializer}
    with torch.no_grad():
        for name in ("extra_mean", "extra_std"):  # set from the training data, not copied by a warm start
            getattr(net, name).copy_(torch.from_numpy(np.array(stats["net." + name])))
    x = torch.rand(1, 19, 64, 96, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        aif, depth, sigma = net(x)
    session = ort.InferenceSession(str(shipped), providers=["CPUExecutionProvider"])
    ref_aif, ref_depth, ref_sigma = session.run(None, {"coded": x.numpy()})
    np.testing.assert_allclose(depth.numpy(), ref_depth, rtol=1e-4)
    np.testing.assert_allclose(sigma.numpy(), ref_sigma, rtol=1e-4)
    assert np.std(ref_sigma / ref_depth) > 1e-3  # a trained head: not the constant 0.2 of a fresh one


def test_an_identity_refinement_returns_the_classical_decode_through_the_tiled_runtime(tmp_path, identity_model, bmi):
    """Tiles of 64 px over a 128² frame, each fed its slice of the classical channels: the learned decoder's
    depth, 1σ and AiF must be the classical decoder's (the channels' clips aside); the design camera's AiF takes no
    step through its kernels (``runtime.learned.consistent_aif``)."""
    bmi("simulate", "--procedural", 5, "--size", 128, "--field-deg", 20, "--psf-mode", "tensor", "--noise", 0.005,
        "--out", tmp_path / "f.dng")
    bmi("infer", tmp_path / "f.dng", "--out", tmp_path / "c", "--decoder", "classical", "--candidates", 12,
        "--quiet")
    out = bmi("infer", tmp_path / "f.dng", "--out", tmp_path / "l", "--decoder", "learned", "--model",
              identity_model, "--tile-px", 64, "--quiet").stdout
    assert "learned refinement" in out
    report = json.loads((tmp_path / "l" / "report.json").read_text())
    assert report["decoder"] == "learned" and report["tiles_run"] > 1 and report["model"]["decoder"] == "learned"
    assert report["decoder_stats"]["config"]["candidates"] == 12 and report["aif_consistency_step"] is False
    depth_c, depth_l = np.load(tmp_path / "c" / "depth.npy"), np.load(tmp_path / "l" / "depth.npy")
    assert np.array_equal(np.isnan(depth_c), np.isnan(depth_l)) and np.isfinite(depth_l).mean() > 0.9
    np.testing.assert_allclose(depth_l, depth_c, rtol=1e-4)
    sigma_c, sigma_l = np.load(tmp_path / "c" / "depth_sigma.npy"), np.load(tmp_path / "l" / "depth_sigma.npy")
    np.testing.assert_allclose(sigma_l, sigma_c, rtol=1e-3)
    aif_c, aif_l = np.load(tmp_path / "c" / "aif.npy"), np.load(tmp_path / "l" / "aif.npy")
    np.testing.assert_allclose(aif_l, np.clip(aif_c, 0.0, 2.0), atol=1e-5)
    assert b"property float sigma" in (tmp_path / "l" / "points.ply").read_bytes()[:400]


class DoubledRefinement(nn.Module):
    """Reads twice the classical depth, with a 1σ of ``rel`` × its own depth; AiF = the classical AiF channels."""

    def __init__(self, rel: float):
        super().__init__()
        self.rel = rel

    def forward(self, x):
        depth = 2.0 * FEATURE_DEPTH_REF_M * torch.exp(x[:, 6:7])
        return x[:, -3:] * 1.0, depth, depth * self.rel


FITTED = {"intercept": 1.0, "rel_sigma_a": -2.0, "rel_sigma_b": 1.0, "gap": -0.5, "gap_floor": 0.01}
FITTED_WITH_VARIATION = {**FITTED, "variation_a": -0.8}


def _doubled_model(path, rel: float, fusion: dict | None = None):
    """A ``DoubledRefinement(rel)`` exported to ``path``, its manifest carrying ``fusion`` weights when given."""
    from bmi_sdk.model_manifest import manifest_path
    from bmi_sdk.runtime import export_model

    model = export_model(DoubledRefinement(rel), path, preset="test-doubled", extra_channels=_channels(),
                         classical_config=CONFIG.to_dict())
    if fusion is not None:
        doc = json.loads(manifest_path(model).read_text())
        manifest_path(model).write_text(json.dumps({**doc, "fusion": {"weights": fusion}}))
    return model


@pytest.mark.parametrize("rel, fusion", [(30.0, None), (1e-4, None), (0.1, FITTED), (0.1, FITTED_WITH_VARIATION)])
def test_bmi_infer_returns_the_fusion_of_the_two_reads(tmp_path, rel, fusion, bmi):
    """Through ``bmi infer --decoder learned``: a network that reads 2× the classical depth with a huge σ leaves
    the classical read (within its weight's share of log 2); one with a tiny σ decides alone; a manifest's
    fitted weights are the ones used. Each time the written depth and σ are ``fuse_log_depth`` of the classical
    decoder's written maps and the network's, with the manifest's weights (else the inverse-variance ones)."""
    from bmi_sdk.decode.fusion import INVERSE_VARIANCE, FusionWeights, fuse_log_depth

    model = _doubled_model(tmp_path / "doubled.onnx", rel, fusion)
    weights = INVERSE_VARIANCE if fusion is None else FusionWeights.from_dict(fusion)
    bmi("simulate", "--procedural", 5, "--size", 128, "--field-deg", 20, "--psf-mode", "tensor", "--noise", 0.005,
        "--out", tmp_path / "f.dng")
    bmi("infer", tmp_path / "f.dng", "--out", tmp_path / "c", "--decoder", "classical", "--candidates", 12,
        "--quiet")
    err = bmi("-v", "infer", tmp_path / "f.dng", "--out", tmp_path / "l", "--decoder", "learned", "--model", model,
              "--tile-px", 64, "--quiet").stderr
    assert "the classical read's mean weight" in err
    depth_c, sigma_c = np.load(tmp_path / "c" / "depth.npy"), np.load(tmp_path / "c" / "depth_sigma.npy")
    depth_l, sigma_l = np.load(tmp_path / "l" / "depth.npy"), np.load(tmp_path / "l" / "depth_sigma.npy")
    ok = np.isfinite(depth_l)
    assert np.array_equal(ok, np.isfinite(depth_c)) and ok.mean() > 0.9
    variation = None
    if weights.reads_variation:  # the classical read's log-depth variation, from the same decode in process
        from bmi_sdk.built_camera import BuiltCamera
        from bmi_sdk.decode.classical import log_depth_variation_px
        from bmi_sdk.runtime.classical import classical_decoder, decode_frame
        from devices.dng import load_raw

        decoded = decode_frame(classical_decoder(BuiltCamera(), CONFIG), load_raw(tmp_path / "f.dng"),
                               BuiltCamera()).parts["classical"]
        np.testing.assert_array_equal(decoded.depth_m, depth_c)
        variation = log_depth_variation_px(decoded, CONFIG.stride_px)
        assert np.nanmax(variation) > 0.05 > np.nanmin(variation)  # the scene has both flat and cluttered parts
    want_depth, want_sigma, want_share = fuse_log_depth(depth_c, sigma_c, 2.0 * depth_c, 2.0 * rel * depth_c,
                                                        weights, None, variation)
    np.testing.assert_allclose(depth_l[ok], want_depth[ok], rtol=1e-3)
    np.testing.assert_allclose(sigma_l[ok], want_sigma[ok], rtol=1e-3)
    report = json.loads((tmp_path / "l" / "report.json").read_text())
    share = report["fusion"]["classical_weight_mean"]
    assert share == pytest.approx(np.mean(want_share[ok]), abs=1e-3)
    assert report["fusion"]["weights"] == ("inverse-variance" if fusion is None else "fitted")
    if fusion is None:
        near = depth_c if rel > 1 else 2.0 * depth_c
        assert np.median(np.abs(depth_l[ok] / near[ok] - 1.0)) < 1e-3
        assert (share > 0.99) if rel > 1 else (share < 0.01)
    else:
        assert 0.01 < share < 0.99


def test_fit_fusion_writes_weights_the_runtime_reads_and_a_rerun_writes_the_same(tmp_path, passthrough_model, bmi):
    """``bmi fit-fusion`` on a refinement whose network reads 2× the classical depth: the fitted fusion's objective
    is no worse than the inverse-variance one's (the fit starts there and only descends), the weights land in the
    manifest, ``Model`` reads them, a second run writes the same weights, and a run over weights the runtime
    refuses replaces them. An end-to-end model is refused."""
    from bmi_sdk.decode.fusion import FusionWeights
    from bmi_sdk.model_manifest import manifest_path
    from bmi_sdk.runtime.model import Model

    model = _doubled_model(tmp_path / "doubled.onnx", 0.1)
    args = ("fit-fusion", "--model", model, "--tiles", 1, "--scales", "4", "--sigmas", "0.005,0.02", "--pixels", 3000)
    out = bmi(*args).stdout
    assert "| scale 4, σ 0.02 |" in out and "wrote the weights" in out
    fit = json.loads(manifest_path(model).read_text())["fusion"]
    assert fit["fit"]["objective"]["fitted"] <= fit["fit"]["objective"]["inverse_variance"]
    assert len(fit["fit"]["mean_abs_log_error"]) == 2
    weights = FusionWeights.from_dict(fit["weights"])
    assert Model(model, tile_px=64, warmup=False).fusion_weights == weights
    assert (weights.noise_ref_sigma, weights.noise_levels) == (0.005, (0.02,))
    bmi(*args)
    assert json.loads(manifest_path(model).read_text())["fusion"]["weights"] == fit["weights"]
    # a manifest whose weights the runtime refuses is repaired by a refit
    doc = json.loads(manifest_path(model).read_text())
    manifest_path(model).write_text(json.dumps({**doc, "fusion": {"weights": {**fit["weights"], "gap": "steep"}}}))
    with pytest.raises(ModelError, match="fusion weights are unreadable"):
        Model(model, tile_px=64, warmup=False)
    bmi(*args)
    assert json.loads(manifest_path(model).read_text())["fusion"]["weights"] == fit["weights"]
    run = subprocess.run([sys.executable, "-m", "bmi_sdk.cli", "fit-fusion", "--model", str(passthrough_model),
                          "--tiles", "1"], capture_output=True, text=True)
    assert run.returncode == 1 and "not a learned refinement" in run.stderr


def test_a_manifest_with_unreadable_fusion_weights_is_refused(tmp_path):
    from bmi_sdk.runtime.model import Model

    model = _doubled_model(tmp_path / "doubled.onnx", 0.1, {**FITTED, "gap": "steep"})
    with pytest.raises(ModelError, match="fusion weights are unreadable.*gap must be a finite number"):
        Model(model, tile_px=64, warmup=False)


def test_a_refinement_trains_from_renders_to_a_verified_model(tmp_path):
    """Render two pairs, decode them, take two optimiser steps from the shipped weights, export: the model is
    verified, says it is a learned refinement and runs in the runtime on its own classical channels."""
    from bmi_sdk.nn.data import CacheSpec
    from bmi_sdk.nn.export import export_with_manifest
    from bmi_sdk.nn.refine_data import RefineSpec
    from bmi_sdk.nn.train import TrainConfig, load_weights, train
    from bmi_sdk.runtime.model import DEFAULT_MODEL, Model

    refine = RefineSpec(decoder={"candidates": 12})
    config = TrainConfig(steps=2, batch_size=2, cache=CacheSpec(samples=2, crop_px=48, jitter_px=4), refine=refine,
                         init_from=str(DEFAULT_MODEL))
    ckpt = train(config, tmp_path / "run", tmp_path / "cache", save_every=1, progress=False)
    log = json.loads((tmp_path / "run" / "train_log.json").read_text())
    assert log["sessions"][-1]["to_step"] == 2
    net, saved = load_weights(ckpt)
    assert saved == config and net.config.extra_channels == _channels() and net.config.sigma_head
    manifest = export_with_manifest(net, tmp_path / "run" / "model.onnx", preset="tiny", lens="bmi_monocentric",
                                    training={}, classical_config=refine.classical_config().to_dict())
    m = verify_model(tmp_path / "run" / "model.onnx")
    assert manifest.exists() and m["decoder"] == "learned" and m["input_channels"] == 6 + _channels()
    assert m["output_names"] == ["aif", "depth_m", "depth_sigma_m"]
    model = Model(tmp_path / "run" / "model.onnx", tile_px=64, warmup=False)
    aif, depth, sigma = model.run(np.zeros((1, model.input_channels, 64, 64), np.float32))
    assert np.isfinite(depth).all() and (sigma > 0).all()
    # resuming a finished run trains nothing more and keeps the same checkpoint config
    train(config, tmp_path / "run", tmp_path / "cache", progress=False)
    assert json.loads((tmp_path / "run" / "train_log.json").read_text())["sessions"][-1]["from_step"] == 2


def test_a_sigma_head_only_run_changes_nothing_but_the_sigma_head(tmp_path):
    """``sigma_head_only`` recalibrates the shipped refinement's 1σ on new pairs: after two optimiser steps every
    tensor but the σ head's, the input standardisation included, is the shipped model's, and the σ head moved.
    Without a refinement to start from it is refused."""
    import onnx
    from onnx import numpy_helper

    from bmi_sdk.nn.data import CacheSpec
    from bmi_sdk.nn.refine_data import RefineSpec
    from bmi_sdk.nn.train import TrainConfig, load_weights, train
    from bmi_sdk.runtime.model import DEFAULT_MODEL

    shipped = DEFAULT_MODEL.parent / "learned.onnx"
    config = TrainConfig(steps=2, batch_size=2, lr=1e-2, cache=CacheSpec(samples=2, crop_px=48, jitter_px=4),
                         refine=RefineSpec(), init_from=str(shipped), sigma_head_only=True)
    net, _ = load_weights(train(config, tmp_path / "run", tmp_path / "cache", progress=False))
    source = {t.name.removeprefix("net."): numpy_helper.to_array(t) for t in onnx.load(str(shipped)).graph.initializer}
    state = net.state_dict()
    kept = [k for k in source if not k.startswith("sigma_out.")]
    assert "extra_mean" in kept and len(kept) > 90
    for name in kept:
        np.testing.assert_array_equal(state[name].numpy().reshape(source[name].shape), source[name], err_msg=name)
    assert any(not np.array_equal(state[k].numpy(), source[k]) for k in source if k.startswith("sigma_out."))
    with pytest.raises(ValueError, match="init_from"):
        TrainConfig(refine=RefineSpec(), sigma_head_only=True)


def test_a_sigma_head_only_run_without_a_refinement_to_start_from_is_refused_before_rendering(tmp_path):
    from bmi_sdk.runtime.model import DEFAULT_MODEL

    for extra, message in (([], "needs --decoder learned and --init-from"),
                           (["--init-from", str(DEFAULT_MODEL)], "is not a learned refinement")):
        run = subprocess.run([sys.executable, "-m", "bmi_sdk.cli", "train", "--decoder", "learned", "--sigma-head-only",
                              "--steps", "2", "--samples", "2", "--crop", "48", "--out", str(tmp_path / "run"),
                              "--cache", str(tmp_path / "cache"), *extra], capture_output=True, text=True)
        assert run.returncode == 1 and message in run.stderr, run.stderr[-2000:]
        assert not (tmp_path / "cache").exists() and not (tmp_path / "run").exists()


def test_manifests_keep_the_two_kinds_of_model_apart(tmp_path, identity_model, passthrough_model):
    from bmi_sdk.runtime.model import select_model

    for src in (identity_model, passthrough_model):
        shutil.copy(src, tmp_path / src.name)
        shutil.copy(src.with_name(src.stem + ".manifest.json"), tmp_path / (src.stem + ".manifest.json"))
    lens = json.loads(passthrough_model.with_name(passthrough_model.stem + ".manifest.json").read_text())["lens"]
    cnn = select_model(lens, "cnn", models_dir=tmp_path)
    learned = select_model(lens, "learned", models_dir=tmp_path)
    assert cnn.name == passthrough_model.name and learned.name == identity_model.name
    manifest_file = tmp_path / "identity.manifest.json"
    doc = json.loads(manifest_file.read_text())
    del doc["classical_config"]
    manifest_file.write_text(json.dumps(doc))
    with pytest.raises(ModelError, match="classical_config"):
        verify_model(tmp_path / "identity.onnx")
    doc["decoder"] = "magic"
    manifest_file.write_text(json.dumps(doc))
    with pytest.raises(ModelError, match="unknown decoder 'magic'"):
        verify_model(tmp_path / "identity.onnx")


def test_a_learned_model_with_another_candidate_grid_is_refused(tmp_path, identity_model):
    """The evidence channels depend on the decoder knobs; a manifest whose knobs give another channel count
    than the graph reads is refused before decoding, naming both counts."""
    from bmi_sdk.built_camera import BuiltCamera
    from bmi_sdk.runtime.learned import learned_decoder
    from bmi_sdk.runtime.model import Model

    shutil.copy(identity_model, tmp_path / "m.onnx")
    doc = json.loads(identity_model.with_name("identity.manifest.json").read_text())
    doc["file"] = "m.onnx"
    doc["classical_config"] = {**doc["classical_config"], "candidates": 48}
    (tmp_path / "m.manifest.json").write_text(json.dumps(doc))
    model = Model(tmp_path / "m.onnx", tile_px=64, warmup=False)
    with pytest.raises(ValueError, match=f"reads {6 + _channels()} channels"):
        learned_decoder(model, BuiltCamera(geometry=lens_geometry("bmi_monocentric")))


def test_a_job_without_a_decoder_runs_the_kind_of_model_it_is_given(identity_model, passthrough_model):
    from bmi_sdk.runtime.decoders import DEFAULT_DECODER, decoder_kind

    assert decoder_kind(None, identity_model) == "learned"
    assert decoder_kind(None, passthrough_model) == "cnn"
    assert decoder_kind(None) == DEFAULT_DECODER and decoder_kind("classical", identity_model) == "classical"
    with pytest.raises(ValueError, match="unknown decoder 'nope'"):
        decoder_kind("nope")


def test_the_shipped_networks_decode_with_the_classical_knobs_their_manifests_name(tmp_path, bmi):
    """`bmi infer` with no decoder named decodes with the packaged evidence network, `--decoder learned` with the
    packaged learned.onnx: each verified, each classical stage run with the knobs its manifest was trained with
    (the frame's noise profile and the tapered window model, not the classical decoder's defaults by chance),
    each writing depth with a positive 1σ inside the image circle."""
    from bmi_sdk.runtime.evidence import EVIDENCE_MODEL
    from bmi_sdk.runtime.model import LEARNED_MODEL

    bmi("simulate", "--procedural", 5, "--size", 96, "--field-deg", 20, "--psf-mode", "tensor", "--noise", 0.005,
        "--out", tmp_path / "f.dng")
    for decoder, model, extra in (("evidence", EVIDENCE_MODEL, ()), ("learned", LEARNED_MODEL, ("--decoder", "learned"))):
        manifest = verify_model(model)
        assert manifest["decoder"] == decoder and manifest["calibration_id"] is None
        bmi("infer", tmp_path / "f.dng", "--out", tmp_path / decoder, "--quiet", *extra)
        report = json.loads((tmp_path / decoder / "report.json").read_text())
        assert report["decoder"] == decoder and report["model"]["sha256"] == manifest["sha256"]
        depth, sigma = np.load(tmp_path / decoder / "depth.npy"), np.load(tmp_path / decoder / "depth_sigma.npy")
        ok = np.isfinite(depth)
        assert ok.mean() > 0.9 and np.all((depth[ok] > 0.1) & (depth[ok] < 100)) and np.all(sigma[ok] > 0)
        knobs = manifest["classical_config"]
        noise_source = {"profile": "profile", "estimate": "estimated"}[knobs["noise_model"]]
        assert report["decoder_stats"]["noise_source"] == noise_source
        assert report["decoder_stats"]["config"]["window_model"] == knobs["window_model"] == "tapered"


def test_classical_knobs_with_another_decoder_are_refused_not_ignored(tmp_path):
    run = subprocess.run([sys.executable, "-m", "bmi_sdk.cli", "infer", str(tmp_path / "f.dng"), "--out",
                          str(tmp_path / "o"), "--decoder", "learned", "--window-px", "48"], capture_output=True, text=True)
    assert run.returncode == 1 and "--window-px" in run.stderr and "--decoder classical" in run.stderr
    assert not (tmp_path / "o").exists()


def test_an_int8_copy_of_a_refinement_is_still_a_refinement(identity_model, tmp_path):
    """quantize_int8 wrote every int8 manifest with the end-to-end network's contract (6 inputs, two outputs): the
    runtime refused an int8 refinement. The copy keeps the channels, the σ output and the classical config."""
    from bmi_sdk.model_manifest import model_decoder, read_manifest
    from bmi_sdk.runtime import Model
    from bmi_sdk.runtime.quantize import quantize_int8

    source = read_manifest(identity_model)
    rng = np.random.default_rng(0)
    inputs = [rng.uniform(-1, 1, (1, source["input_channels"], 64, 64)).astype(np.float32) for _ in range(2)]
    copy = read_manifest(quantize_int8(identity_model, tmp_path / "identity_int8.onnx", inputs))
    for key in ("input_channels", "output_names", "classical_config", "receptive_field_px", "size_multiple"):
        assert copy[key] == source[key], key
    assert model_decoder(copy) == "learned" and len(copy["output_names"]) == 3
    model = Model(tmp_path / "identity_int8.onnx", tile_px=64, threads=1)
    assert model.decoder == "learned" and len(model.run(inputs[0])) == 3


def test_eval_refuses_options_its_decoders_would_ignore_and_no_tiles(capsys, exit_code):
    """`bmi eval --decoder learned --model M` ran the shipped refinement and never read M; a classical knob with
    another decoder was ignored too; `--tiles 0` printed an empty table. Each is refused before any tile renders:
    a bad option value exits 2 (a usage error, as argparse's), a missing model or a tile its decoder cannot read 1."""
    for argv, named, code in ((["--decoder", "learned", "--model", "nosuch.onnx"], "nosuch.onnx", 1),
                              (["--decoder", "cnn,learned", "--window-px", "48"], "--window-px", 2),
                              (["--decoder", "classical", "--tiles", "0"], "tiles", 2),
                              (["--decoder", "classical", "--tiles", "-3"], "tiles", 2),
                              (["--decoder", "classical", "--tile-px", "0"], "tile-px: 0", 2),
                              (["--decoder", "learned", "--tile-px", "32"], "64-px evidence window", 1),
                              (["--decoder", "cnn", "--tile-px", "90"], "multiple of 4", 2),
                              (["--decoder", "classical", "--seed", "-1"], "seed", 2)):
        assert exit_code(["eval", *argv]) == code, argv
        captured = capsys.readouterr()
        assert named in captured.err and "rendering" not in captured.err + captured.out


def test_the_classical_options_defaults_are_the_decoders():
    """``bmi infer``'s classical options default to ``ClassicalConfig``'s own knobs (read from the dataclass, not
    kept as literals), and every option names a field of it."""
    from bmi_sdk.cli.infer import CLASSICAL_FLAGS, classical_defaults

    defaults = classical_defaults()
    assert set(defaults) == set(CLASSICAL_FLAGS)
    assert defaults == {knob: getattr(ClassicalConfig(), knob) for knob in CLASSICAL_FLAGS}


def test_each_training_pair_draws_its_own_camera_within_the_papers_ranges():
    """``CacheSpec(camera_errors=f)``: sample i's camera is drawn from its own seeded stream (the same camera every
    time, another for another index or seed), every term within f × the paper's range; f = 0 is the nominal
    camera, and a fraction outside [0, 1] is refused."""
    from bmi_sdk.nn.data import CacheSpec
    from bmi_sdk.optics.perturb import PAPER_RANGES, Perturbation

    spec = CacheSpec(camera_errors=0.5, seed=3)
    cameras = [spec.camera(i).perturbation for i in range(200)]
    assert spec.camera(7).perturbation == cameras[7] != cameras[8]
    assert CacheSpec(camera_errors=0.5, seed=4).camera(7).perturbation != cameras[7]
    assert CacheSpec(seed=3).camera(7).perturbation == Perturbation() and CacheSpec().camera(0).is_nominal
    for name, bound in PAPER_RANGES.items():
        size = np.array([np.linalg.norm(np.atleast_1d(getattr(p, name))) for p in cameras])
        assert size.max() <= 0.5 * bound + 1e-12 and size.max() > 0.4 * bound  # the range is filled, not exceeded
    assert min(p.stray_light_fraction for p in cameras) >= 0  # glare adds light
    for bad in (-0.1, 1.5):
        with pytest.raises(ValueError, match="camera_errors"):
            CacheSpec(camera_errors=bad)


def test_a_pair_of_a_sampled_camera_is_decoded_with_that_cameras_exact_kernels():
    """The refinement's decode of a pair reads the kernels it was rendered with: the shared nominal decoder for a
    nominal cache; for a sampled camera, the exact kernels of the errors stored with the pair, centre calibrated
    (as ``render_sample`` renders it), with the refinement's decoder knobs."""
    from bmi_sdk.nn.data import CacheSpec
    from bmi_sdk.nn.refine_data import RefineSpec, ShardDecoder, pair_decoder

    decoding = ShardDecoder("bmi_monocentric", RefineSpec(decoder={"candidates": 12}))()
    assert pair_decoder(decoding, None) is decoding["decoder"]
    camera = CacheSpec(camera_errors=1.0).camera(2)
    decoder = pair_decoder(decoding, camera.perturbation.to_vector().astype(np.float32))
    psf_map = decoder.zones.psf_map
    assert psf_map.mode == "exact" and psf_map.centre_calibrated
    assert np.allclose(psf_map.perturbation.to_vector(), camera.perturbation.to_vector(), atol=1e-6)
    assert decoder.config == decoding["config"] and len(decoder.candidates) == len(decoding["decoder"].candidates)
