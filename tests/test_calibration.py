"""Calibration pipeline on small simulated captures (21 px patches, ≥ 2.5 m sources, green lamp)."""

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from bmi_sdk.optics.perturb import VECTOR_NAMES, Perturbation
from calibration import (
    CalibrationError,
    CapturePlan,
    PointSource,
    Target,
    extract_spots,
    fit_calibration,
    load_calibration,
    load_captures,
    simulate_captures,
    write_calibration,
)
from calibration.model import in_float64

DIAG = math.degrees(math.atan2(2250, 3000))
PLAN = CapturePlan(kernel_px=21, roi_margin_px=10)
SOURCES = [(0.0, 0.0, 4.0), (55.0, DIAG, 10.0), (55.0, 180 - DIAG, 2.5), (55.0, 180 + DIAG, 4.0),
           (44.0, 0.0, 2.5), (32.0, 90.0, 10.0), (44.0, 180.0, 4.0)]
TARGET = Target(tuple(PointSource(t, a, d) for t, a, d in SOURCES) + (PointSource(30.0, 270.0, 4.0, held_out=True),))


def _within(result, truth, k=3.5):
    z = (result.vector - truth.to_vector()) / result.sigma
    return {n: float(v) for n, v, s in zip(VECTOR_NAMES, z, result.sigma) if not np.isnan(s) and not abs(v) <= k}


@pytest.fixture(scope="module")
def single():
    """Decenter alone injected; every parameter free."""
    truth = Perturbation(decenter_um=(8.0, 0.0))
    captures = simulate_captures(TARGET, PLAN, truth, seed=11)
    extraction = extract_spots(captures)
    result = fit_calibration(extraction, on_step=lambda stage, done, total: STEPS.append((stage, done, total)))
    return truth, captures, extraction, result


STEPS: list[tuple[str, int, int]] = []
"""The progress steps the ``single`` fixture's fit reported."""


def test_the_fit_reports_its_progress_step_by_step(single):
    assert STEPS[0] == ("initial positions", 1, 6) and STEPS[-1] == ("held-out check", 6, 6)
    assert STEPS[1] == ("relinearisation 1 of at most 4", 2, 6)
    assert [done for _, done, _ in STEPS] == sorted({done for _, done, _ in STEPS})  # increasing, no repeats


def test_single_injected_term_is_recovered_alone(single):
    truth, _, extraction, result = single
    assert not extraction.rejected
    assert _within(result, truth) == {}
    assert 0.8 < result.chi2_reduced < 1.2
    held = result.held_out[0]
    assert held["chi2_reduced"] < 1.5 < 10 < held["chi2_reduced_nominal"]


def test_fit_runs_in_float64_and_leaves_jax_in_float32(single):
    import jax

    from calibration.model import linearisation_arrays

    assert single[3].patches["model"].dtype == np.float64  # the jax model's prediction, computed in the fit
    assert jax.config.jax_enable_x64 is False
    with pytest.raises(RuntimeError, match="float64"):
        linearisation_arrays([], np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0), [1])


def test_near_degenerate_pairs_are_reported(single):
    from bmi_sdk.cli.calibrate import degeneracy_lines

    pairs = {frozenset(d["parameters"]) for d in single[3].degeneracies if len(d["parameters"]) == 2}
    # shift against tilt: a tilt about the lens centre is almost a rotation of the view
    assert frozenset({"psf_shift_px[0]", "tilt_arcmin[1]"}) in pairs
    assert any("monocentric" in d["advice"] for d in single[3].degeneracies)
    lines = degeneracy_lines(single[3].degeneracies)  # what bmi calibrate prints: one short line each
    assert len(lines) == len(single[3].degeneracies) and all(len(line) <= 120 for line in lines)
    assert any(line.startswith("degenerate: psf_shift_px[0] / tilt_arcmin[1] (correlation ") for line in lines)


def test_fit_started_far_from_the_truth_converges(single):
    truth, _, extraction, near = single
    far = fit_calibration(extraction, initial=Perturbation(decenter_um=(-9.0, 9.0), tilt_arcmin=(0.8, -0.8),
                                                           psf_scale_pct=-3.0, sensor_radius_error_pct=1.5),
                          max_outer=5)
    assert _within(far, truth) == {}
    assert np.all(np.abs(far.vector - near.vector) < near.sigma)


@in_float64  # the jax solver is called directly below, as the fit calls it
def test_perfect_lens_fits_to_zero_and_scipy_agrees():
    captures = simulate_captures(TARGET, PLAN, Perturbation(), seed=5)
    extraction = extract_spots(captures)
    free = {"tilt_arcmin": False}  # tilt fixed: also checks fixed parameters are held and reported
    result = fit_calibration(extraction, free=free)
    assert _within(result, Perturbation()) == {}
    assert np.isnan(result.sigma[5:7]).all() and np.all(result.vector[5:7] == 0)
    assert result.parameters()["tilt_arcmin"]["free"] is False
    # scipy cross-check on the same (linearised) problem, from the same start
    import jax.numpy as jnp
    from scipy.optimize import least_squares

    from bmi_sdk.geometry import BMI_SENSOR
    from bmi_sdk.optics import get_lens
    from calibration.fit import linearise
    from calibration.model import UNITS, linearisation_arrays, make_solver

    spots = [s for s in extraction.spots if not s.source.held_out]
    g0 = result.vector.copy()
    lin = linearisation_arrays(spots, *linearise(get_lens(), g0, spots, [1], 21, BMI_SENSOR, 8.0), [1])
    run, residual, jacobian = make_solver(len(spots), 1, 8.0, "lm", 30)
    amp_scale = np.array([[s.data_dn[s.used].sum()] for s in spots])
    free_mask = np.array([True] * 5 + [False, False] + [True, True])
    args = (jnp.asarray(g0), jnp.asarray(g0), jnp.asarray(free_mask), jnp.asarray(amp_scale), lin,
            jnp.asarray(np.stack([s.data_dn for s in spots])), jnp.asarray(1 / np.stack([s.sigma_dn for s in spots])),
            jnp.asarray(np.stack([s.used for s in spots])))
    x0 = np.concatenate([(g0 + 0.05 * free_mask) / UNITS, np.zeros(2 * len(spots))])
    x_jax, _ = run(jnp.asarray(x0), *args)
    keep = np.concatenate([free_mask, np.ones(2 * len(spots), bool)])

    def f(xf):
        x = x0.copy()
        x[keep] = xf
        return np.asarray(residual(jnp.asarray(x), *args))

    def jac(xf):
        x = x0.copy()
        x[keep] = xf
        return np.asarray(jacobian(jnp.asarray(x), *args))[:, keep]

    ref = least_squares(f, x0[keep], jac=jac, method="trf", xtol=1e-12, ftol=1e-12, gtol=1e-12)
    g_jax = np.asarray(x_jax)[:9][free_mask] * UNITS[free_mask]
    g_ref = ref.x[:int(free_mask.sum())] * UNITS[free_mask]
    sigma = result.sigma[free_mask]
    assert np.all(np.abs(g_jax - g_ref) < 0.01 * sigma)
    # jax.jacfwd against central finite differences of the same residual
    j = np.asarray(jacobian(jnp.asarray(x_jax), *args))
    for col in (0, 2, 7, 9):
        e = np.zeros_like(x0)
        e[col] = 1e-5
        fd = (np.asarray(residual(x_jax + e, *args)) - np.asarray(residual(x_jax - e, *args))) / 2e-5
        assert np.abs(fd - j[:, col]).max() < 1e-6 * np.abs(j[:, col]).max()


def test_engine_derivatives_match_central_differences(single):
    """The forward differences the fit uses against central differences with smaller steps."""
    from bmi_sdk.geometry import BMI_SENSOR
    from bmi_sdk.optics import get_lens
    from bmi_sdk.optics.perturb import spot_kernels
    from calibration.fit import FD_STEPS, linearise
    from calibration.model import ENGINE

    spots = [s for s in single[2].spots if not s.source.held_out][1:3]
    g = np.zeros(9)
    _, dk, _, _ = linearise(get_lens(), g, spots, [1], 21, BMI_SENSOR, 8.0)
    centre = np.array([[s.row0 + 10, s.col0 + 10] for s in spots], dtype=float)
    src = [(s.source.field_deg, s.source.azimuth_deg, s.source.depth_m) for s in spots]
    for j, idx in enumerate(ENGINE):
        h = FD_STEPS[idx] / 4
        k = []
        for sign in (1, -1):
            gj = g.copy()
            gj[idx] += sign * h
            k.append(spot_kernels(get_lens(), Perturbation.from_vector(gj), [a for a, _, _ in src],
                                  [b for _, b, _ in src], [c for _, _, c in src], 0.5876, centre, 21,
                                  BMI_SENSOR.centre_px, stray_light=False).kernels)
        central = (k[0] - k[1]) / (2 * h)
        err = np.abs(dk[:, j, 0] - central).max() / np.abs(central).max()
        assert err < 0.05, (VECTOR_NAMES[idx], err)


def test_saturated_corner_and_too_few(tmp_path):
    target = Target((PointSource(0.0, 0.0, 4.0, peak_fill=4.0), PointSource(60.0, DIAG, 4.0),
                     PointSource(30.0, 0.0, 4.0)))
    captures = simulate_captures(target, PLAN, Perturbation(), seed=2)
    captures.save(tmp_path / "caps")
    loaded = load_captures(tmp_path / "caps")
    assert loaded.sha256() == captures.sha256()
    extraction = extract_spots(loaded)
    reasons = dict(extraction.rejected)
    assert "saturated" in reasons[0]
    assert "frame edge" in reasons[1]
    assert [s.index for s in extraction.spots] == [2]
    with pytest.raises(CalibrationError, match="too few usable point sources: 1"):
        fit_calibration(extraction)
    # a frame that no longer matches the listing is caught
    listing = json.loads((tmp_path / "caps" / "captures.json").read_text())
    listing["frames"][3]["pixel_sha256"] = "0" * 64
    (tmp_path / "caps" / "captures.json").write_text(json.dumps(listing))
    with pytest.raises(CalibrationError, match="pixels do not match"):
        load_captures(tmp_path / "caps")


def test_overlapping_spots_are_rejected():
    plan = CapturePlan(kernel_px=21, roi_margin_px=10, one_lamp_at_a_time=False)
    target = Target((PointSource(20.0, 0.0, 4.0), PointSource(20.1, 0.0, 4.0), PointSource(30.0, 90.0, 4.0)))
    extraction = extract_spots(simulate_captures(target, plan, Perturbation(), seed=3))
    reasons = dict(extraction.rejected)
    assert "overlapping" in reasons[0] and "overlapping" in reasons[1] and 2 not in reasons


def test_calibration_file_round_trip_and_validation(single, tmp_path):
    truth, captures, extraction, result = single
    calib = write_calibration(tmp_path / "calib.json", result, captures, extraction, tensor_fields_deg=(0.0, 30.0),
                              tensor_depths_m=(4.0,))
    doc = json.loads((tmp_path / "calib.json").read_text())
    assert doc["schema"] == "bmi-calibration/1" and doc["injected"]["decenter_um"] == [8.0, 0.0]
    assert doc["parameters"]["decenter_um"]["unit"] == "um" and doc["parameters"]["decenter_um"]["free"] is True
    assert doc["device"]["serial"].startswith("BMI-") and doc["device"]["firmware_version"]
    assert (tmp_path / "calib.png").stat().st_size > 10_000
    again = load_calibration(tmp_path / "calib.json")
    assert again.id == calib.id and again.perturbation == result.estimate
    _runtime_accepts_only_a_matching_frame(tmp_path / "calib.json", calib.id, doc)
    _validation_changes_no_process_state(tmp_path / "calib.json", doc)
    tensor = again.tensor()
    assert tensor.data.shape == (3, 2, 1, 21, 21) and np.allclose(tensor.data.sum(axis=(-1, -2)), 1.0, atol=1e-5)
    assert tensor.perturbation == again.perturbation  # an exact-mode map over it traces the fitted errors
    tensor_json = tmp_path / "calib.psf.json"
    edited = json.loads(tensor_json.read_text())
    edited["perturbation"]["decenter_um"] = [99.0, 0.0]  # the npz hash does not cover this JSON
    tensor_json.write_text(json.dumps(edited))
    with pytest.raises(CalibrationError, match="fitted"):
        again.tensor()
    doc["parameters"]["decenter_um"]["value"] = [0.0, 0.0]
    (tmp_path / "calib.json").write_text(json.dumps(doc))
    with pytest.raises(CalibrationError, match="calibration_id"):
        load_calibration(tmp_path / "calib.json")
    doc["schema"] = "other/1"
    (tmp_path / "calib.json").write_text(json.dumps(doc))
    with pytest.raises(CalibrationError, match="schema"):
        load_calibration(tmp_path / "calib.json")


def _runtime_accepts_only_a_matching_frame(path, calibration_id, doc):
    """``bmi infer --calibration FILE``: the file, read once, is checked against each frame; another camera or
    lens is refused."""
    from types import SimpleNamespace

    from bmi_sdk.runtime.job import check_calibration, load_calibration

    calibration = load_calibration(path)
    frame = SimpleNamespace(lens={"name": doc["lens"]["name"]}, device=dict(doc["device"]))
    info = check_calibration(frame, calibration)
    assert info["id"] == calibration_id and info["device"]["serial"] == doc["device"]["serial"]
    with pytest.raises(ValueError, match="made on camera"):
        check_calibration(SimpleNamespace(lens=frame.lens, device={"serial": "BMI-OTHER"}), calibration)
    with pytest.raises(ValueError, match="taken through 'fisheye'"):
        check_calibration(SimpleNamespace(lens={"name": "fisheye"}, device=frame.device), calibration)


def _validation_changes_no_process_state(path, doc):
    """A fresh process: importing ``calibration`` and validating a file in the runtime leave jax's
    precision and the warning filters as they were."""
    script = f"""
import json, sys, warnings
from types import SimpleNamespace
import jax
before = (jax.config.jax_enable_x64, list(warnings.filters))
import calibration
after_import = (jax.config.jax_enable_x64, list(warnings.filters))
from bmi_sdk.runtime.job import check_calibration, load_calibration
frame = SimpleNamespace(lens={{"name": {doc["lens"]["name"]!r}}}, device={{"serial": {doc["device"]["serial"]!r}}})
check_calibration(frame, load_calibration({str(path)!r}))
after_validation = (jax.config.jax_enable_x64, list(warnings.filters))
print(json.dumps([before == after_import, before == after_validation, jax.config.jax_enable_x64]))
"""
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    assert json.loads(out.stdout.splitlines()[-1]) == [True, True, False]


def test_cli_refuses_ambiguous_input(tmp_path):
    out = subprocess.run([sys.executable, "-m", "bmi_sdk.cli", "calibrate", "--out", str(tmp_path / "c.json")],
                         capture_output=True, text=True)
    assert out.returncode != 0 and "either --captures" in out.stderr
