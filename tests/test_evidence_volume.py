"""The evidence decoder's parts against independent references: the volume's normalisation, cell targets,
the posterior, colour-guided upsampling (bilinear on a flat image, each side of a colour edge), the network's
untrained identity and its ONNX export."""

import numpy as np
import pytest

from bmi_sdk.decode.classical import upsample_grid
from bmi_sdk.decode.volume import CLIP_NATS, cell_colour, grid_targets, guided_upsample, posterior, volume_inputs


def _curves(rng, rows=6, cols=7, d=9):
    own = rng.uniform(0, 30, (rows, cols, d)).astype(np.float32)
    own -= own.min(axis=-1, keepdims=True)
    return own


def test_volume_inputs_takes_each_curves_minimum_and_clips():
    rng = np.random.default_rng(0)
    own = _curves(rng)
    pooled = own + 500.0  # a pooled curve's minimum is its neighbours' cost there
    pooled[0, 0, :] = np.nan
    colour = rng.normal(0, 1, own.shape[:2] + (3,)).astype(np.float32)
    vol, guide, valid = volume_inputs(pooled, own, colour)
    assert vol.shape == (2, own.shape[2], *own.shape[:2]) and guide.shape == (4, *own.shape[:2])
    assert not valid[0, 0] and valid.sum() == valid.size - 1
    assert np.all(vol[:, :, 0, 0] == 0) and guide[3, 0, 0] == 0 and np.all(guide[3][valid] == 1)
    np.testing.assert_allclose(vol[0].min(axis=0)[valid], 0.0)
    np.testing.assert_allclose(vol[0].transpose(1, 2, 0)[valid], np.minimum(own, CLIP_NATS)[valid], atol=1e-4)
    np.testing.assert_allclose(guide[:3].transpose(1, 2, 0)[valid].mean(axis=0), 0.0, atol=1e-5)


def test_volume_inputs_refuses_mismatched_shapes():
    own = np.zeros((4, 4, 5), np.float32)
    with pytest.raises(ValueError, match="R × C × D"):
        volume_inputs(own, own[:, :3], np.zeros((4, 4, 3)))


def test_grid_targets_are_each_cells_median_inverse_depth():
    stride = 16
    range_m = np.full((64, 80), 2.0, np.float32)
    range_m[:, 40:] = 5.0
    range_m[:4, :4] = np.nan  # window (0, 0)'s cell is [0, 8)²: 16 of its 64 pixels unknown
    t = grid_targets(range_m, stride, (5, 6))
    assert t[0, 0] == pytest.approx(0.5)
    assert t[2, 2] == pytest.approx(0.5)             # cell columns [24, 40): all 2 m
    assert t[2, 3] == pytest.approx(0.2)             # cell columns [40, 56): all 5 m
    assert t[2, 5] == pytest.approx(0.2)             # the last cell, [72, 80), clipped to the frame
    range_m[:, :] = np.nan
    assert np.isnan(grid_targets(range_m, stride, (5, 6))).all()


def test_posterior_matches_a_brute_force_integral():
    """The read against adaptive quadrature of the continuous posterior built independently: scipy's cubic Hermite
    spline of the logits over 1/d with numpy's gradient as its slopes, and a uniform prior on the candidate index
    (within each interval, density e^logit / the interval's width in 1/d), over the ``reach`` candidates either
    side of the mode, on uneven candidate spacings and logits from flat to sharp: with many points per interval
    to 1e-7, with the default 8 to a sixteenth of the widest spacing; the spread against the discrete
    posterior's std."""
    from scipy.integrate import quad
    from scipy.interpolate import CubicHermiteSpline

    rng = np.random.default_rng(1)
    x = np.sort(rng.uniform(0.1, 1.4, 7))[::-1]
    logits = rng.normal(0, 3, (7, 4, 5))
    logits[:, 0, 0] = 0.0                                 # flat
    logits[:, 2, 2] *= 10.0                               # sharp
    fine, std = posterior(logits, x, axis=0, reach=2, points=4096)
    coarse, _ = posterior(logits, x, axis=0, reach=2)
    p = np.exp(logits - logits.max(axis=0)) / np.exp(logits - logits.max(axis=0)).sum(axis=0)
    brute_mean = np.einsum("dij,d->ij", p, x)
    brute_var = np.einsum("dij,dij->ij", p, (x[:, None, None] - brute_mean) ** 2)
    np.testing.assert_allclose(std, np.sqrt(brute_var), rtol=1e-10)
    for i in range(4):
        for j in range(5):
            z = logits[:, i, j] - logits[:, i, j].max()
            curve = CubicHermiteSpline(x[::-1], z[::-1], np.gradient(z, x)[::-1])  # over increasing 1/d
            k = int(np.argmax(z))
            mass = moment = 0.0
            for a in range(max(0, k - 2), min(6, k + 2)):
                lo, hi, width = x[a + 1], x[a], x[a] - x[a + 1]
                mass += quad(lambda v: np.exp(curve(v)), lo, hi, epsabs=0, epsrel=1e-12)[0] / width
                moment += quad(lambda v: v * np.exp(curve(v)), lo, hi, epsabs=0, epsrel=1e-12)[0] / width
            assert fine[i, j] == pytest.approx(moment / mass, rel=1e-7)
            assert abs(coarse[i, j] - moment / mass) < np.abs(np.diff(x)).max() / 16
    # a flat posterior over every candidate reads the mean of 1/d along the index (the trapezoid rule over them)
    assert posterior(np.zeros(7), x, reach=7)[0] == pytest.approx(np.trapezoid(x) / 6, rel=1e-12)


def test_a_sharp_posterior_between_two_candidates_reads_between_them():
    """Two neighbouring candidates of equal logit far above the rest: the read is their midpoint in 1/d, where a
    read snapped to the candidates would sit on one of them; a small lead of one moves the read towards it."""
    x = np.linspace(1.4, 0.1, 27)
    logits = np.full(27, -200.0)
    logits[10] = logits[11] = 0.0
    assert posterior(logits, x)[0] == pytest.approx(0.5 * (x[10] + x[11]), rel=1e-9)
    logits[11] = -0.5
    read = posterior(logits, x)[0]
    assert 0.5 * (x[10] + x[11]) < read < x[10]
    with pytest.raises(ValueError, match="reach"):
        posterior(logits, x, reach=0)


def test_a_sharp_pooled_curve_whose_minimum_lies_between_candidates_reads_between_them():
    """A large surface's pooled curve: a parabola in 1/d, 17 and 67 nats above its vertex at the two candidates,
    its vertex a third of the way from candidate 12 to 13. Through the volume's clip and the shipped anchor's
    temperature, the read lies between the two candidates, near the vertex: the clip leaves the curve's shape
    about its minimum alone (at a clip of 60 nats both neighbours would clip alike and the read would sit on
    candidate 12)."""
    from bmi_sdk.runtime.evidence import EvidenceNetwork

    network = EvidenceNetwork()
    x = network.inv_depth_per_m.astype(np.float64)
    vertex = x[12] + (x[13] - x[12]) / 3
    curve = 150.0 * ((x - vertex) / (x[13] - x[12])) ** 2            # ΔNLL: 150 nats per spacing², one window
    pooled = curve[None, None, :].astype(np.float32)
    vol, guide, _ = volume_inputs(pooled, pooled, np.zeros((1, 1, 3), np.float32))
    read, _ = network.read(vol, guide)
    assert x[13] < read[0, 0] < x[12]
    assert abs(read[0, 0] - vertex) < 0.05 * abs(x[13] - x[12])
    assert CLIP_NATS * 0.058 > 20  # the clip is e^-20 below the mode at the shipped temperature


def test_the_network_reads_its_logits_as_the_numpy_posterior_does():
    """``nn.volume_net.posterior_torch`` (training, export) is ``decode.volume.posterior`` (the runtime) in float32."""
    torch = pytest.importorskip("torch")
    from bmi_sdk.nn.volume_net import posterior_torch

    rng = np.random.default_rng(4)
    x = np.sort(rng.uniform(0.1, 1.4, 11))[::-1].copy()
    logits = rng.normal(0, 4, (2, 11, 3, 6))
    logits[0, :, 0, 0] = 0.0
    got, got_std = posterior_torch(torch.as_tensor(logits, dtype=torch.float32), torch.as_tensor(x, dtype=torch.float32))
    for n in range(2):
        want, want_std = posterior(logits[n], x, axis=0)
        np.testing.assert_allclose(got[n].numpy(), want, rtol=2e-6, atol=1e-6)
        np.testing.assert_allclose(got_std[n].numpy(), want_std, rtol=1e-4, atol=1e-5)


def test_a_far_second_mode_widens_the_spread_but_does_not_pull_the_read():
    x = np.linspace(1.4, 0.1, 27)
    logits = np.full(27, -50.0)
    logits[3], logits[20] = 0.0, -0.5   # two surfaces, the nearer a little more probable
    read, std = posterior(logits, x)
    assert read == pytest.approx(x[3], abs=1e-6)
    assert std > 0.3 * abs(x[20] - x[3])


def test_guided_upsample_on_a_flat_image_is_the_decoders_bilinear_interpolation():
    rng = np.random.default_rng(2)
    stride, height, width = 16, 96, 128
    rows, cols = -(-height // stride) + 1, -(-width // stride) + 1
    inv = rng.uniform(0.1, 1.4, (rows, cols)).astype(np.float32)
    var = np.full_like(inv, 1e-4)
    flat = np.zeros((height, width, 3), np.float32)
    got, got_var = guided_upsample(inv, var, flat, stride, colour_sigma=0.3)
    want = upsample_grid(inv, stride, height, width)
    np.testing.assert_allclose(got, want, atol=2e-5)
    # the mixture's variance: the windows' own plus their spread about the pixel's mean
    assert np.all(got_var >= 1e-4 - 1e-9)


def test_guided_upsample_follows_each_side_of_a_colour_edge():
    stride, height, width = 16, 64, 64
    rows, cols = 5, 5
    log_rgb = np.zeros((height, width, 3), np.float32)
    log_rgb[:, 44:] = 2.0   # a colour edge at column 44, inside window 3's cell [40, 56)
    inv = np.where(np.arange(cols)[None, :] >= 3, 1.0, 0.25).astype(np.float32) * np.ones((rows, 1), np.float32)
    var = np.full((rows, cols), 1e-6, np.float32)
    got, got_var = guided_upsample(inv, var, log_rgb, stride, colour_sigma=0.2)
    cells = cell_colour(log_rgb, stride, (rows, cols))
    assert cells[0, 3, 0] == pytest.approx(1.5) and cells[0, 2, 0] == 0.0
    np.testing.assert_allclose(got[:, 44:60], 1.0, atol=1e-3)   # right of the edge: the right surface only
    np.testing.assert_allclose(got[:, 24:44], 0.25, atol=1e-3)  # left of it: the left surface only
    assert got_var[:, 44:60].max() < 1e-3
    bilinear = upsample_grid(inv, stride, height, width)
    assert np.abs(bilinear[:, 40:48] - got[:, 40:48]).max() > 0.3  # plain interpolation blurs the step


def test_guided_upsample_refuses_a_zero_colour_scale_and_keeps_nan_outside():
    inv = np.full((3, 3), np.nan, np.float32)
    got, _ = guided_upsample(inv, inv, np.zeros((32, 32, 3), np.float32), 16, 0.3)
    assert np.isnan(got).all()
    with pytest.raises(ValueError, match="colour_sigma"):
        guided_upsample(inv, inv, np.zeros((32, 32, 3), np.float32), 16, 0.0)


torch = pytest.importorskip("torch")


def test_untrained_network_returns_the_pooled_evidence_posterior():
    from bmi_sdk.nn.volume_net import VolumeDecoderGraph, VolumeNet, VolumeNetConfig

    rng = np.random.default_rng(3)
    d = 9
    own = _curves(rng, 8, 12, d)
    pooled = own * 2.0
    vol, guide, _ = volume_inputs(pooled, own, rng.normal(0, 1, (8, 12, 3)).astype(np.float32))
    x = np.linspace(1.4, 0.1, d)
    graph = VolumeDecoderGraph(VolumeNet(VolumeNetConfig(candidates=d)), x)
    with torch.no_grad():
        mean, _, logits = graph(torch.as_tensor(vol[None]), torch.as_tensor(guide[None]))
    np.testing.assert_allclose(logits[0].numpy(), -vol[0], atol=1e-5)
    want, _ = posterior(-vol[0].astype(np.float64), x, axis=0)
    np.testing.assert_allclose(mean[0].numpy(), want, rtol=1e-5)


def test_two_hot_target_has_the_target_as_its_expectation():
    from bmi_sdk.nn.volume_train import two_hot

    x = torch.tensor(np.linspace(1.4, 0.1, 11), dtype=torch.float32)
    t = torch.tensor([[[0.1, 0.37], [1.4, 0.9]]], dtype=torch.float32)
    w = two_hot(t, x)
    assert torch.allclose(w.sum(dim=1), torch.ones_like(t))
    assert torch.allclose((w * x.view(1, -1, 1, 1)).sum(dim=1), t, atol=1e-6)
    assert (w >= 0).all() and ((w > 0).sum(dim=1) <= 2).all()


def test_export_round_trips_through_onnxruntime(tmp_path):
    from bmi_sdk.nn.volume_net import VolumeNet, VolumeNetConfig
    from bmi_sdk.nn.volume_train import export

    ort = pytest.importorskip("onnxruntime")
    torch.manual_seed(0)
    net = VolumeNet(VolumeNetConfig(candidates=7, width=4))
    with torch.no_grad():  # a trained-looking head: the residual is not zero
        net.head.weight.normal_(0, 0.1)
    x = np.linspace(1.4, 0.1, 7)
    path = export(net, x, tmp_path / "ev.onnx")
    rng = np.random.default_rng(4)
    vol, guide, _ = volume_inputs(_curves(rng, 12, 20, 7) * 3, _curves(rng, 12, 20, 7), rng.normal(0, 1, (12, 20, 3)))
    out = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(
        None, {"volume": vol[None], "guide": guide[None]})
    with torch.no_grad():
        logits = net(torch.as_tensor(vol[None]), torch.as_tensor(guide[None]))[0].numpy()
    np.testing.assert_allclose(out[2][0], logits, atol=1e-4)
    assert not np.allclose(logits, -vol[0], atol=1e-3)


def test_a_zero_residual_is_left_out_of_the_exported_graph_with_the_same_logits(tmp_path):
    """A network whose residual is exactly zero (only its scalars fitted) exports as the anchor alone: no
    convolution in the graph, and the logits the whole hourglass gives."""
    import onnx

    from bmi_sdk.nn.volume_net import VolumeNet, VolumeNetConfig
    from bmi_sdk.nn.volume_train import export

    ort = pytest.importorskip("onnxruntime")
    torch.manual_seed(2)
    net = VolumeNet(VolumeNetConfig(candidates=7, width=4))
    with torch.no_grad():
        net.log_anchor.fill_(-1.3)
    assert net.residual_is_zero()
    rng = np.random.default_rng(6)
    vol, guide, _ = volume_inputs(_curves(rng, 12, 20, 7) * 3, _curves(rng, 12, 20, 7), rng.normal(0, 1, (12, 20, 3)))
    with torch.no_grad():
        whole = net(torch.as_tensor(vol[None]), torch.as_tensor(guide[None]))[0].numpy()
    path = export(net, np.linspace(1.4, 0.1, 7), tmp_path / "ev.onnx")
    assert not [n for n in onnx.load(str(path)).graph.node if n.op_type == "Conv"]
    out = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(None, {"volume": vol[None]})
    np.testing.assert_allclose(out[2][0], whole, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(whole, -np.exp(-1.3) * vol[0], rtol=1e-5, atol=1e-5)


def test_the_networks_reach_across_the_grid_is_within_the_runtimes_band_halo():
    """One window's volume changes the logits no further than ``HALO_ROWS`` windows away, so reading a frame's grid
    in bands (``runtime.evidence``) gives what reading it whole would."""
    from bmi_sdk.nn.volume_net import VolumeNet, VolumeNetConfig
    from bmi_sdk.runtime.evidence import HALO_ROWS

    torch.manual_seed(1)
    net = VolumeNet(VolumeNetConfig(candidates=5, width=4)).eval()
    with torch.no_grad():
        net.head.weight.normal_(0, 0.3)
        vol = torch.zeros(1, 2, 5, 96, 8)
        guide = torch.zeros(1, 4, 96, 8)
        guide[:, 3] = 1.0
        base = net(vol, guide)
        vol[0, :, :, 48, 4] = 20.0
        moved = (net(vol, guide) - base).abs().amax(dim=(0, 1, 3))
    rows = torch.nonzero(moved > 1e-6).flatten()
    assert len(rows) > 1 and int((rows - 48).abs().max()) <= HALO_ROWS


def test_training_pairs_are_made_once_resume_and_refuse_another_spec(tmp_path):
    """One pair through the real chain (render, raw frame, classical decode): its volume, guide and cell targets on
    the decoder's window grid, the same shard kept on a second build, and another spec refused in that folder."""
    from bmi_sdk.nn.volume_data import VolumePairs, VolumeSpec, build_pairs

    spec = VolumeSpec(pairs=1, crop_px=128, seed=5, scene_scale_max=2.0)
    build_pairs(tmp_path, spec, progress=False)
    shard = tmp_path / "shard_00000.npz"
    stamp = shard.stat().st_mtime_ns
    build_pairs(tmp_path, spec, progress=False)
    assert shard.stat().st_mtime_ns == stamp
    with pytest.raises(ValueError, match="another spec"):
        build_pairs(tmp_path, VolumeSpec(pairs=1, crop_px=128, seed=6, scene_scale_max=2.0), progress=False)
    pairs = VolumePairs([tmp_path])
    a = pairs.arrays
    d = len(pairs.inv_depth_per_m)
    assert a["volume"].shape == (1, 2, d, 9, 9) and a["guide"].shape == (1, 4, 9, 9) and a["target"].shape == (1, 9, 9)
    ok = np.isfinite(a["target"][0])
    assert ok.mean() > 0.5 and np.all((a["target"][0][ok] > 0.09) & (a["target"][0][ok] < 1.5))
    assert np.all(a["volume"][0][:, :, a["guide"][0, 3] > 0].min(axis=1) == 0)  # each valid curve's minimum is 0
    batch = pairs.batch(np.random.default_rng(0), 3, crop=8)
    assert batch["volume"].shape == (3, 2, d, 8, 8) and batch["target"].shape == (3, 8, 8)


def test_cells_past_the_frames_last_pixel_are_empty_not_out_of_bounds():
    """A frame whose size is no multiple of the stride (a full frame's 4500 rows over 16) has grid cells past its
    last pixel: they hold no pixel, and guided upsampling still reads every pixel."""
    from bmi_sdk.decode.classical import ClassicalConfig, window_grid_shape

    height, width, stride = 100, 104, 16
    rows, cols = window_grid_shape(ClassicalConfig(), height, width)
    log_rgb = np.zeros((height, width, 3), np.float32)
    cells = cell_colour(log_rgb, stride, (rows, cols))
    assert cells.shape == (rows, cols, 3) and np.all(cells == 0)
    assert np.isnan(grid_targets(np.full((height, width), 2.0), stride, (rows, cols))[-1]).all()
    inv = np.full((rows, cols), 0.5, np.float32)
    got, _ = guided_upsample(inv, np.full_like(inv, 1e-4), log_rgb, stride, 0.3)
    np.testing.assert_allclose(got, 0.5, rtol=1e-6)
