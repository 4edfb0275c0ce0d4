"""`bmi lens`: first-order data, Seidel sums and traced wavefronts of a lens."""

from __future__ import annotations

import json


def _print_table(report: dict) -> None:
    print(f"lens {report['lens']}  (sha256 {report['lens_sha256'][:12]})  at {report['wavelength_nm']} nm")
    for key in ("efl_mm", "epd_mm", "f_number", "petzval_radius_mm", "seidel_w040_waves", "stop_radius_mm",
                "paraxial_bfd_mm", "sensor_from_paraxial_focus_um"):
        print(f"  {key:32s} {report[key]: .5f}")
    print("  chief ray: " + ", ".join(f"{r['field_deg']:.0f}° → {r['image_radial_mm']:.4f} mm" for r in report["chief_ray"]))
    print(f"  {'λ nm':>7s} {'depth m':>8s} {'W020':>8s} {'W040':>8s} {'W060':>8s} {'rms':>7s} {'2-term err':>10s}  (waves)")
    for r in report["wavefront"]:
        depth = "inf" if r["depth_m"] is None else f"{r['depth_m']:.1f}"
        print(f"  {r['wavelength_nm']:7.1f} {depth:>8s} {r['w020_waves']:8.3f} {r['w040_waves']:8.3f} "
              f"{r['w060_waves']:8.3f} {r['rms_waves']:7.3f} {r['two_term_rms_error_waves']:10.4f}")


def _lens(name: str):
    """The lens ``--lens`` names; a name or file that is none, one line naming the option."""
    from bmi_sdk.optics import get_lens

    from ..option_values import OptionError

    try:
        return get_lens(name)
    except (ValueError, OSError) as exc:  # PrescriptionError is a ValueError
        raise OptionError(f"--lens {name}: {exc}", "--lens") from None


def _run(args) -> int:
    from bmi_sdk.optics import lens_report

    if args.write_sensor_mapping:
        from bmi_sdk.io_atomic import write_json
        from bmi_sdk.optics.report import sensor_mapping

        from ._options import check_output_file

        check_output_file("--write-sensor-mapping", args.write_sensor_mapping, (".json",))
        write_json(args.write_sensor_mapping, sensor_mapping(_lens(args.lens)))
        print(f"wrote {args.write_sensor_mapping}")
        return 0
    report = lens_report(_lens(args.lens))
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        _print_table(report)
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "lens", help="lens report: EFL, EPD, F-number, Petzval radius, Seidel W040, traced wavefronts",
        description="First-order data and Seidel sums at 587.6 nm, plus the exact traced axial wavefront "
                    "(W020, W040, W060, RMS, two-term model error) for 0.7–10 m and infinity at 656.3/587.6/486.1 nm. "
                    "Object distance is measured from the lens centre (the stop).")
    p.add_argument("--lens", default="bmi_monocentric",
                   help="built-in lens name (bmi_monocentric, fisheye) or a prescription JSON path")
    p.add_argument("--json", action="store_true", help="print JSON (keys efl_mm, epd_mm, f_number, "
                   "petzval_radius_mm, seidel_w040_waves, wavefront[...])")
    p.add_argument("--write-sensor-mapping", metavar="PATH", default=None,
                   help="write the traced chief-ray table (pixel ↔ field mapping) as JSON; "
                        "bmi_sdk/data/bmi_sensor_mapping.json is this for bmi_monocentric")
    p.set_defaults(handler=_run)
