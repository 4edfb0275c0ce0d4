"""The per-pixel choice among the windows' reads (``decode.pixel_select``): its Sobel gradient against scipy's, its
candidates against a direct reading of the grids, the mixture at a zero scorer against the plain mean, the blocks it
leaves alone, the manifest's checks, and a rendered near object over a far wall."""

import json
import shutil

import numpy as np
import pytest
from scipy import ndimage

from bmi_sdk.decode.pixel_select import (
    FEATURES,
    Grids,
    PixelSelect,
    candidate_features,
    disagreeing_blocks,
    gradient_at,
    select_depth,
)
from bmi_sdk.model_manifest import ModelError
from bmi_sdk.runtime.evidence import EVIDENCE_MODEL, EvidenceNetwork

STRIDE = 16


def _grids(rng, rows=6, cols=7, height=80, width=96, step_col=None) -> Grids:
    """Random grids over an 80 × 96 frame (a 6 × 7 window grid at stride 16); with ``step_col`` the support reads
    jump from 0.2 to 1 m⁻¹ at that grid column (two surfaces) and are uniform on each side."""
    inv = rng.uniform(0.2, 1.0, (rows, cols)).astype(np.float32)
    if step_col is not None:
        inv = np.where(np.arange(cols)[None, :] < step_col, 0.2, 1.0) * np.ones((rows, 1))
        inv = inv.astype(np.float32)
    rgb = rng.uniform(0.0, 1.0, (height, width, 3)).astype(np.float32)
    log_rgb = np.log(np.maximum(rgb, 1e-3))
    def draw(kind, *args):
        return getattr(rng, kind)(*args).astype(np.float32)

    colours = (rows, cols, 3)
    grid = (rows, cols)
    return Grids(inv, draw("uniform", 1e-4, 1e-2, grid), draw("uniform", 0.2, 1.0, grid),
                 draw("uniform", 1e-4, 1e-2, grid), draw("normal", 0, 1, colours), draw("normal", 0, 1, colours),
                 draw("normal", 0, 1, colours), draw("uniform", 0, 1, grid), log_rgb, rgb, 0.01, STRIDE)


def _zero_scorer() -> PixelSelect:
    n = len(FEATURES)
    return PixelSelect(np.zeros(n, np.float32), np.ones(n, np.float32),
                       ((np.ones((n, 4), np.float32), np.zeros(4, np.float32)),
                        (np.zeros((4, 1), np.float32), np.zeros(1, np.float32))), float(np.log(1.1)))


def test_the_gradient_at_pixels_is_scipys_sobel_magnitude_edges_included():
    rgb = np.random.default_rng(0).uniform(-0.05, 1.0, size=(9, 11, 3)).astype(np.float32)  # some below black
    image = np.log(np.maximum(rgb, 0.0) + 0.01)
    want = np.sqrt(sum(ndimage.sobel(image[..., c].astype(np.float64), a) ** 2 for c in range(3) for a in (0, 1)))
    rows, cols = np.mgrid[0:9, 0:11]
    got = gradient_at(rgb, rows.ravel(), cols.ravel(), 0.01).reshape(9, 11)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)


def test_a_pixels_candidates_are_the_4x4_windows_around_it_read_directly_from_the_grids():
    """Pixel (37, 50) lies in block (2, 3): between windows 2 and 3 down, 3 and 4 across, 7/32 and 3/32 of a stride
    past windows 2 and 3 (window k's centre at k·16 − ½). Its candidates are windows 1–4 × 2–5, support reads
    first, then own reads, and their features follow FEATURES' definitions."""
    rng = np.random.default_rng(1)
    g = _grids(rng)
    feats, inv, var, ok = candidate_features(g, np.array([37]), np.array([50]))
    assert feats.shape == (len(FEATURES), 1, 32) and ok.all()
    fy, fx = (37 % 16 + 0.5) / 16, (50 % 16 + 0.5) / 16
    median = np.median(np.log([g.inv_support[r, c] for r in (2, 3) for c in (3, 4)]))
    grad = np.log1p(gradient_at(g.rgb, np.array([37]), np.array([50]), 0.01)[0])
    floored = np.log(np.maximum(g.rgb, 0.0) + 0.01)
    n = 0
    for grid_inv, grid_var, own in ((g.inv_support, g.var_support, 0.0), (g.inv_own, g.var_own, 1.0)):
        for r in (1, 2, 3, 4):
            for c in (2, 3, 4, 5):
                dy, dx = r - 2 - fy, c - 3 - fx
                floored_cell = ((floored[37, 50] - g.cells[r, c]) ** 2).sum()
                want = [dy ** 2, dx ** 2, abs(dy), abs(dx), ((g.log_rgb[37, 50] - g.cell_log[r, c]) ** 2).sum(),
                        floored_cell, ((floored[37, 50] - g.evidence[r, c]) ** 2).sum(), g.spread[r, c],
                        np.log(np.sqrt(grid_var[r, c]) / grid_inv[r, c]), np.log(grid_inv[r, c]) - median, own,
                        grad * floored_cell, grad, np.log(grid_inv[r, c])]
                np.testing.assert_allclose(feats[:, 0, n], want, rtol=1e-5, atol=1e-6)
                assert inv[0, n] == grid_inv[r, c] and var[0, n] == grid_var[r, c]
                n += 1


def test_windows_off_the_grid_or_without_a_read_are_not_candidates():
    g = _grids(np.random.default_rng(2))
    g.inv_own[0, 0] = np.nan
    _, _, _, ok = candidate_features(g, np.array([3]), np.array([4]))  # block (0, 0): windows −1 … 2 on each axis
    off_grid = np.array([r < 0 or c < 0 for r in (-1, 0, 1, 2) for c in (-1, 0, 1, 2)])
    assert (ok[0, :16] == ~off_grid).all()
    assert not ok[0, 16 + 5] and ok[0, 16 + 6]  # own read of window (0, 0) missing, (0, 1) there


def test_a_zero_scorer_reads_the_mean_of_the_candidates_and_the_mixtures_variance_only_where_windows_disagree():
    """Support reads of 0.2 m⁻¹ left of grid column 3 and 1 m⁻¹ from it: only blocks 2 (between windows 2 and 3)
    disagree. With every score equal, each of their pixels reads the plain mean of its usable candidates' 1/d, with
    the mixture's variance; every other pixel keeps its guided read."""
    rng = np.random.default_rng(3)
    g = _grids(rng, step_col=3)
    blocks = disagreeing_blocks(g.inv_support, np.log(1.1), 5, 6)
    assert blocks[:, 2].all() and blocks.sum() == 5
    inv_px = np.full((80, 96), 0.5, np.float32)
    var_px = np.full((80, 96), 1e-3, np.float32)
    assert select_depth(_zero_scorer(), g, inv_px, var_px) == 5 * 16 * 16
    _, inv, var, ok = candidate_features(g, np.array([40]), np.array([40]))
    mean = inv[0][ok[0]].mean()
    np.testing.assert_allclose(inv_px[40, 40], mean, rtol=1e-5)
    np.testing.assert_allclose(var_px[40, 40], (var[0][ok[0]] + (inv[0][ok[0]] - mean) ** 2).mean(), rtol=1e-4)
    untouched = np.ones((80, 96), bool)
    untouched[:, 32:48] = False
    assert (inv_px[untouched] == 0.5).all() and (var_px[untouched] == 1e-3).all()


def test_no_block_disagrees_on_one_surface_or_without_reads():
    assert not disagreeing_blocks(np.full((4, 5), 0.3), np.log(1.1), 3, 4).any()
    assert not disagreeing_blocks(np.full((4, 5), np.nan), np.log(1.1), 3, 4).any()


@pytest.mark.parametrize("change, word", [({"features": ["dy2"]}, "features"), ({"std": [0.0] * len(FEATURES)}, "std"),
                                          ({"layers": [[[[1.0]], [0.0]]]}, "layer"), ({"disagreement": -1}, "negative"),
                                          ({"mean": [float("nan")] * len(FEATURES)}, "non-finite")])
def test_a_manifest_with_bad_pixel_select_weights_is_refused(tmp_path, change, word):
    path = tmp_path / EVIDENCE_MODEL.name
    shutil.copy(EVIDENCE_MODEL, path)
    manifest = json.loads(EVIDENCE_MODEL.with_suffix(".manifest.json").read_text())
    assert manifest.get("pixel_select")  # the shipped network reads with fitted weights
    path.with_suffix(".manifest.json").write_text(json.dumps(dict(manifest,
                                                                  pixel_select={**manifest["pixel_select"], **change})))
    with pytest.raises(ModelError, match=f"pixel_select.*{word}"):
        EvidenceNetwork(path)
    without_support = {k: v for k, v in manifest.items() if k != "support"}
    path.with_suffix(".manifest.json").write_text(json.dumps(without_support))
    with pytest.raises(ModelError, match="pixel_select scores support reads"):
        EvidenceNetwork(path)


def test_the_shipped_weights_round_trip_through_their_dictionary():
    manifest = json.loads(EVIDENCE_MODEL.with_suffix(".manifest.json").read_text())
    select = PixelSelect.from_dict(manifest["pixel_select"])
    again = PixelSelect.from_dict(json.loads(json.dumps(select.to_dict())))
    x = np.random.default_rng(4).normal(size=(len(FEATURES), 5)).astype(np.float32)
    np.testing.assert_array_equal(select.scores(x), again.scores(x))


def test_two_threads_score_the_same_bits_as_one(monkeypatch):
    """Chunks are independent: scored on 2 threads, many small chunks give the one-thread result bit for bit."""
    from bmi_sdk.decode import pixel_select

    monkeypatch.setattr(pixel_select, "CHUNK_PX", 256)
    rng = np.random.default_rng(5)
    g = _grids(rng)
    n = len(FEATURES)
    scorer = PixelSelect(np.zeros(n, np.float32), np.ones(n, np.float32),
                         ((rng.normal(size=(n, 8)).astype(np.float32), rng.normal(size=8).astype(np.float32)),
                          (rng.normal(size=(8, 1)).astype(np.float32), np.zeros(1, np.float32))), 0.0)
    reads = []
    for threads in (1, 2):
        inv_px, var_px = np.full((80, 96), 0.5, np.float32), np.full((80, 96), 1e-3, np.float32)
        assert select_depth(scorer, g, inv_px, var_px, threads) > 4 * 256
        reads.append((inv_px, var_px))
    np.testing.assert_array_equal(reads[0][0], reads[1][0])
    np.testing.assert_array_equal(reads[0][1], reads[1][1])
    assert not np.all(reads[0][0] == 0.5)


@pytest.mark.parametrize("argv, word", [(["--seed", "20260"], "reported"), (["--seed", "-2"], ">= 0"),
                                        (["--seed", "4242,777"], "reported"), (["--seed", "5,5"], "distinct"),
                                        (["--seed", "5,x"], "integers"), (["--steps", "0"], "--steps"),
                                        (["--steps", "100001"], "--steps"), (["--seed", ",".join(map(str, range(17)))],
                                                                        "distinct"),
                                        (["--seed", "5", "--tiles", "0"], "--tiles"),
                                        (["--seed", "5", "--tiles", "65"], "--tiles")])
def test_the_fit_refuses_bad_arguments_before_decoding_a_tile(capsys, argv, word):
    from bmi_sdk.nn.pixel_select_fit import main

    with pytest.raises(SystemExit) as exit_info:
        main(argv + ["--manifest", str(EVIDENCE_MODEL.with_suffix(".manifest.json"))])
    assert exit_info.value.code == 2 and word in capsys.readouterr().err


@pytest.mark.parametrize("text, word", [(None, "cannot read"), ("not json", "cannot read"),
                                        ('{"decoder": "learned"}', "not an evidence")])
def test_the_fit_refuses_a_manifest_it_cannot_write_into(tmp_path, capsys, text, word):
    from bmi_sdk.nn.pixel_select_fit import main

    path = tmp_path / "m.json"
    if text is not None:
        path.write_text(text)
    with pytest.raises(SystemExit) as exit_info:
        main(["--seed", "5", "--manifest", str(path)])
    assert exit_info.value.code == 2 and word in capsys.readouterr().err


def test_a_second_fit_into_a_manifest_another_fit_is_writing_is_refused_before_decoding_a_tile(tmp_path, capsys):
    """Two fits into one manifest at once would each write their weights over the other's: a fit holds the lock file
    beside the manifest from reading it to writing it, and a second is refused, naming the first's process, with the
    manifest untouched."""
    import os

    from bmi_sdk.io_atomic import lock_folder, unlock_folder
    from bmi_sdk.nn.pixel_select_fit import LOCK_SUFFIX, main

    manifest = tmp_path / "evidence.manifest.json"
    manifest.write_text(EVIDENCE_MODEL.with_suffix(".manifest.json").read_text())
    before = manifest.read_bytes()
    lock = tmp_path / ("evidence.manifest.json" + LOCK_SUFFIX)
    fd = lock_folder(lock)  # the other fit's lock
    try:
        code = main(["--seed", "5", "--manifest", str(manifest)])
    finally:
        unlock_folder(lock, fd)
    err = capsys.readouterr().err
    assert code == 1 and f"being written by another run (process {os.getpid()})" in err, err
    assert manifest.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == [manifest.name]
