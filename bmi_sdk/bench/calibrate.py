"""`bmi bench calibrate`: hardware-error recovery, honesty of the 1σ, point sources and iterations against time.

Every run draws seeded random perturbations uniformly within the paper's ranges
(shift ≤ 0.5 px, scale ≤ 5 %, decenter ≤ 10 µm, tilt ≤ 1′, stray light ≤ 3 %,
sensor radius ≤ 2 %), captures the standard target through the simulated
camera at the standard noise (the SensorModel's shot + read noise, lamp
peaks at 60 % of full well, 4 repeats and 4 darks per exposure), extracts
and fits. Coverage is the fraction of |fit − truth| ≤ kσ; an honest σ gives
about 68 % (k = 1) and 95 % (k = 2). Times are the fit alone (capture
simulation excluded), on this machine as it was loaded.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from ..option_values import whole
from . import add_json_argument, check_record_path, emit, markdown_table

RECOVERY_SEEDS_QUICK = 8
RECOVERY_SEEDS_FULL = 50


def one_seed(seed: int, n_points: int = 13, n_held_out: int = 4, max_outer: int = 4) -> dict:
    """Capture + fit one random perturbation; truth, estimate, σ, history, held-out χ², times."""
    from bmi_sdk.optics.perturb import Perturbation

    # Submodules, not the package: an editable install made before calibration/ had an __init__.py
    # resolves ``calibration`` as a namespace package outside the repository root.
    from calibration.extract import extract_spots
    from calibration.fit import fit_calibration
    from calibration.targets import CapturePlan, simulate_captures, standard_target

    truth = Perturbation.random(np.random.default_rng(seed))
    t0 = time.perf_counter()
    captures = simulate_captures(standard_target(n_points, n_held_out), CapturePlan(), truth, seed=seed)
    t_capture = time.perf_counter() - t0
    t0 = time.perf_counter()
    result = fit_calibration(extract_spots(captures), max_outer=max_outer)
    t_fit = time.perf_counter() - t0
    return {"seed": seed, "n_points": n_points, "truth": truth.to_vector().tolist(), "fit": result.vector.tolist(),
            "sigma": result.sigma.tolist(), "history": [h.tolist() for h in result.history],
            "chi2_reduced": result.chi2_reduced, "outer_iterations": result.outer_iterations,
            "held_out_chi2": [h["chi2_reduced"] for h in result.held_out],
            "held_out_chi2_nominal": [h["chi2_reduced_nominal"] for h in result.held_out],
            "degenerate_pairs": [d["parameters"] for d in result.degeneracies],
            "capture_s": t_capture, "fit_s": t_fit}


def recovery_table(records: list) -> str:
    from bmi_sdk.optics.perturb import UNITS, VECTOR_NAMES

    truth = np.array([r["truth"] for r in records])
    fit = np.array([r["fit"] for r in records])
    sigma = np.array([r["sigma"] for r in records])
    err = fit - truth
    z = err / sigma
    rows = []
    for j, name in enumerate(VECTOR_NAMES):
        unit = UNITS[name.split("[")[0]]
        rows.append([name, unit, float(np.sqrt(np.mean(err[:, j] ** 2))), float(np.max(np.abs(err[:, j]))),
                     float(np.median(sigma[:, j])), f"{np.mean(np.abs(z[:, j]) <= 1) * 100:.0f} %",
                     f"{np.mean(np.abs(z[:, j]) <= 2) * 100:.0f} %", float(np.std(z[:, j]))])
    held = np.array([c for r in records for c in r["held_out_chi2"]])
    nominal = np.array([c for r in records for c in r["held_out_chi2_nominal"]])
    fit_s = np.array([r["fit_s"] for r in records])
    cap_s = np.array([r["capture_s"] for r in records])
    text = markdown_table(["parameter", "unit", "RMS error", "max abs error", "median 1σ", "abs err ≤ 1σ", "abs err ≤ 2σ",
                           "std(err/σ)"], rows)
    text += (f"\n\n{len(records)} seeds ({records[0]['seed']}–{records[-1]['seed']}), {records[0]['n_points']} fit "
             f"sources + {len(records[0]['held_out_chi2'])} held out. Held-out χ²/dof (PSF + position predicted by the "
             f"calibration, only flux and background fitted): median {np.median(held):.3f}, 95th percentile "
             f"{np.percentile(held, 95):.3f}; with the nominal (design) PSFs: median {np.median(nominal):.0f}. "
             f"Fit χ²/dof median {np.median([r['chi2_reduced'] for r in records]):.3f}. Fit time median "
             f"{np.median(fit_s):.1f} s, max {fit_s.max():.1f} s; capture simulation median {np.median(cap_s):.1f} s.")
    return text


def _iterations_table(record: dict) -> str:
    from bmi_sdk.optics.perturb import VECTOR_NAMES

    truth = np.array(record["truth"])
    sigma = np.array(record["sigma"])
    rows = []
    for i, h in enumerate(record["history"]):
        z = np.abs(np.array(h) - truth) / sigma
        rows.append([i, float(np.max(z)), float(np.sqrt(np.mean(z**2))), VECTOR_NAMES[int(np.argmax(z))]])
    return markdown_table(["outer iterations", "max abs err/σ", "RMS err/σ", "worst parameter"], rows)


def run(full: bool = False, seeds: int | None = None, out_json: str | None = None) -> str:
    n_seeds = seeds or (RECOVERY_SEEDS_FULL if full else RECOVERY_SEEDS_QUICK)
    records = []
    for seed in range(n_seeds):
        records.append(one_seed(seed))
        print(f"seed {seed}: fit {records[-1]['fit_s']:.1f} s, χ² {records[-1]['chi2_reduced']:.3f}", flush=True)
        if out_json:
            Path(out_json).write_text(json.dumps(records))
    out = ["### Recovery over random perturbations (standard target, 13 + 4 held-out sources)\n\n"
           + recovery_table(records)]
    out.append("### Outer iterations (relinearisations) against error, seed 0\n\n" + _iterations_table(records[0]))
    rows = []
    for n_points in (5, 9, 13, 17):
        r = one_seed(1000 + n_points, n_points=n_points)
        z = np.abs(np.array(r["fit"]) - np.array(r["truth"])) / np.array(r["sigma"])
        rows.append([n_points, float(np.median(r["sigma"][2:3])), float(np.median(np.array(r["sigma"])[3:5])),
                     float(np.max(z)), r["outer_iterations"], r["fit_s"]])
    out.append("### Number of point sources against uncertainty and time (one seed each)\n\n"
               + markdown_table(["fit sources", "1σ scale %", "1σ decenter µm", "max abs err/σ", "outer iterations",
                                 "fit s"], rows))
    return "\n\n".join(out)


def register(subparsers) -> None:
    def handler(args) -> int:
        check_record_path(args.json, args.overwrite)
        emit(run(full=args.full, seeds=args.seeds, out_json=args.records), args.json, args.overwrite)
        return 0

    p = subparsers.add_parser("calibrate", help="hardware-error calibration: recovery, σ coverage, points and "
                              "iterations against time", description=__doc__)
    p.add_argument("--full", action="store_true", help=f"{RECOVERY_SEEDS_FULL} recovery seeds instead of "
                   f"{RECOVERY_SEEDS_QUICK} (about a minute each here)")
    p.add_argument("--seeds", type=whole(1), default=None, help="number of recovery seeds (overrides --full)")
    p.add_argument("--records", default=None, metavar="PATH",
                   help="also write every seed's fit to this JSON file as it goes")
    add_json_argument(p)
    p.set_defaults(handler=handler)
