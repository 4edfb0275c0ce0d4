"""The differentiable forward model of the spot patches (JAX, float64).

At a linearisation point g₀ (the nine hardware parameters, see
``bmi_sdk.optics.perturb.VECTOR_NAMES``) the exact engine gives, per spot and
lamp channel, the kernel K₀ sampled on the patch's own pixels (glare left
out), its forward-difference derivatives ∂K/∂g_j for the eight terms that act
through the engine (PSF shift x/y and scale — exact moves of the transform's
sample positions —, decenter x/y, tilt x/y, sensor radius — through the ray
trace), and the spot's landing point c and ∂c/∂g_j. For g near g₀

    K(g) = (1 − f) · [K₀ + Σ_j ∂K/∂g_j Δg_j] + f · G(c₀ + Σ_j ∂c/∂g_j Δg_j, σ_glare)
    patch = illumination ⊙ Σ_ch [CFA = ch] · A_ch · K_ch(g) + b

with G the pixel-integrated Gaussian glare (erf differences), differentiable
in jax; amplitudes A (per spot and channel) and backgrounds b are nuisance
parameters. At g = g₀ the model and its Jacobian are the exact engine's, so
Gauss–Newton with relinearisation (``fit``) converges to the exact model's
optimum.

Why not move the kernel in jax (a Fourier / periodic-sinc shift and
resampling): the pixel-integrated kernel is undersampled (the intensity's
spectrum reaches ~4× the pixel Nyquist frequency at F/1.79), so the
derivative of any band-limited interpolant at the samples is not the
derivative of the pixel-integrated PSF. Tried first, it biased the fixed
point (scale 0.63 % fitted for 3.01 % injected, 480 σ off); the exact-engine
derivatives removed that bias.

Precision: the model runs in float64, but only inside :func:`float64` (jax's
thread-local ``enable_x64`` switch), which ``fit_calibration`` enters. Importing
this package leaves jax's process-wide setting, and everyone else's float32
jax code, alone.
"""

from __future__ import annotations

import warnings
from functools import lru_cache, wraps

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import erf


def float64():
    """Context manager: jax computes in float64 inside it (this thread only), as the fit needs.

    Jitted functions trace separately for each precision, so the solvers of
    :func:`make_solver` must be called inside it too.
    """
    return jax.enable_x64(True)


def in_float64(fn):
    """Decorator: run ``fn`` inside :func:`float64`."""
    @wraps(fn)
    def wrapper(*args, **kwargs):
        with float64():
            return fn(*args, **kwargs)
    return wrapper


def _require_float64() -> None:
    if not jax.config.jax_enable_x64:
        raise RuntimeError("the calibration model needs float64: call it inside `with calibration.model.float64():`")

ENGINE = (0, 1, 2, 3, 4, 5, 6, 8)  # parameters the exact engine differentiates (all but stray light)
STRAY = 7
# Solver units of the nine parameters (the solver sees parameter / unit, so all are O(1)).
UNITS = np.array([0.1, 0.1, 1.0, 1.0, 1.0, 0.3, 0.3, 0.01, 0.3])


def _glare_axis(edges_minus_c, spread):
    cdf = 0.5 * (1 + erf(edges_minus_c / (jnp.sqrt(2.0) * spread)))
    return cdf[..., 1:] - cdf[..., :-1]


def spot_patches(g, g0, amp, bg, lin, spread_px):
    """Predicted patches (S, K, K) for global parameters ``g`` (9,), amplitudes (S, C), backgrounds (S,).

    ``lin`` is a dict of arrays (see :func:`linearisation_arrays`).
    """
    k0, dk, land0, dland = lin["k0"], lin["dk"], lin["land0"], lin["dland"]
    origin = lin["origin"]  # (S, 2) absolute (row, col) of patch pixel (0, 0)
    kk = k0.shape[-1]
    dq = (g - g0)[jnp.array(ENGINE)]
    kern = k0 + jnp.einsum("j,sjcab->scab", dq, dk)
    land = land0 + jnp.einsum("j,sjx->sx", dq, dland)
    edges = jnp.arange(kk + 1, dtype=jnp.float64) - 0.5
    gy = _glare_axis(origin[:, 0, None] + edges - land[:, 0, None], spread_px)
    gx = _glare_axis(origin[:, 1, None] + edges - land[:, 1, None], spread_px)
    glare = gy[:, :, None] * gx[:, None, :]
    glare = glare / jnp.sum(glare, axis=(-1, -2), keepdims=True)
    f = g[STRAY]
    kern_c = (1 - f) * kern + f * glare[:, None]
    onehot = lin["onehot"]  # (S, C, K, K) CFA channel masks of the lamp's channels
    return lin["illum"] * jnp.einsum("sc,scab->sab", amp, kern_c * onehot) + bg[:, None, None]


def linearisation_arrays(spots, k0, dk, land0, dland, channels) -> dict:
    """Bundle the per-spot arrays the model needs (numpy → jax; inside :func:`float64`)."""
    _require_float64()
    onehot = np.stack([[s.channel == c for c in channels] for s in spots]).astype(np.float64)
    return {"k0": jnp.asarray(k0), "dk": jnp.asarray(dk), "land0": jnp.asarray(land0), "dland": jnp.asarray(dland),
            "origin": jnp.asarray(np.array([[s.row0, s.col0] for s in spots], dtype=np.float64)),
            "illum": jnp.asarray(np.stack([s.illumination for s in spots])), "onehot": jnp.asarray(onehot)}


def _solver_module():
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="JAXopt is no longer maintained")
        import jaxopt
    return jaxopt


def unpack(x, g_fixed, free, n_spots, n_channels, amp_scale):
    """Solver vector → (g, amp, bg). ``x`` = [global/UNITS (free ones used), amp/amp_scale − 1, bg]."""
    g = jnp.where(free, x[:9] * UNITS, g_fixed)
    amp = amp_scale * (1.0 + x[9:9 + n_spots * n_channels].reshape(n_spots, n_channels))
    bg = x[9 + n_spots * n_channels:]
    return g, amp, bg


def make_residual(n_spots, n_channels, spread_px):
    """r(x, g0, g_fixed, free, amp_scale, lin, data, inv_sigma, used) → whitened residuals (flat)."""
    def residual(x, g0, g_fixed, free, amp_scale, lin, data, inv_sigma, used):
        g, amp, bg = unpack(x, g_fixed, free, n_spots, n_channels, amp_scale)
        pred = spot_patches(g, g0, amp, bg, lin, spread_px)
        return jnp.where(used, (pred - data) * inv_sigma, 0.0).ravel()
    return residual


@lru_cache(maxsize=8)
def make_solver(n_spots, n_channels, spread_px, method: str = "lm", maxiter: int = 20):
    """Jitted (fit, residual, Jacobian): fit(x0, g0, g_fixed, free, amp_scale, lin, data, inv_sigma, used) → (x, iterations).

    ``method``: "lm" (jaxopt.LevenbergMarquardt) or "gn" (jaxopt.GaussNewton). Cached: one compilation
    per problem shape and process (compiling costs seconds; a fit then takes milliseconds per inner solve).
    """
    jaxopt = _solver_module()
    residual = make_residual(n_spots, n_channels, spread_px)
    if method == "lm":
        solver = jaxopt.LevenbergMarquardt(residual_fun=residual, maxiter=maxiter, tol=1e-8, xtol=1e-8,
                                           gtol=1e-8)
    elif method == "gn":
        solver = jaxopt.GaussNewton(residual_fun=residual, maxiter=maxiter, tol=1e-8)
    else:
        raise ValueError(f"method must be 'lm' or 'gn', got {method!r}")

    @jax.jit
    def run(x0, *args):
        out = solver.run(x0, *args)
        return out.params, out.state.iter_num

    return run, residual, jax.jit(jax.jacfwd(residual))
