"""`bmi calibrate`: fit the lens's hardware errors from point-source captures (or a simulated device)."""

from __future__ import annotations

import logging
import time
from pathlib import Path

from ..option_values import SEED, OptionError, whole
from ._logging import bars_shown


def _outputs(out: str) -> list[Path]:
    """The files ``calibration.io.write_calibration`` writes for calibration file ``out``."""
    path = Path(out)
    tensor = path.with_name(path.stem + ".psf.npz")
    return [path, tensor, tensor.with_suffix(".json"), path.with_suffix(".png")]


def _show_step(bar, stage: str, done: int) -> None:
    """Move the fit's bar to step ``done`` and name the step."""
    bar.set_postfix_str(stage, refresh=False)
    bar.update(done - bar.n)


def degeneracy_lines(degeneracies: list[dict]) -> list[str]:
    """One short line per degeneracy of a fit (``FitResult.degeneracies``): the parameters and the correlation
    or the 1σ; the advice on captures that would separate them is logged at -v."""
    lines = []
    for d in degeneracies:
        what = " / ".join(d["parameters"])
        if "correlation" in d:
            lines.append(f"degenerate: {what} (correlation {d['correlation']:+.2f}; -v: captures that separate them)")
        else:
            lines.append(f"degenerate: {what} (1σ {d['sigma']:.3g} beyond the paper's range; -v: what to do)")
    return lines


def _run(args) -> int:
    # Submodules, not the package: an editable install made before calibration/ had an __init__.py
    # resolves ``calibration`` as a namespace package outside the repository root.
    from tqdm import tqdm

    from calibration.extract import extract_spots
    from calibration.fit import fit_calibration
    from calibration.io import write_calibration
    from calibration.targets import CalibrationError, CapturePlan, load_captures, simulate_captures, standard_target

    from ._options import check_output_file, check_writable_folder, perturbation_option
    from ._outputs import refuse_existing

    if bool(args.captures) == bool(args.simulate):
        raise CalibrationError("give either --captures DIR (real or saved captures) or --simulate NAME=VALUE ...")
    check_output_file("--out", args.out, (".json",))  # a wrong name or folder fails before the capture and fit
    if args.save_captures:
        check_writable_folder("--save-captures", args.save_captures)
    if args.captures and not Path(args.captures).is_dir():
        raise OptionError(f"--captures {args.captures}: no such folder", "--captures")
    if not args.overwrite:  # before minutes of capturing and fitting
        refuse_existing(_outputs(args.out))
        if args.save_captures and Path(args.save_captures).is_dir() and any(Path(args.save_captures).iterdir()):
            raise FileExistsError(f"--save-captures folder {args.save_captures} is not empty; pass --overwrite to "
                                  "write into it, or choose another folder")
    free = {}
    for name in args.fix or []:
        free[name] = False
    if args.captures:
        captures = load_captures(args.captures)
    else:
        truth = perturbation_option("--simulate", args.simulate)
        t0 = time.perf_counter()
        captures = simulate_captures(standard_target(args.points, args.held_out), CapturePlan(), truth, seed=args.seed)
        print(f"simulated {sum(len(f) for f in captures.frames)} ROI frames of {len(captures.target.sources)} point "
              f"sources through sim:// in {time.perf_counter() - t0:.1f} s (injected {truth.to_dict()})")
        if args.save_captures:
            captures.save(args.save_captures, overwrite=args.overwrite)
            print(f"wrote captures to {args.save_captures}")
    t0 = time.perf_counter()
    extraction = extract_spots(captures)
    for i, reason in extraction.rejected:
        print(f"source {i} rejected: {reason}")
    with tqdm(total=args.max_outer + 2, desc="fit", unit="step", disable=not bars_shown()) as bar:
        result = fit_calibration(extraction, free=free, method=args.method, max_outer=args.max_outer,
                                 on_step=lambda stage, done, total: _show_step(bar, stage, done))
    calib = write_calibration(args.out, result, captures, extraction, method=args.method)
    elapsed = time.perf_counter() - t0
    truth = captures.injected
    tv = None if truth is None else truth.to_vector()
    from bmi_sdk.optics.perturb import VECTOR_NAMES

    for j, name in enumerate(VECTOR_NAMES):
        line = f"  {name:26s} {result.vector[j]: .4f} ± {result.sigma[j]:.4f}"
        if tv is not None:
            line += f"   injected {tv[j]: .4f}  ({(result.vector[j] - tv[j]) / result.sigma[j]:+.2f} σ)"
        print(line)
    for line in degeneracy_lines(result.degeneracies):
        print(line)
    for advice in dict.fromkeys(d["advice"] for d in result.degeneracies):  # each piece of advice once
        logging.getLogger("bmi.calibrate").info("%s", advice)
    held = result.held_out
    if held:
        print("held-out χ²/dof: calibrated " + ", ".join(f"{h['chi2_reduced']:.2f}" for h in held)
              + "; nominal " + ", ".join(f"{h['chi2_reduced_nominal']:.0f}" for h in held))
    print(f"wrote {args.out} (id {calib.id}), {calib.doc['corrected_tensor']['file']} and "
          f"{calib.doc.get('report_png')}; fit χ²/dof {result.chi2_reduced:.3f}, calibration {elapsed:.1f} s "
          f"(capture simulation excluded)")
    return 0


def register(subparsers) -> None:
    from bmi_sdk.optics.perturb import PARAMETERS

    p = subparsers.add_parser(
        "calibrate", help="measure the lens's hardware errors from point-source captures; write a calibration",
        description="Fits psf_shift_px, psf_scale_pct, decenter_um, tilt_arcmin, stray_light_fraction and "
                    "sensor_radius_error_pct to point-source captures and writes CALIB.json, the corrected PSF "
                    "tensor (CALIB.psf.npz) and a PNG report (docs/calibration.md).")
    p.add_argument("--captures", help="captures folder (captures.json + DNGs)")
    p.add_argument("--simulate", action="append", metavar="NAME=VALUE",
                   help="capture the standard target through the simulated camera with this error injected "
                        "(repeat; e.g. decenter_um=10,0 stray_light_fraction=0.03)")
    p.add_argument("--seed", type=SEED, default=0, help="noise seed of the simulated captures (0 … 2³²−1)")
    p.add_argument("--points", type=whole(4, 21), default=13,
                   help="fit sources in the simulated standard target (4 … 21)")
    p.add_argument("--held-out", type=whole(0, 6), default=4,
                   help="held-out sources in the simulated standard target (0 … 6)")
    p.add_argument("--save-captures", help="also write the simulated captures to this folder")
    p.add_argument("--fix", action="append", choices=PARAMETERS, help="hold this parameter at 0 (repeatable)")
    p.add_argument("--method", choices=("lm", "gn"), default="lm", help="jaxopt LevenbergMarquardt or GaussNewton")
    p.add_argument("--max-outer", type=whole(1, 20), default=4, help="relinearisations of the exact engine (1 … 20)")
    p.add_argument("--out", required=True, help="calibration file (.json)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an earlier calibration's files (and write into a non-empty --save-captures "
                        "folder); default: refuse them, before any capture or fit")
    p.set_defaults(handler=_run)
