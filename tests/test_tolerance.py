"""`bmi bench tolerance`: the depth information a built camera's errors take from the field edge."""

import numpy as np
import pytest

from bmi_sdk.bench.tolerance import benchmark_edge_ranges_m, camera_curves, depth_weighted


def test_depth_weighting_is_exact_for_a_quantity_linear_in_inverse_depth():
    """Interpolated linearly in 1/d, a + b/d averages to a + b·mean(1/r) over ranges inside the planes, and is held
    at the end planes' values beyond them."""
    depths = np.array([0.8, 1.0, 2.0, 3.5, 9.5])
    ranges = np.random.default_rng(0).uniform(0.8, 9.5, 10_000)
    assert depth_weighted(0.3 + 0.2 / depths, depths, ranges) == pytest.approx(0.3 + 0.2 * np.mean(1 / ranges))
    assert depth_weighted(0.3 + 0.2 / depths, depths, [0.5, 20.0]) == pytest.approx(0.3 + 0.1 / 0.8 + 0.1 / 9.5)


def test_benchmark_edge_ranges_are_the_edge_tiles_true_ranges():
    from bmi_sdk.nn.evaluate import Benchmark

    bench = Benchmark(tiles=2, tile_px=32)
    ranges = benchmark_edge_ranges_m(bench)
    m = bench.margin_px
    tile0 = bench.scene("edge", 0)[1][m:-m, m:-m]
    assert len(ranges) == 2 * 32 * 32 and np.all(ranges > 0)
    np.testing.assert_array_equal(ranges[:32 * 32], tile0.ravel())


def test_a_focus_moved_into_range_takes_the_window_bound_there():
    """A sensor sphere 0.5 % too large, vertex held, moves the 55° focus from beyond 10 m to ~3.4 m. At 3 m the
    blur's first-order change with depth nearly vanishes there, so one window's Cramér–Rao bound rises several
    times over the design's; at 1.25 m, far from either focus, the two bounds stay within 40 % of each other."""
    from bmi_sdk.built_camera import BuiltCamera
    from bmi_sdk.optics.perturb import Perturbation

    depths = (1.25, 3.0)
    nominal_bound, nominal_decoded = camera_curves(BuiltCamera(), depths)
    built_bound, _ = camera_curves(BuiltCamera(perturbation=Perturbation(sensor_radius_error_pct=0.5)), depths)
    assert built_bound[1] > 4 * nominal_bound[1]
    assert 0.6 < built_bound[0] / nominal_bound[0] < 1.4
    assert np.all(nominal_decoded < 0.1)  # the design's planes decode near their bound


def test_only_targets_with_a_full_size_measurement_take_full():
    """``bmi bench tolerance`` has no full-size run: ``--full`` is refused by the parser instead of ignored."""
    from bmi_sdk.cli import build_parser

    parser = build_parser()
    assert parser.parse_args(["bench", "decoder", "--full"]).full
    with pytest.raises(SystemExit):
        parser.parse_args(["bench", "tolerance", "--full"])
    assert not hasattr(parser.parse_args(["bench", "tolerance"]), "full")
