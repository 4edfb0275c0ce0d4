"""CRLB on depth: the Fisher machinery against independent truths (spatial-domain brute force,
a Gaussian blur family with a closed-form OTF derivative), the cos²θ throughput law, an
infinite bound where ∂PSF/∂d = 0, and the monocentric bound's growth with depth on axis."""

import json
import math
import warnings

import numpy as np
import pytest

from bmi_sdk.cli import main
from bmi_sdk.optics.crlb import (
    QUANTISATION_SIGMA_8BIT,
    CrlbSettings,
    crlb,
    crlb_from_fisher_mm,
    depth_stencil,
    fisher_information,
    scene_power_spectrum,
)
from bmi_sdk.optics.prescription import load_lens


@pytest.fixture(scope="module")
def mono():
    return load_lens()


def _circular_convolve(scene, kernel):
    """s ⊛ k on the periodic patch by explicit shifted sums (no FFT)."""
    out = np.zeros_like(scene)
    for i in range(kernel.shape[0]):
        for j in range(kernel.shape[1]):
            out += kernel[i, j] * np.roll(scene, (i, j), axis=(0, 1))
    return out


def test_fisher_matches_spatial_brute_force():
    """(1/σ²) Σ_c Σ_x (T s ⊛ ∂h_c)² computed in space equals the frequency-domain formula (Parseval)."""
    rng = np.random.default_rng(3)
    n, k, sigma, t = 24, 7, 0.01, 0.6
    scene = rng.uniform(0, 1, (n, n))
    dk = rng.normal(size=(2, k, k))
    spatial = sum(np.sum((t * _circular_convolve(scene, dk[c])) ** 2) for c in range(2)) / sigma**2
    power = np.abs(np.fft.fft2(scene)) ** 2
    assert fisher_information(dk, power, sigma, t) == pytest.approx(spatial, rel=1e-10)


@pytest.mark.parametrize("kind,power_exponent", [("amplitude", 1.6), ("power", 0.8)])
def test_scene_spectrum_shape_and_contrast(kind, power_exponent):
    """A real scene built with exactly this spectrum has the requested standard deviation and 1/f slope."""
    n, contrast = 64, 0.2
    power = scene_power_spectrum(n, 0.8, kind, contrast)
    assert power[0, 0] == 0.0
    phase = np.fft.fft2(np.random.default_rng(0).normal(size=(n, n)))  # Hermitian: the scene is real
    scene = np.fft.ifft2(np.sqrt(power) * phase / np.abs(phase))
    assert np.max(np.abs(scene.imag)) < 1e-12
    assert np.std(scene.real) == pytest.approx(contrast, rel=1e-10)
    # one octave up the radial frequency: power falls by 2^-power_exponent
    assert power[0, 8] / power[0, 4] == pytest.approx(2.0**-power_exponent, rel=1e-12)


def _gaussian_kernel(sigma_px, k=61):
    x = np.arange(k) - k // 2
    g = np.exp(-0.5 * (x / sigma_px) ** 2)
    return np.outer(g, g) / np.sum(g) ** 2


def test_gaussian_family_closed_form():
    """Blur σ_b(d) = a + b/d: ∂OTF/∂d = −4π² σ_b σ_b' f² exp(−2π² σ_b² f²) in closed form."""
    a, b = 1.5, 3.0
    n, noise = 128, QUANTISATION_SIGMA_8BIT
    power = scene_power_spectrum(n, 0.8, "amplitude", 0.2)
    freq = np.fft.fftfreq(n)
    f2 = freq[:, None] ** 2 + freq[None, :] ** 2
    for depth_m in (0.8, 3.0, 20.0):
        near, far, scale = depth_stencil(depth_m, 0.01)
        dk = (_gaussian_kernel(a + b / far) - _gaussian_kernel(a + b / near)) * scale
        s_b, ds_b = a + b / depth_m, -b / depth_m**2
        d_otf = -4 * np.pi**2 * s_b * ds_b * f2 * np.exp(-2 * np.pi**2 * s_b**2 * f2)
        closed = np.sum(power * d_otf**2) / n**2 / noise**2
        assert fisher_information(dk[None], power, noise) == pytest.approx(closed, rel=2e-4)


def test_depth_stencil_infinity_and_bad_input():
    near, far, scale = depth_stencil(np.array([4.0, 100.0, math.inf]), 0.01)
    assert near[0] == pytest.approx(1 / 0.26) and far[0] == pytest.approx(1 / 0.24)
    assert far[1] == pytest.approx(200.0)  # step shrinks to u/2 beyond 1/(2δ)
    assert near[2] == far[2] == math.inf and scale[2] == 0.0
    with pytest.raises(ValueError, match="depth_m"):
        depth_stencil(-1.0, 0.01)
    with pytest.raises(ValueError, match="inverse_step"):
        depth_stencil(1.0, 0.0)


def test_zero_derivative_gives_infinite_bound_without_nan():
    power = scene_power_spectrum(64)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fisher = fisher_information(np.zeros((2, 3, 9, 9)), power, QUANTISATION_SIGMA_8BIT, 0.5)
        bound = crlb_from_fisher_mm(fisher)
    assert np.all(fisher == 0) and np.all(np.isinf(bound))
    with pytest.raises(ValueError, match="non-finite"):
        fisher_information(np.full((3, 9, 9), np.nan), power, 1.0)


def test_lens_at_infinity_and_far_away(mono):
    """At d = ∞ the kernels do not depend on d (∂/∂d = −u² ∂/∂u = 0): infinite bound. Far away the
    kernels change with u = 1/d at a nearly constant rate, so σ_d = d² σ_u grows as d²."""
    inf_pt, mid_pt, far_pt = crlb(mono, 0.0, [math.inf, 50.0, 100.0], 41)
    assert inf_pt.crlb_mm == math.inf and inf_pt.fisher_per_m2 == 0.0
    row = json.loads(json.dumps(inf_pt.to_dict()))
    assert row["crlb_mm"] is None and row["depth_m"] is None
    assert far_pt.crlb_mm / mid_pt.crlb_mm == pytest.approx(4.0, rel=0.1)
    with pytest.raises(ValueError, match="beyond 100 m"):
        crlb(mono, 0.0, 1e4, 41)


def test_throughput_scales_fisher_by_cos_squared(mono):
    ones = crlb(mono, 60.0, 4.0, 41, throughput=lambda f: np.ones_like(np.asarray(f, dtype=float)))[0]
    cos = crlb(mono, 60.0, 4.0, 41)[0]
    assert cos.fisher_per_m2 == pytest.approx(0.25 * ones.fisher_per_m2, rel=1e-12)
    assert cos.crlb_mm == pytest.approx(2.0 * ones.crlb_mm, rel=1e-12)


def test_monocentric_on_axis_bound_grows_with_depth(mono):
    """Defocus changes as 1/d, so ∂PSF/∂d falls about as 1/d²: the bound rises monotonically over 1–6 m."""
    depths = np.arange(1.0, 6.01, 0.5)
    points = crlb(mono, 0.0, depths, 41)
    bounds = np.array([p.crlb_mm for p in points])
    assert np.all(np.diff(bounds) > 0)
    assert all(p.energy_captured_min >= 0.99 for p in points)


def test_settings_and_inputs_refused(mono):
    with pytest.raises(ValueError, match="spectrum_kind"):
        CrlbSettings(spectrum_kind="phase")
    with pytest.raises(ValueError, match="noise_sigma"):
        CrlbSettings(noise_sigma=0.0)
    with pytest.raises(ValueError, match="exceeds"):
        crlb(mono, 0.0, 4.0, 41, CrlbSettings(patch_px=32))
    with pytest.raises(ValueError, match="field_deg"):
        crlb(mono, 95.0, 4.0, 41)


def test_cli_json_and_plot(tmp_path, capsys):
    png = tmp_path / "crlb.png"
    assert main(["crlb", "--json", "--lenses", "monocentric", "--depths-m", "2,4", "--fields-deg", "0,60",
                 "--plot", str(png)]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [(r["lens"], r["field_deg"], r["depth_m"]) for r in rows] == [
        ("monocentric", 0.0, 2.0), ("monocentric", 0.0, 4.0), ("monocentric", 60.0, 2.0), ("monocentric", 60.0, 4.0)]
    assert all(r["crlb_mm"] > 0 for r in rows)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(SystemExit) as exc:  # argparse refuses an unknown lens name
        main(["crlb", "--lenses", "zoom"])
    assert exc.value.code == 2
