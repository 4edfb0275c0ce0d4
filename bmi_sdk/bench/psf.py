"""`bmi bench psf`: PSF accuracy knobs against run time, the fast models' error, tensor build cost.

Errors are L1 distances Σ|k − k_ref| between unit-sum kernels (0 = identical,
2 = disjoint) against a converged reference (fit grid 32, degree 12, pupil
guard 3, 9 samples per pixel side), over fields 0/30/60°, depths
0.7/2/10 m and infinity, at 587.6 and 486.1 nm.
"""

from __future__ import annotations

import math
import os

import numpy as np

from . import markdown_table, peak_rss_mb, register_target, timed, timed_cpu

CASES = [(0.0, 0.7), (30.0, 0.7), (60.0, 0.7), (0.0, 2.0), (60.0, 2.0), (0.0, 10.0), (60.0, 10.0), (60.0, math.inf)]
WAVELENGTHS_UM = (0.5876, 0.4861)
KERNEL_PX = 41
REF = dict(grid=32, degree=12, guard=3.0, oversample=9)


def _cases():
    theta = np.array([c[0] for c in CASES for _ in WAVELENGTHS_UM])
    depth = np.array([c[1] for c in CASES for _ in WAVELENGTHS_UM])
    lam = np.array([w for _ in CASES for w in WAVELENGTHS_UM])
    return theta, depth, lam


def cold(call):
    """``call()`` with no pupil aims memoised (``pupil.clear_aim_memo``): the cost of a (θ, d, λ) met the first time."""
    from bmi_sdk.optics.pupil import clear_aim_memo

    clear_aim_memo()
    return call()


def run(full: bool = False) -> str:
    from bmi_sdk.optics import PsfTensor, TensorSpec, axial_wavefront, fit_pupils, get_lens, psf_from_pupil
    from bmi_sdk.optics.models import ellipse_psf, two_term_fit

    lens = get_lens("bmi_monocentric")
    theta, depth, lam = _cases()
    ref_fits = fit_pupils(lens, theta, depth, lam, grid=REF["grid"], degree=REF["degree"])
    ref = [psf_from_pupil(f, KERNEL_PX, guard=REF["guard"], oversample=REF["oversample"]).kernel for f in ref_fits]
    default_fits = fit_pupils(lens, theta, depth, lam)

    def err(kernels):
        return max(float(np.abs(k - r).sum()) for k, r in zip(kernels, ref))

    out = []
    rows = []
    for guard in (1.0, 1.25, 1.5, 2.0, 3.0):
        ks, t = timed(lambda: [psf_from_pupil(f, KERNEL_PX, guard=guard).kernel for f in default_fits], 2)
        rows.append([guard, err(ks), t / len(ks) * 1e3])
    out.append("### Pupil sampling (guard = replica spacing / kernel width; 5 samples per pixel side, default fit)\n\n"
               + markdown_table(["guard", "max L1 error", "ms per PSF (transform)"], rows))
    rows = []
    for q in (1, 3, 5, 7):
        ks, t = timed(lambda: [psf_from_pupil(f, KERNEL_PX, oversample=q).kernel for f in default_fits], 2)
        rows.append([q, err(ks), t / len(ks) * 1e3])
    out.append("### Pixel integration (samples per pixel side, exact box filter of the band-limited intensity; guard 1.25)\n\n"
               + markdown_table(["oversample", "max L1 error", "ms per PSF (transform)"], rows))
    rows = []
    batch_theta, batch_depth = np.meshgrid([12.0], np.arange(0.7, 10.01, 0.1), indexing="ij")
    for grid, degree in ((12, 6), (16, 8), (20, 8), (20, 10), (24, 10), (32, 12)):
        fits = fit_pupils(lens, theta, depth, lam, grid=grid, degree=degree)
        ks = [psf_from_pupil(f, KERNEL_PX, guard=REF["guard"], oversample=REF["oversample"]).kernel for f in fits]
        _, t = timed(lambda: cold(lambda: fit_pupils(lens, batch_theta.ravel(), batch_depth.ravel(), 0.5876, grid=grid,
                                                     degree=degree)))
        rows.append([f"{grid}² rays, degree {degree}", max(f.fit_rms_waves for f in fits), err(ks),
                     t / batch_theta.size * 1e3])
    out.append("### Ray sampling and wavefront fit (exact trace; transform at reference settings)\n\n"
               + markdown_table(["rays / fit", "max fit residual (waves rms)", "max L1 error",
                                 "ms per entry (batch of 94)"], rows))
    # Fast models against the exact trace, at default settings.
    rows = []
    on_axis = {d: f for f, d, t in zip(default_fits, depth, theta) if t == 0.0 and lam[list(default_fits).index(f)] == 0.5876}
    for f in default_fits:
        if f.wavelength_um != 0.5876 or f.field_deg == 0.0:
            continue
        exact = psf_from_pupil(f, KERNEL_PX).kernel
        base = on_axis.get(f.depth_m) or fit_pupils(lens, 0.0, f.depth_m, 0.5876)[0]
        approx, t_e = timed(lambda: ellipse_psf(base, f.field_deg, KERNEL_PX).kernel)
        aw = axial_wavefront(lens, 587.6, f.depth_m)
        two = psf_from_pupil(two_term_fit(f, aw.two_term_w020_waves, aw.two_term_w040_waves), KERNEL_PX).kernel
        seidel = psf_from_pupil(two_term_fit(f, aw.w020_waves, aw.w040_waves), KERNEL_PX).kernel
        rows.append([f.field_deg, "inf" if math.isinf(f.depth_m) else f.depth_m, float(np.abs(approx - exact).sum()),
                     float(np.abs(two - exact).sum()), float(np.abs(seidel - exact).sum())])
    out.append("### The paper's approximations against the exact trace (587.6 nm, L1 error)\n\n"
               "Ellipse: on-axis traced pupil with a cos θ-compressed aperture. Two-term best fit: "
               "W020ρ² + W040ρ⁴ fitted to the traced wavefront. Two-term truncated: the traced power series "
               "cut after ρ⁴ (its W040 ≈ 2.46 λ, the Seidel-like value the paper quotes).\n\n"
               + markdown_table(["field °", "depth m", "ellipse", "two-term best fit", "two-term truncated"], rows))
    # Single PSF and per-shard costs.
    _, t_single = timed(lambda: cold(lambda: psf_from_pupil(fit_pupils(lens, 37.0, 1.3, 0.5876)[0], KERNEL_PX)), 5)
    _, _, cpu_single = timed_cpu(lambda: [cold(lambda: psf_from_pupil(fit_pupils(lens, 37.0, 1.3, 0.5876)[0],
                                                                      KERNEL_PX)) for _ in range(5)])
    spec = TensorSpec()
    tensor = PsfTensor(lens, spec, use_cache=False)
    _, t_shard = timed(lambda: tensor.ensure([50], range(len(spec.depth_m))))
    n_shard = len(spec.depth_m) * len(spec.channels)
    base = fit_pupils(lens, 0.0, 1.3, 0.5876)[0]
    _, t_ellipse = timed(lambda: ellipse_psf(base, 37.0, KERNEL_PX), 5)
    rows = [["single PSF, exact (trace + fit + transform), best wall", t_single * 1e3],
            ["single PSF, exact, mean CPU", cpu_single / 5 * 1e3],
            ["single PSF, ellipse model (transform only, pupil reused)", t_ellipse * 1e3],
            [f"one θ shard of the tensor ({n_shard} PSFs), per PSF", t_shard / n_shard * 1e3]]
    est = t_shard * len(spec.field_deg)
    out.append("### Cost\n\n" + markdown_table(["what", "ms"], rows)
               + f"\n\nDefault tensor ({len(spec.channels)}×{len(spec.field_deg)}×{len(spec.depth_m)} kernels of "
               f"{KERNEL_PX}²), extrapolated from one shard: {est:.0f} s single process.")
    if full:
        tensor = PsfTensor(lens, spec, use_cache=False)
        _, wall, cpu = timed_cpu(lambda: tensor.ensure_all(progress=True))
        out.append(f"Full default tensor built from scratch over {os.cpu_count()} processes: {wall:.1f} s wall, "
                   f"{cpu:.1f} s CPU in all ({cpu / tensor.filled.size * 1e3:.1f} ms CPU per PSF), "
                   f"peak resident memory {peak_rss_mb():.0f} MB (main process).")
    return "\n\n".join(out)


def register(subparsers) -> None:
    register_target(subparsers, "psf", "PSF accuracy against run time; tensor build time and memory", __doc__, "PSF (optics engine)", run)
