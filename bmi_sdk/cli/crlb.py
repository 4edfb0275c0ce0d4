"""`bmi crlb`: the Cramér–Rao bound on depth against depth and field, for both lenses (paper §3.2)."""

from __future__ import annotations

import argparse
import logging
import sys
import time

from ..option_values import number, whole

LENS_PROFILES = {"monocentric": "bmi_monocentric", "fisheye": "fisheye"}
"""--lenses name → the lens profile (bmi_sdk.lenses) it stands for."""
LENSES = tuple(LENS_PROFILES)
DEFAULT_DEPTHS_M = (1.0, 1.5, 2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0)
DEFAULT_FIELDS_DEG = (0.0, 30.0, 45.0, 60.0)


MIN_DEPTH_M = 0.1
"""Nearest range of --depths-m: the lens's front surface is 4 mm from its centre; nearer than 0.1 m no kernel of
a usable size holds the PSF."""
MAX_DEPTH_M = 100.0
"""Farthest finite range of --depths-m (the traced pupil fits lose precision beyond; 'inf' is traced exactly)."""
MAX_FIELD_DEG = 80.0
"""Widest --fields-deg: the traced PSF is valid to 80° (docs/reliability.md; NaN from 81°)."""


def _number_list(text: str, check) -> list[float]:
    """A comma list of numbers, each passed through the argparse type ``check``."""
    items = [item.strip() for item in text.split(",")]
    if not all(items):
        raise argparse.ArgumentTypeError(f"{text!r} is not a comma list of numbers")
    return [check(item) for item in items]


def _depths(text: str) -> list[float]:
    return _number_list(text, number(MIN_DEPTH_M, MAX_DEPTH_M, unit="m (or inf)", allow_inf=True))


def _fields(text: str) -> list[float]:
    return _number_list(text, number(0, MAX_FIELD_DEG, unit="°"))


def _lenses(text: str) -> list[str]:
    names = [t.strip() for t in text.split(",") if t.strip()]
    bad = [n for n in names if n not in LENSES]
    if bad or not names:
        raise argparse.ArgumentTypeError(f"a comma list of {', '.join(LENSES)}, got {text!r}")
    return names


def _lens(name: str):
    from bmi_sdk.optics import get_lens

    return get_lens(LENS_PROFILES[name])


def _plot(rows: list[dict], path: str, conventions: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from bmi_sdk.io_atomic import atomic_path

    fig, ax = plt.subplots(figsize=(6.4, 4.2), dpi=100)
    fields = sorted({r["field_deg"] for r in rows})
    colours = plt.cm.viridis([i / max(len(fields) - 1, 1) * 0.85 for i in range(len(fields))])
    styles = {"monocentric": ("-", "o"), "fisheye": ("--", "s")}
    for lens in LENSES:
        for field_deg, colour in zip(fields, colours):
            pts = sorted((r["depth_m"], r["crlb_mm"]) for r in rows if r["lens"] == lens and r["field_deg"] == field_deg
                         and r["depth_m"] is not None and r["crlb_mm"] is not None)
            if pts:
                line, marker = styles[lens]
                ax.plot([p[0] for p in pts], [p[1] for p in pts], line, marker=marker, ms=3.5, color=colour,
                        label=f"{lens} {field_deg:g}°")
    ax.set_yscale("log")
    ax.set_xlabel("depth (m, range from the lens centre)")
    ax.set_ylabel("CRLB σ_d (mm)")
    ax.set_title(f"Depth CRLB ({conventions})", fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def _run(args) -> int:
    import json

    import numpy as np

    from bmi_sdk.optics.crlb import MIN_ENERGY_CAPTURED, CrlbSettings, cos_throughput, crlb

    if args.plot:
        import matplotlib  # noqa: F401  (a missing [plot] extra stops the command now, not after minutes of work)

    settings = CrlbSettings(patch_px=args.patch_px, spectrum_exponent=args.spectrum_exponent,
                            spectrum_kind=args.spectrum_kind, rms_contrast=args.rms_contrast,
                            noise_sigma=CrlbSettings().noise_sigma if args.noise_sigma is None else args.noise_sigma,
                            inverse_step_per_m=args.inverse_step_per_m)
    kernel_px = {"monocentric": args.kernel_px_monocentric, "fisheye": args.kernel_px_fisheye}
    field_grid, depth_grid = np.meshgrid(np.asarray(args.fields_deg), np.asarray(args.depths_m), indexing="ij")
    throughput = (lambda f: np.ones_like(np.asarray(f, dtype=np.float64))) if args.no_throughput else cos_throughput
    rows = []
    for name in args.lenses:
        start = time.perf_counter()
        points = crlb(_lens(name), field_grid.ravel(), depth_grid.ravel(), kernel_px[name], settings, throughput)
        print(f"{name}: {len(points)} points in {time.perf_counter() - start:.1f} s", file=sys.stderr)
        for p in points:
            row = p.to_dict()
            row["lens"] = name
            if p.energy_captured_min < MIN_ENERGY_CAPTURED:
                logging.getLogger("bmi.crlb").warning(
                    f"{name} {p.field_deg:g}° {p.depth_m:g} m: the {kernel_px[name]} px kernel holds only "
                    f"{p.energy_captured_min:.3f} of the energy; raise --kernel-px-{name}")
            rows.append(row)
    if args.plot:
        noise = "8-bit quantisation" if args.noise_sigma is None else f"σ = {settings.noise_sigma:g}"
        conventions = (f"{settings.spectrum_kind} 1/f^{settings.spectrum_exponent:g}, {settings.patch_px} px patch, "
                       f"RMS contrast {settings.rms_contrast:g}, {noise} noise, "
                       f"T = {'1' if args.no_throughput else 'cos θ'}")
        _plot(rows, args.plot, conventions)
        print(f"wrote {args.plot}", file=sys.stderr)
    if args.json:
        print(json.dumps(rows, indent=1))
    else:
        print(f"{'lens':<12} {'field_deg':>9} {'depth_m':>8} {'crlb_mm':>12}")
        for r in rows:
            depth = "inf" if r["depth_m"] is None else f"{r['depth_m']:g}"
            bound = "inf" if r["crlb_mm"] is None else f"{r['crlb_mm']:.4g}"
            print(f"{r['lens']:<12} {r['field_deg']:>9g} {depth:>8} {bound:>12}")
    return 0


def register(subparsers) -> None:
    from bmi_sdk.lenses import LENS_KERNEL_PX

    p = subparsers.add_parser(
        "crlb", help="Cramér–Rao bound on depth (paper §3.2) for the monocentric lens and the fisheye",
        description="σ_d ≥ I(d)^-1/2 with I = (1/σ²)(1/N²) Σ_c Σ_uv |S|² |T(θ) ∂OTF_c/∂d|² from exact traced "
                    "PSFs. Conventions: bmi_sdk/optics/crlb.py and docs/crlb.md. In --json output a null "
                    "crlb_mm means an infinite bound (no depth information), a null depth_m means infinity.")
    p.add_argument("--json", action="store_true", help="print one JSON row per (lens, field_deg, depth_m)")
    p.add_argument("--plot", metavar="PATH.png", help="write the bound against depth (log y) per field and lens")
    p.add_argument("--lenses", type=_lenses, default=list(LENSES), help="comma list of monocentric,fisheye")
    p.add_argument("--depths-m", type=_depths, default=list(DEFAULT_DEPTHS_M),
                   help="comma list of ranges in metres, 0.1–100 ('inf' allowed; default 1,1.5,2,3,4,5,6,8,10: ≈ 40 s on 2 cores)")
    p.add_argument("--fields-deg", type=_fields, default=list(DEFAULT_FIELDS_DEG),
                   help="comma list of field angles in degrees, 0–80 (default 0,30,45,60)")
    # default: each lens's kernel, holding ≥ 99 % of the energy at 1–10 m over 0–60° (docs/crlb.md)
    for name, profile in LENS_PROFILES.items():
        p.add_argument(f"--kernel-px-{name}", type=whole(1, 401, unit="px", odd=True), default=LENS_KERNEL_PX[profile],
                       help=f"PSF kernel side in pixels (default {LENS_KERNEL_PX[profile]}, the lens profile's)")
    p.add_argument("--patch-px", type=whole(2, 4096, unit="px"), default=256,
                   help="scene patch side N in pixels, 2–4096 (I ∝ N²)")
    p.add_argument("--spectrum-exponent", type=number(0, 4), default=0.8, help="α of the 1/f^α scene spectrum, 0–4")
    p.add_argument("--spectrum-kind", choices=("amplitude", "power"), default="amplitude",
                   help="whether 1/f^α is the amplitude |S| (default) or the power |S|²")
    p.add_argument("--rms-contrast", type=number(0, 1, lo_open=True), default=0.2,
                   help="scene standard deviation on [0, 1], > 0 (I ∝ c²)")
    p.add_argument("--noise-sigma", type=number(0, 1, lo_open=True), default=None,
                   help="noise standard deviation on [0, 1] (default 8-bit quantisation (1/255)/√12)")
    p.add_argument("--inverse-step-per-m", type=number(0, 0.1, lo_open=True, unit="m⁻¹"), default=0.01,
                   help="central-difference step in 1/d (m⁻¹) for ∂PSF/∂d, (0, 0.1]")
    p.add_argument("--no-throughput", action="store_true", help="T(θ) = 1 instead of cos θ")
    p.set_defaults(handler=_run)
