"""Fit the hardware errors to extracted spots: Gauss–Newton on the exact engine, LM inside, honest σ.

Outer loop (relinearisation): at the current estimate g the exact engine
gives every spot's kernel, its derivatives for the ray-traced terms and its
landing point (``model`` module doc); jaxopt's Levenberg–Marquardt (or
Gauss–Newton) then solves the jitted, differentiable patch model for the nine
parameters and the per-spot amplitudes/backgrounds; the noise weights are
re-evaluated from the model's own prediction (the data's would bias low
counts); repeat until the step is below 5 % of every σ.

Uncertainties: the covariance is (JᵀJ)⁻¹ of the whitened residuals at the
solution (J by ``jax.jacfwd``), nuisance parameters included, so each σ is
marginal over the others. Degeneracy: parameter pairs whose correlation
exceeds 0.9 and parameters whose σ exceeds the paper's range are reported
with advice on captures that would separate them.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import jax.numpy as jnp
import numpy as np

from bmi_sdk.geometry import BMI_SENSOR
from bmi_sdk.optics import get_lens
from bmi_sdk.optics.perturb import (
    PAPER_RANGES,
    PARAMETERS,
    SIZES,
    VECTOR_NAMES,
    Perturbation,
    chief_landing_px,
    spot_kernels,
)

from .extract import Extraction
from .model import ENGINE, UNITS, in_float64, linearisation_arrays, make_solver, spot_patches
from .targets import CHANNEL_NM, CalibrationError

MIN_FIT_SPOTS = 4
# Forward-difference steps: px, px, %, µm, µm, arcmin, arcmin, (stray: analytic), %.
FD_STEPS = {0: 0.01, 1: 0.01, 2: 0.02, 3: 0.02, 4: 0.02, 5: 0.01, 6: 0.01, 8: 0.002}
CORRELATION_LIMIT = 0.9

_ADVICE = {
    frozenset({"psf_shift_px", "tilt_arcmin"}):
        "a tilt of the nearly monocentric lens about its centre turns the view: every spot moves by about R·τ "
        "(1.05 px per arcmin) with almost no PSF change, as a PSF shift does; they separate only through the field "
        "dependence of that motion. Add sources at θ ≥ 50° in four azimuths, or fix tilt_arcmin (or the shift) "
        "when the rig's orientation is not known to better than 1′",
    frozenset({"psf_shift_px", "decenter_um"}):
        "a decenter moves every spot by δ/pitch as a shift does; it separates through the focus change it makes "
        "across the field: add sources at θ ≥ 45° in opposite azimuths, at near (0.7 m) and far (10 m) ranges",
    frozenset({"decenter_um", "tilt_arcmin"}):
        "both move the spots; only the decenter defocuses the field edge: add large-field sources in opposite "
        "azimuths at near and far ranges",
    frozenset({"sensor_radius_error_pct", "psf_scale_pct"}):
        "both resize off-axis PSFs; the radius error also moves spots radially by ∝ R(1 − cos θ): add sources at "
        "several fields (20°, 40°, 55°) and ranges",
    frozenset({"stray_light_fraction", "psf_scale_pct"}):
        "glare and a larger PSF both put energy into the wings: raise the exposure (more SNR in the wings) and add "
        "far (10 m) sources whose cores are sharp",
}


@dataclass
class FitResult:
    estimate: Perturbation
    vector: np.ndarray  # (9,) in VECTOR_NAMES order
    sigma: np.ndarray  # (9,) 1σ, nan for fixed
    free: np.ndarray  # (9,) bool
    correlation: np.ndarray  # (9, 9) among the global parameters (nan rows for fixed)
    chi2_reduced: float
    n_pixels: int
    n_parameters: int
    outer_iterations: int
    inner_iterations: list
    per_capture: list  # dicts per fitted spot
    held_out: list  # dicts per held-out spot
    degeneracies: list
    seconds: dict
    history: list = field(default_factory=list)  # (9,) estimate after each outer iteration, start first
    patches: dict = field(default_factory=dict)  # "data", "model" (S, K, K), "index" for the report

    def parameters(self) -> dict:
        """{name: {"value", "sigma", "unit", "free"}} with the file's names (2-D terms as lists)."""
        from bmi_sdk.optics.perturb import UNITS as PUNITS

        out, i = {}, 0
        for n in PARAMETERS:
            sl = slice(i, i + SIZES[n])
            val = [float(v) for v in self.vector[sl]]
            sig = [None if np.isnan(v) else float(v) for v in self.sigma[sl]]
            out[n] = {"value": val if SIZES[n] == 2 else val[0], "sigma": sig if SIZES[n] == 2 else sig[0],
                      "unit": PUNITS[n], "free": bool(self.free[sl].all())}
            i += SIZES[n]
        return out


def _free_mask(free: dict | None) -> np.ndarray:
    mask = np.ones(9, dtype=bool)
    if free:
        unknown = set(free) - set(PARAMETERS)
        if unknown:
            raise CalibrationError(f"unknown parameters {sorted(unknown)}; known: {PARAMETERS}")
        i = 0
        for n in PARAMETERS:
            if n in free:
                mask[i:i + SIZES[n]] = bool(free[n])
            i += SIZES[n]
    return mask


def _sources(spots):
    return (np.array([s.source.field_deg for s in spots]), np.array([s.source.azimuth_deg for s in spots]),
            np.array([s.source.depth_m for s in spots]))


def _centres(spots, k):
    return np.array([[s.row0 + k // 2, s.col0 + k // 2] for s in spots], dtype=np.float64)


def linearise(lens, g, spots, channels, kernel_px, geometry, spread_px):
    """Exact kernels (S, C, K, K) on the patches' pixels, their derivatives (S, 8, C, K, K) for the engine
    parameters (``model.ENGINE``), landing points (S, 2) and their derivatives (S, 8, 2)."""
    theta, phi, depth = _sources(spots)
    centre = _centres(spots, kernel_px)
    n = len(spots)
    k0 = np.zeros((n, len(channels), kernel_px, kernel_px))
    dk = np.zeros((n, len(ENGINE), len(channels), kernel_px, kernel_px))
    land0, dland = None, np.zeros((n, len(ENGINE), 2))
    for ci, c in enumerate(channels):
        lam = CHANNEL_NM[c] * 1e-3

        def kernels(vector):
            return spot_kernels(lens, Perturbation.from_vector(vector, spread_px), theta, phi, depth, lam, centre,
                                kernel_px, geometry.centre_px, geometry.pitch_um, stray_light=False)

        base = kernels(np.asarray(g, dtype=np.float64))
        k0[:, ci] = base.kernels
        if land0 is None:
            land0 = base.landing_px
        for j, idx in enumerate(ENGINE):
            gj = np.array(g, dtype=np.float64)
            gj[idx] += FD_STEPS[idx]
            moved = kernels(gj)
            dk[:, j, ci] = (moved.kernels - base.kernels) / FD_STEPS[idx]
            if ci == 0:
                dland[:, j] = (moved.landing_px - base.landing_px) / FD_STEPS[idx]
    return k0, dk, land0, dland


POSITION = (0, 1, 3, 4, 5, 6, 8)  # parameters that move spots (scale and glare do not)
MAX_STEP_PX = 0.5  # trust region: a linearised step may move no spot further than this
MAX_STEP_SCALE_PCT = 2.5  # … nor change the PSF scale by more than this
CENTROID_PX = 0.05  # centroid accuracy assumed by the start-value solve


def initial_positions(lens, g, spots, channel, kernel_px, geometry, spread_px, free_mask, iterations: int = 2):
    """Start values for the spot-moving parameters from the centroids alone (Gauss–Newton on positions).

    The patch model is linear in the kernels, so it is only valid for moves well
    below a PSF width; the centroids place shift, decenter, tilt and radius
    within a fraction of a pixel first. The centroid of each spot relative to
    its chief ray comes from the exact kernel at the start values.

    Positions alone cannot tell a shift from a tilt or a decenter (all move
    every spot nearly alike), so the solve carries a weak prior: each
    parameter ~ N(0, paper range²) against centroids good to
    ``CENTROID_PX``; it picks the small-parameter point of the valley and the
    patch fit, which sees the focus changes, moves along it.
    """
    theta, phi, depth = _sources(spots)
    lam = CHANNEL_NM[channel] * 1e-3
    measured = np.array([s.centroid_px for s in spots])
    start = Perturbation.from_vector(g, spread_px)
    land = chief_landing_px(lens, start, theta, phi, depth, lam, geometry.centre_px, geometry.pitch_um)
    land = land + start.psf_shift_rc
    # kernels centred on their own landing point, so no spot is cut by the window
    first = spot_kernels(lens, start, theta, phi, depth, lam, np.rint(land), kernel_px, geometry.centre_px,
                         geometry.pitch_um, stray_light=False)
    origin = np.rint(land) - kernel_px // 2
    offset = np.stack([_centroid(k, np.ones_like(k, dtype=bool)) for k in first.kernels]) + origin - first.landing_px
    g = np.array(g, dtype=np.float64)
    cols = [i for i in POSITION if free_mask[i]]
    if not cols:
        return g

    def landing(vector):
        p = Perturbation.from_vector(vector, spread_px)
        chief = chief_landing_px(lens, p, theta, phi, depth, lam, geometry.centre_px, geometry.pitch_um)
        return chief + p.psf_shift_rc

    base_names = [n for n in PARAMETERS for _ in range(SIZES[n])]
    prior = np.array([PAPER_RANGES[base_names[i]] for i in cols])
    for _ in range(iterations):
        base = landing(g)
        jac = np.zeros((len(spots) * 2, len(cols)))
        for j, idx in enumerate(cols):
            gj = g.copy()
            gj[idx] += FD_STEPS[idx]
            jac[:, j] = ((landing(gj) - base) / FD_STEPS[idx]).ravel()
        resid = (measured - base - offset).ravel()
        a = np.vstack([jac / CENTROID_PX, np.diag(1.0 / prior)])
        b = np.concatenate([resid / CENTROID_PX, -g[cols] / prior])
        step, *_ = np.linalg.lstsq(a, b, rcond=None)
        g[cols] += step
    return g


def _centroid(patch, used):
    w = np.where(used, np.maximum(patch, 0.0), 0.0)
    rr, cc = np.mgrid[0:patch.shape[0], 0:patch.shape[1]]
    return np.array([(w * rr).sum(), (w * cc).sum()]) / w.sum()


def _linear_fit(kernels, spot, extraction, channels, iterations: int = 2):
    """Best amplitudes + background for fixed kernels (weighted LS, weights from the model); (pred, chi2, dof)."""
    onehot = [spot.channel == c for c in channels]
    cols = [spot.illumination * kernels[ci] * onehot[ci] for ci in range(len(channels))] + [np.ones_like(spot.data_dn)]
    a = np.stack([c[spot.used] for c in cols], axis=1)
    y = spot.data_dn[spot.used]
    var = spot.sigma_dn[spot.used] ** 2
    for _ in range(iterations):
        w = 1.0 / np.sqrt(var)
        coef, *_ = np.linalg.lstsq(a * w[:, None], y * w, rcond=None)
        pred = a @ coef
        var = extraction.variance(pred, spot.n_repeats, spot.n_dark)
    chi2 = float(np.sum((y - pred) ** 2 / var))
    full = np.zeros_like(spot.data_dn)
    full[spot.used] = pred
    return full, chi2, int(y.size - a.shape[1])


def evaluate_spots(lens, perturbation: Perturbation, spots, extraction, channels, kernel_px, geometry=BMI_SENSOR):
    """Exact kernels of ``perturbation`` at each spot (position predicted, not refitted), best flux and
    background per spot; per spot {index, chi2_reduced, rms_dn, centroid_residual_px}."""
    theta, phi, depth = _sources(spots)
    centre = _centres(spots, kernel_px)
    kern = np.stack([spot_kernels(lens, perturbation, theta, phi, depth, CHANNEL_NM[c] * 1e-3, centre, kernel_px,
                                  geometry.centre_px, geometry.pitch_um).kernels for c in channels], axis=1)
    out = []
    for s, spot in enumerate(spots):
        pred, chi2, dof = _linear_fit(kern[s], spot, extraction, channels)
        out.append({"source": spot.index, "chi2_reduced": chi2 / dof,
                    "rms_dn": float(np.sqrt(np.mean((pred - spot.data_dn)[spot.used] ** 2))),
                    "centroid_residual_px": (_centroid(spot.data_dn, spot.used) - _centroid(pred, spot.used)).tolist()})
    return out


def _degeneracies(corr, sigma, free):
    found = []
    base = [n for n in PARAMETERS for _ in range(SIZES[n])]
    for i in range(9):
        for j in range(i + 1, 9):
            if free[i] and free[j] and base[i] != base[j] and abs(corr[i, j]) > CORRELATION_LIMIT:
                pair = frozenset({base[i], base[j]})
                found.append({"parameters": [VECTOR_NAMES[i], VECTOR_NAMES[j]], "correlation": float(corr[i, j]),
                              "advice": _ADVICE.get(pair, "add sources at more fields, azimuths and ranges")})
    for i in range(9):
        if free[i] and sigma[i] > PAPER_RANGES[base[i]]:
            found.append({"parameters": [VECTOR_NAMES[i]], "sigma": float(sigma[i]),
                          "advice": f"{VECTOR_NAMES[i]} is barely constrained (1σ {sigma[i]:.3g} exceeds the paper's "
                                    f"range {PAPER_RANGES[base[i]]:g}): fix it or add captures as advised above"})
    return found


@in_float64
def fit_calibration(extraction: Extraction, free: dict | None = None, method: str = "lm", max_outer: int = 4,
                    inner_maxiter: int = 10, lens_name: str = "bmi_monocentric", geometry=BMI_SENSOR,
                    initial: Perturbation | None = None, channels=None, spread_px: float | None = None,
                    on_step: Callable[[str, int, int], None] | None = None) -> FitResult:
    """Fit the hardware errors to ``extraction``'s spots (held-out sources kept for the check).

    jax runs in float64 for the duration of the call only (``model.float64``). ``on_step(stage, done, total)``
    is called after each of its ``max_outer + 2`` steps (initial positions, each relinearisation, the
    held-out check; a fit that converges early jumps to the last), for a progress display."""
    t_start = time.perf_counter()
    fit_spots = [s for s in extraction.spots if not s.source.held_out]
    held = [s for s in extraction.spots if s.source.held_out]
    if len(fit_spots) < MIN_FIT_SPOTS:
        reasons = "; ".join(f"source {i}: {r}" for i, r in extraction.rejected) or "none rejected"
        raise CalibrationError(f"too few usable point sources: {len(fit_spots)} (need ≥ {MIN_FIT_SPOTS} for the "
                               f"{len(VECTOR_NAMES)} hardware parameters); rejected: {reasons}. Add sources at "
                               "several fields (0–55°), azimuths and ranges (standard_target)")
    lens = get_lens(lens_name)
    k = fit_spots[0].data_dn.shape[0]
    channels = list(channels) if channels is not None else sorted({int(c) for s in fit_spots
                                                                    for c in np.unique(s.channel[s.used])})
    init = initial or Perturbation()
    spread = init.stray_light_spread_px if spread_px is None else spread_px
    free_mask = _free_mask(free)
    g = init.to_vector()
    t0 = time.perf_counter()
    g = initial_positions(lens, g, fit_spots, channels[0], k, geometry, spread, free_mask)
    seconds_init = time.perf_counter() - t0
    steps = max_outer + 2

    def step(stage: str, done: int) -> None:
        if on_step is not None:
            on_step(stage, done, steps)

    step("initial positions", 1)
    n_s, n_c = len(fit_spots), len(channels)
    data = jnp.asarray(np.stack([s.data_dn for s in fit_spots]))
    used = jnp.asarray(np.stack([s.used for s in fit_spots]))
    sigma = np.stack([s.sigma_dn for s in fit_spots])
    run, residual, jacobian = make_solver(n_s, n_c, spread, method, inner_maxiter)
    amp_scale = None
    bg = np.zeros(n_s)
    amp_rel = np.zeros((n_s, n_c))
    inner, seconds = [], {"initial_positions": seconds_init, "linearise": 0.0, "solve": 0.0}
    sig_g = np.full(9, np.inf)
    outer = 0
    history = [g.copy()]
    for outer in range(1, max_outer + 1):
        t0 = time.perf_counter()
        k0, dk, land0, dland = linearise(lens, g, fit_spots, channels, k, geometry, spread)
        lin = linearisation_arrays(fit_spots, k0, dk, land0, dland, channels)
        seconds["linearise"] += time.perf_counter() - t0
        t0 = time.perf_counter()
        if amp_scale is None:
            amp_scale = np.stack([[(s.data_dn * (s.channel == c) * s.used).sum()
                                   / (s.illumination * k0[i, ci] * (s.channel == c)).sum()
                                   for ci, c in enumerate(channels)] for i, s in enumerate(fit_spots)])
        x0 = np.concatenate([g / UNITS, amp_rel.ravel(), bg])
        args = (jnp.asarray(g), jnp.asarray(g), jnp.asarray(free_mask), jnp.asarray(amp_scale), lin, data,
                jnp.asarray(1.0 / sigma), used)
        x, iters = run(jnp.asarray(x0), *args)
        x = np.asarray(x)
        inner.append(int(iters))
        g_new = np.where(free_mask, x[:9] * UNITS, g)
        move = np.abs(np.einsum("j,sjx->sx", (g_new - g)[list(ENGINE)], dland)).max()
        shrink = min(1.0, MAX_STEP_PX / max(move, 1e-300), MAX_STEP_SCALE_PCT / max(abs(g_new[2] - g[2]), 1e-300))
        if shrink < 1.0:  # outside the linearisation's validity: a shorter step, then relinearise
            g_new = g + (g_new - g) * shrink
            x = np.concatenate([np.where(free_mask, g_new / UNITS, x[:9]), x[9:]])
        amp_rel = x[9:9 + n_s * n_c].reshape(n_s, n_c)
        bg = x[9 + n_s * n_c:]
        amp = amp_scale * (1 + amp_rel)
        pred = np.asarray(spot_patches(jnp.asarray(g_new), jnp.asarray(g), jnp.asarray(amp), jnp.asarray(bg), lin,
                                       spread))
        sigma = np.sqrt(np.stack([extraction.variance(pred[i], s.n_repeats, s.n_dark)
                                  for i, s in enumerate(fit_spots)]))
        # Uncertainty at this solution (with the re-evaluated weights).
        args = (jnp.asarray(g), jnp.asarray(g), jnp.asarray(free_mask), jnp.asarray(amp_scale), lin, data,
                jnp.asarray(1.0 / sigma), used)
        jac = np.asarray(jacobian(jnp.asarray(x), *args))
        seconds["solve"] += time.perf_counter() - t0
        cols = np.concatenate([free_mask, np.ones(x.size - 9, dtype=bool)])
        jf = jac[:, cols]
        w, v = np.linalg.eigh(jf.T @ jf)
        cov_f = (v / np.maximum(w, w.max() * 1e-15)) @ v.T
        cov = np.full((x.size, x.size), np.nan)
        cov[np.ix_(cols, cols)] = cov_f
        new_sig = np.sqrt(np.diag(cov)[:9]) * UNITS
        moved = np.abs(g_new - g)
        g = g_new
        history.append(g.copy())
        step(f"relinearisation {outer} of at most {max_outer}", 1 + outer)
        if outer > 1 and np.all((moved / np.where(np.isfinite(new_sig), new_sig, np.inf))[free_mask] < 0.05):
            sig_g = new_sig
            break
        sig_g = new_sig
    res = np.asarray(residual(jnp.asarray(x), *args))
    n_pix = int(np.asarray(used).sum())
    n_par = int(cols.sum())
    chi2_red = float(np.sum(res**2) / (n_pix - n_par))
    d = np.sqrt(np.diag(cov)[:9])
    corr = cov[:9, :9] / np.outer(d, d)
    estimate = Perturbation.from_vector(g, spread)
    per_capture = []
    for i, s in enumerate(fit_spots):
        r = np.asarray(res).reshape(n_s, k, k)[i][np.asarray(used)[i]]
        per_capture.append({"source": s.index, "chi2_reduced": float(np.sum(r**2) / max(r.size - n_c - 1, 1)),
                            "rms_dn": float(np.sqrt(np.mean((pred[i] - s.data_dn)[s.used] ** 2))),
                            "centroid_residual_px": (_centroid(s.data_dn, s.used) - _centroid(pred[i], s.used)).tolist()})
    t0 = time.perf_counter()
    held_out = []
    if held:
        fitted = evaluate_spots(lens, estimate, held, extraction, channels, k, geometry)
        nominal = evaluate_spots(lens, Perturbation(stray_light_spread_px=spread), held, extraction, channels, k,
                                 geometry)
        for a, b in zip(fitted, nominal):
            held_out.append({"source": a["source"], "chi2_reduced": a["chi2_reduced"],
                             "chi2_reduced_nominal": b["chi2_reduced"], "rms_dn": a["rms_dn"],
                             "rms_dn_nominal": b["rms_dn"], "centroid_residual_px": a["centroid_residual_px"]})
    seconds["held_out"] = time.perf_counter() - t0
    step("held-out check", steps)
    seconds["total"] = time.perf_counter() - t_start
    sigma_out = np.where(free_mask, sig_g, np.nan)
    return FitResult(estimate=estimate, vector=g, sigma=sigma_out, free=free_mask, correlation=corr,
                     chi2_reduced=chi2_red, n_pixels=n_pix, n_parameters=n_par, outer_iterations=outer,
                     inner_iterations=inner, per_capture=per_capture, held_out=held_out,
                     degeneracies=_degeneracies(np.nan_to_num(corr), sigma_out, free_mask), seconds=seconds,
                     history=history,
                     patches={"data": np.stack([s.data_dn for s in fit_spots]), "model": pred,
                              "used": np.stack([s.used for s in fit_spots]),
                              "index": [s.index for s in fit_spots]})
