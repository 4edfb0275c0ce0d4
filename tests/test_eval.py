"""`bmi eval` (bmi_sdk.nn.evaluate, bmi_sdk.cli.eval): decoders through the registry, tiles as raw frames, scene
scales, the breakdown by range band, depth edge and signal (bmi_sdk.nn.eval_strata) and the sampled built cameras."""

import math

import numpy as np
import pytest

from bmi_sdk.nn import evaluate
from bmi_sdk.nn.eval_strata import EDGE_BANDS, SIGNAL_BANDS, StrataSums, depth_edges, edge_distance_px
from bmi_sdk.runtime.decoders import DECODERS, DEFAULT_DECODER, DecodedFrame
from bmi_sdk.sensor import NoiseProfile

# -- breakdown on hand-computable maps -----------------------------------------------------------------------------


def test_a_depth_edge_is_a_log_range_step_above_the_threshold_between_neighbours():
    step = np.array([[1.0, 1.0, 2.0, 2.0]])  # |Δ log| = log 2 between columns 1 and 2: both are edge pixels
    assert depth_edges(step).tolist() == [[False, True, True, False]]
    slope = np.array([[1.0, 1.05, 1.05 ** 2, 1.05 ** 3]])  # a slanted surface: log 1.05 ≈ 0.049 per pixel, no edge
    assert not depth_edges(slope).any()
    column = step.T  # along rows as well
    assert depth_edges(column).ravel().tolist() == [False, True, True, False]
    with_unknown = np.array([[1.0, np.nan, 5.0]])  # no edge against an unknown range
    assert not depth_edges(with_unknown).any()


def test_edge_distance_is_the_euclidean_distance_to_the_nearest_edge_pixel():
    wall = np.ones((5, 6))
    wall[:, 3:] = 3.0  # a vertical step between columns 2 and 3
    expected = np.abs(np.arange(6) - np.where(np.arange(6) <= 2, 2, 3))[None].repeat(5, 0)
    np.testing.assert_array_equal(edge_distance_px(wall), expected)
    corner = np.ones((4, 4))
    corner[0, 0] = 5.0  # edge pixels (0,0), (0,1), (1,0): (2,2) is √(1² + 2²) from the nearest, (0,1) or (1,0)
    assert edge_distance_px(corner)[2, 2] == pytest.approx(math.sqrt(5))
    assert np.isinf(edge_distance_px(np.full((3, 3), 2.0))).all()


def test_strata_sums_pool_pixels_into_range_edge_and_signal_bands_with_hand_computed_numbers():
    true = np.array([[1.0, 3.0, 5.0, 8.0, 2.0]])
    pred = np.array([[1.1, 3.0, 4.0, 8.0, np.nan]])  # the last pixel has no read: not scored
    sigma = np.array([[0.05, 0.5, 0.5, 1.0, 1.0]])
    edge = np.array([[0.0, 1.0, 9.0, 20.0, 0.0]])
    signal = np.array([[0.01, 0.02, 0.049, 0.5, 0.0]])  # a band holds its lower bound, not its upper
    valid = np.ones_like(true, bool)
    sums = StrataSums()
    sums.add(pred, true, valid, sigma, edge, signal)
    out = sums.summary()
    rng = out["by_range"]
    # |error| / range: 0.1, 0, 0.2, 0 (sum 0.3); 5/4 = 1.25 is not < 1.25, so the 4–6 m pixel fails δ1
    assert [rng[b]["absrel"] for b in rng] == pytest.approx([0.1, 0.0, 0.2, 0.0])
    assert [rng[b]["pixel_share"] for b in rng] == pytest.approx([0.25] * 4)
    assert [rng[b]["error_share"] for b in rng] == pytest.approx([1 / 3, 0.0, 2 / 3, 0.0])
    assert [rng[b]["delta1"] for b in rng] == [1.0, 1.0, 0.0, 1.0]
    assert rng["4–6 m"]["rmse_m"] == pytest.approx(1.0)
    near, far = (out["by_edge"][b] for b in EDGE_BANDS)  # distances 0, 1 | 9, 20 against 8 px
    assert near["absrel"] == pytest.approx(0.05) and far["absrel"] == pytest.approx(0.1)
    assert near["pixel_share"] == far["pixel_share"] == 0.5
    dark, dim, bright = (out["by_signal"][b] for b in SIGNAL_BANDS)  # 0.01 | 0.02, 0.049 | 0.5
    assert [dark["pixel_share"], dim["pixel_share"], bright["pixel_share"]] == pytest.approx([0.25, 0.5, 0.25])
    assert [dark["absrel"], dim["absrel"], bright["absrel"]] == pytest.approx([0.1, 0.1, 0.0])
    assert [dark["error_share"], dim["error_share"], bright["error_share"]] == pytest.approx([1 / 3, 2 / 3, 0.0])
    # σ/read: 0.045 (confident), 0.167, 0.125, 0.125; z = 2, 0, −2, 0
    assert out["confident_coverage"] == pytest.approx(0.25)
    assert out["confident_absrel"] == pytest.approx(0.1)
    assert out["sigma_z_std"] == pytest.approx(math.sqrt(2)) and out["sigma_z_rms"] == pytest.approx(math.sqrt(2))
    assert out["sigma_z_within_1"] == pytest.approx(0.5)  # |z| = 2, 0, 2, 0
    # a second tile pools: the 4–6 m band now holds two pixels
    sums.add(np.array([[5.0]]), np.array([[5.0]]), np.array([[True]]), None, np.array([[3.0]]), np.array([[0.3]]))
    assert sums.summary()["by_range"]["4–6 m"]["absrel"] == pytest.approx(0.1)


def test_sigma_within_one_tells_a_wide_sigma_with_wrong_tails_from_an_honest_one():
    """An honest Gaussian σ holds 68.3 % of the errors within 1σ and z std 1. A σ five times too wide beside 2 % of
    pixels read 35 true σ off also has z std near 1, but nearly every pixel within 1σ: the share tells them apart."""
    from bmi_sdk.nn.eval_strata import HONEST_WITHIN_1

    rng = np.random.default_rng(5)
    true = np.full((400, 400), 4.0)
    sigma = np.full(true.shape, 0.2)
    error = rng.normal(0.0, 0.2, true.shape)
    ones, zeros = np.ones(true.shape, bool), np.zeros(true.shape)
    honest, faked = StrataSums(), StrataSums()
    honest.add(true + error, true, ones, sigma, zeros, zeros + 0.5)
    tails = rng.random(true.shape) < 0.02
    faked.add(true + np.where(tails, 35 * 0.2, error), true, ones, 5 * sigma, zeros, zeros + 0.5)
    h, f = honest.summary(), faked.summary()
    assert h["sigma_z_std"] == pytest.approx(1.0, abs=0.01) and h["sigma_z_within_1"] == pytest.approx(HONEST_WITHIN_1,
                                                                                                         abs=0.005)
    assert f["sigma_z_std"] == pytest.approx(1.0, abs=0.1) and f["sigma_z_within_1"] > 0.95


def test_a_band_without_pixels_reads_nan_and_a_decoder_without_sigma_reports_no_coverage():
    sums = StrataSums()
    sums.add(np.array([[1.0]]), np.array([[1.0]]), np.array([[True]]), None, np.array([[0.0]]), np.array([[0.1]]))
    out = sums.summary()
    assert math.isnan(out["by_range"]["> 6 m"]["absrel"]) and out["by_range"]["> 6 m"]["pixel_share"] == 0
    assert math.isnan(out["by_signal"]["signal < 0.02"]["absrel"])
    assert "confident_coverage" not in out and "sigma_z_std" not in out and "sigma_z_within_1" not in out


# -- tiles as frames, decoders from the registry -------------------------------------------------------------------


class _FlatDecoder:
    """A registered decoder of its own kind: the demosaiced frame as AiF, 2 m everywhere, σ 0.1 m. Adding it to the
    registry is all it takes for bmi eval to score it; it records the frames and the camera it was given."""

    kind = "flat_test"
    title = "flat test decoder"
    model_kind = None
    takes_config = False
    takes_texture_exponent = False
    frames: list = []

    def __init__(self, camera, model, config, options):
        self.camera, self.model = camera, None

    def decode(self, frame, progress: bool = False) -> DecodedFrame:
        from bmi_sdk.model_io import raw_to_rgb, window_cfa

        type(self).frames.append((frame, self.camera))
        rgb = raw_to_rgb(frame.data, frame.black_level_dn, frame.white_level_dn,
                         window_cfa(frame.cfa, frame.roi.y_px, frame.roi.x_px))
        shape = frame.data.shape
        return DecodedFrame(rgb, np.full(shape, 2.0, np.float32), np.ones(shape, bool),
                            np.full(shape, 0.1, np.float32), {})

    def head(self) -> dict:
        return {"decoder": self.kind, "camera": self.camera.to_dict()}


@pytest.fixture
def flat_decoder(monkeypatch):
    monkeypatch.setitem(DECODERS, _FlatDecoder.kind, _FlatDecoder)
    monkeypatch.setattr(_FlatDecoder, "frames", [])
    return _FlatDecoder


def test_a_tile_reaches_the_decoder_as_the_raw_frame_of_its_roi(flat_decoder):
    from bmi_sdk.runtime.pipeline import check_decodable

    bench = evaluate.Benchmark(tiles=1, tile_px=32, scene_scale=4.0)
    rows = evaluate.run_benchmark(None, bench, ["noise_0.02"], progress=False, decoders=(flat_decoder.kind,))
    assert [(r["condition"], r["decoder"], r["region"]) for r in rows] == [
        ("noise_0.02", "flat_test", "centre"), ("noise_0.02", "flat_test", "edge")]
    assert all(r["scene_scale"] == 4.0 and set(r["by_range"]) and set(r["by_edge"]) == set(EDGE_BANDS)
               and set(r["by_signal"]) == set(SIGNAL_BANDS) for r in rows)
    assert all(r["confident_coverage"] == 1.0 for r in rows)  # σ 0.1 m at a read of 2 m: σ/depth 0.05
    windows = bench.windows()
    for (frame, camera), (_, _, row0, col0) in zip(flat_decoder.frames, windows):
        check_decodable(frame, camera.lens_name, "the decoder's camera has", "the test decoder")
        m = bench.margin_px
        assert (frame.roi.y_px, frame.roi.x_px, frame.data.shape) == (row0 + m, col0 + m, (32, 32))
        assert frame.noise_profile == NoiseProfile.additive(0.02)
        assert camera.kernel_mode == "tensor" and camera.is_nominal


def test_a_hardware_condition_reads_with_the_design_and_the_built_cameras_kernels(flat_decoder, monkeypatch):
    """decenter renders with the built lens's exact kernels (optical centre calibrated); the decoder reads them once
    with the design camera and once, as ``<kind>_calibrated``, with a camera whose kernels are the render's; a noise
    condition has no calibrated row."""
    monkeypatch.setattr(evaluate, "REGIONS", {"centre": evaluate.REGIONS["centre"]})  # one tile: ~7 s of traces
    bench = evaluate.Benchmark(tiles=1, tile_px=16)
    rows = evaluate.run_benchmark(None, bench, ["standard", "decenter_10um"], progress=False,
                                  decoders=(flat_decoder.kind,))
    assert [(r["condition"], r["decoder"]) for r in rows] == [
        ("standard", "flat_test"), ("decenter_10um", "flat_test"), ("decenter_10um", "flat_test_calibrated")]
    cameras = [camera for _, camera in flat_decoder.frames]
    assert cameras[1].is_nominal and cameras[1].kernel_mode == "tensor"
    built = cameras[2]
    assert built.perturbation == evaluate.EXACT["decenter_10um"]
    assert built.kernel_mode == "exact" and built.centre_calibrated
    assert built.psf_map().mode == "exact" and built.psf_map().centre_calibrated
    assert rows[1]["psnr_db"] == rows[2]["psnr_db"]  # one render read twice; its AiF is the demosaiced frame


def test_every_packaged_decoder_kind_scores_through_the_registry(passthrough_model):
    """cnn (here a pass-through model given with --model's path) and classical on two 64-px tiles at the paper's
    scale: rows named by kind, a σ row only for the decoder that reports one."""
    bench = evaluate.Benchmark(tiles=1, tile_px=64, scene_scale=evaluate.PAPER_SCENE_SCALE)
    rows = evaluate.run_benchmark(passthrough_model, bench, ["standard"], progress=False,
                                  decoders=("cnn", "classical"))
    by_name = {(r["decoder"], r["region"]): r for r in rows}
    assert set(by_name) == {(d, region) for d in ("cnn", "classical") for region in ("centre", "edge")}
    assert "sigma_z_std" in by_name["classical", "edge"] and "sigma_z_std" not in by_name["cnn", "edge"]
    assert all(0.0 <= r["absrel"] < 5.0 for r in rows)


def test_a_model_for_a_decoder_not_run_and_a_tile_without_an_evidence_window_are_refused(passthrough_model):
    with pytest.raises(ValueError, match="model of the cnn decoder"):
        evaluate.run_benchmark(passthrough_model, evaluate.Benchmark(tiles=1, tile_px=64), ["standard"],
                               progress=False, decoders=("classical",))
    with pytest.raises(ValueError, match="no 64-px evidence window of the classical decoder"):
        evaluate.run_benchmark(None, evaluate.Benchmark(tiles=1, tile_px=32), ["standard"], progress=False,
                               decoders=("classical",))


def test_the_benchmark_camera_keeps_the_render_kernel_model_in_its_identity():
    from bmi_sdk.built_camera import BuiltCamera

    design = evaluate.BenchmarkCamera("bmi_monocentric")
    assert design.psf_map().mode == "tensor" and BuiltCamera("bmi_monocentric").psf_map().mode == "exact"
    assert design.sha256() != BuiltCamera("bmi_monocentric").sha256()
    assert design.sha256() != evaluate.BenchmarkCamera("bmi_monocentric", kernel_mode="exact").sha256()


# -- the command line ----------------------------------------------------------------------------------------------


def _args(*argv):
    import argparse

    from bmi_sdk.cli import eval as cli_eval

    parser = argparse.ArgumentParser()
    cli_eval.register(parser.add_subparsers())
    return parser.parse_args(["eval", *argv])


def test_eval_defaults_to_the_default_decoder_and_the_papers_scene_scale():
    from bmi_sdk.cli.eval import _scales

    args = _args()
    assert args.decoder is None and args.scene_scale == evaluate.PAPER_SCENE_SCALE == 4.0
    assert _scales(args) == [4.0] and _scales(_args("--scales", "1,4,16")) == [1.0, 4.0, 16.0]
    assert DEFAULT_DECODER in DECODERS
    for bad in ("0.5", "x"):
        with pytest.raises(ValueError, match="--scales"):
            _scales(_args("--scales", bad))


def test_eval_refuses_tiles_and_scene_scales_that_would_not_fit_in_memory_before_drawing_anything(capsys, tmp_path):
    from bmi_sdk.cli import main

    record = tmp_path / "r.json"
    for argv, named in ((["--tiles", "99999999999"], "--tiles/--tile-px 99999999999/192 needs about"),
                        (["--tile-px", "100000"], "--tiles/--tile-px 12/100000 needs about"),
                        (["--scales", "1,4,1e9"], "--scales 1,4,1e9 needs about"),
                        (["--scene-scale", "inf"], "--scene-scale inf needs about")):
        assert main(["eval", "--decoder", "classical", "--conditions", "standard", *argv, "--json", str(record)]) == 2
        captured = capsys.readouterr()
        assert named in captured.err and "GiB limit" in captured.err
        assert "rendering" not in captured.err + captured.out and not record.exists()
    # the bytes a run holds grow with the tiles and the tile's area; a scene with the square of its scale
    small, more = evaluate.Benchmark(tiles=2), evaluate.Benchmark(tiles=4)
    assert more.renders_bytes() == pytest.approx(2 * small.renders_bytes())
    assert evaluate.Benchmark(scene_scale=8.0).scene_bytes() == pytest.approx(4 * small.scene_bytes() * 16)


def test_eval_refuses_an_unknown_decoder_and_no_cameras(capsys, exit_code):
    for argv, named in ((["--decoder", "classical", "--decoder", "nosuch"], "--decoder nosuch: unknown decoder"),
                        (["--decoder", "classical", "--cameras", "0"], "--cameras: 0 is outside"),
                        (["--decoder", "classical", "--tile-px", "0"], "--tile-px: 0 is outside"),
                        (["--decoder", "classical", "--tile-px", "90"],
                         "--tile-px: 90 is outside [4, inf) px, a multiple of 4"),
                        (["--decoder", "classical", "--threads", "-1"], "--threads: -1 is outside"),
                        (["--decoder", "classical", "--seed", "nan"], "--seed: 'nan' is not a whole number"),
                        (["--decoder", "classical", "--scene-scale", "0.5"], "--scene-scale")):
        assert exit_code(["eval", *argv]) == 2  # a bad option value is a usage error, as argparse's
        captured = capsys.readouterr()
        assert named in captured.err and "rendering" not in captured.err + captured.out


def test_the_tables_name_the_scale_and_hold_every_stratum():
    from bmi_sdk.cli.eval import eval_table, strata_table

    sums = StrataSums()
    sums.add(np.array([[1.0, 3.0]]), np.array([[1.0, 3.3]]), np.ones((1, 2), bool), None, np.array([[0.0, 10.0]]),
             np.array([[0.01, 0.2]]))
    row = {"condition": "standard", "decoder": "classical", "region": "centre", "scene_scale": 1.0, "absrel": 0.05,
           **sums.summary()}
    bench = evaluate.Benchmark(tiles=1, tile_px=64)
    head = eval_table([row], bench)
    assert head["rows"][0][:4] == ["×1 (stress test)", "standard", "classical", "centre"]
    strata = strata_table([row], bench)
    assert [r[4] for r in strata["rows"]] == [*row["by_range"], *row["by_edge"], *row["by_signal"]]


# -- built cameras drawn from the error prior, read with their fitted calibration ---------------------------------


@pytest.mark.slow
def test_built_camera_sampled_reads_each_camera_with_its_fitted_calibration(flat_decoder, monkeypatch):
    """One camera (capture and fit: ~35 s idle) on one 16-px tile: the decoder's calibrated camera carries the
    fitted errors, close to but not the true ones the tile was rendered with."""
    from bmi_sdk.nn.sampled_cameras import sampled_cameras

    monkeypatch.setattr(evaluate, "REGIONS", {"centre": evaluate.REGIONS["centre"]})
    bench = evaluate.Benchmark(tiles=1, tile_px=16)
    rows = evaluate.run_benchmark(None, bench, [evaluate.SAMPLED], progress=False, decoders=(flat_decoder.kind,),
                                  cameras=1)
    assert [(r["decoder"], r["cameras"]) for r in rows] == [("flat_test", 1), ("flat_test_calibrated", 1)]
    (sampled,) = sampled_cameras(1, bench.seed, bench.lens)
    fitted_camera = flat_decoder.frames[-1][1]
    assert fitted_camera.perturbation == sampled.fitted != sampled.truth
    truth, fitted = sampled.truth.to_vector(), sampled.fitted.to_vector()
    assert np.abs(fitted[3:5] - truth[3:5]).max() < 2.0  # decenter (µm) recovered to well within its 10-µm range


def test_a_rows_absrel_carries_the_standard_error_of_its_mean_over_the_tiles():
    sums = StrataSums()
    sums.add(np.array([[1.0]]), np.array([[1.0]]), np.array([[True]]), None, np.array([[0.0]]), np.array([[0.1]]))
    tiles = [{"absrel": 0.1}, {"absrel": 0.3}, {"absrel": float("nan")}]  # a tile without valid pixels is left out
    bench = evaluate.Benchmark(tiles=3, tile_px=64)
    (row,) = evaluate.region_rows({"centre": (tiles, sums)}, "standard", "classical", bench)
    assert row["absrel"] == pytest.approx(0.2)
    assert row["absrel_se"] == pytest.approx(0.1)  # sample std 0.1414 over √2 tiles
    assert math.isnan(evaluate.tile_standard_error([0.2]))
    assert math.isnan(evaluate.tile_standard_error([]))


def test_paired_differences_subtract_the_reference_tile_by_tile_and_cancel_the_spread_between_tiles():
    from bmi_sdk.cli.eval import paired_table
    from bmi_sdk.nn.eval_paired import paired_differences

    # tiles of very different difficulty; the candidate reads each 0.01 (±0.001) better than the reference
    ref = [0.05, 0.30, 0.12, float("nan")]
    new = [0.039, 0.291, 0.11, 0.2]  # the 4th tile has no reference read: left out of the pair
    base = {"scene_scale": 4.0, "condition": "standard", "region": "edge"}
    rows = [base | {"decoder": "evidence", "tile_absrel": ref}, base | {"decoder": "trial", "tile_absrel": new},
            base | {"decoder": "trial", "tile_absrel": new, "region": "centre"}]  # no reference row: no pair
    (pair,) = paired_differences(rows, "evidence")
    diffs = np.array([-0.011, -0.009, -0.01])
    assert pair["decoder"] == "trial" and pair["reference"] == "evidence" and pair["tiles"] == 3
    assert pair["absrel_diff"] == pytest.approx(-0.01)
    assert pair["absrel_diff_se"] == pytest.approx(diffs.std(ddof=1) / math.sqrt(3))  # 0.00058
    assert pair["better_share"] == 1.0
    # the unpaired rows' own standard errors would not resolve the 0.01
    assert evaluate.tile_standard_error(ref[:3]) > 0.07 > 7 * pair["absrel_diff_se"]
    table = paired_table([pair], evaluate.Benchmark(tiles=4, tile_px=64))
    assert table["rows"] == [["×4 (paper)", "standard", "edge", "trial", "evidence", 3, -0.01, 0.0006, 1.0]]
    with pytest.raises(ValueError, match="same tiles"):
        paired_differences([rows[0], rows[1] | {"tile_absrel": new[:2]}], "evidence")


def test_eval_refuses_a_texture_exponent_no_decoder_run_takes_and_an_unknown_one(capsys):
    from bmi_sdk.cli import main
    from bmi_sdk.nn.evaluate import Benchmark

    assert main(["eval", "--decoder", "learned,cnn", "--texture-exponent", "profiled", "--conditions", "standard"]) == 2
    captured = capsys.readouterr()
    assert "--texture-exponent profiled" in captured.err and "rendering" not in captured.err + captured.out
    with pytest.raises(SystemExit):
        main(["eval", "--decoder", "classical", "--texture-exponent", "natural"])
    with pytest.raises(ValueError, match="texture_exponent must be one of prior, profiled"):
        Benchmark(texture_exponent="natural")


def test_eval_refuses_a_reference_that_is_not_a_decoder_run(capsys):
    from bmi_sdk.cli import main

    assert main(["eval", "--decoder", "classical", "--reference", "evidence", "--conditions", "standard"]) == 2
    captured = capsys.readouterr()
    assert "--reference evidence" in captured.err and "rendering" not in captured.err + captured.out


def test_natural_textures_draw_the_standard_tiles_with_scattered_texture_exponents():
    """The condition's tiles hold the same layout and ranges as ``standard``'s, with other textures."""
    assert evaluate.NATURAL in evaluate.known_conditions()
    plain = evaluate.Benchmark(tiles=1, tile_px=64, scene_scale=4.0)
    natural = evaluate.Benchmark(tiles=1, tile_px=64, scene_scale=4.0,
                                 texture_spread=evaluate.NATURAL_TEXTURE_SPREAD)
    (rgb_p, range_p), (rgb_n, range_n) = plain.scene("edge", 0), natural.scene("edge", 0)
    np.testing.assert_array_equal(range_p, range_n)
    assert not np.array_equal(rgb_p, rgb_n)
    for bad in (-0.1, 2.0, math.nan):
        with pytest.raises(ValueError, match="texture_spread"):
            evaluate.Benchmark(texture_spread=bad)
