"""`bmi demo` (the `make demo` target): the SDK's main job on the embedded default.

Today: the lens report and a PSF gallery across depth and field. Later stages
(acquire → infer → outputs) join as they land.
"""

from __future__ import annotations

from pathlib import Path


def _run(args) -> int:
    from bmi_sdk.cli.lens import _print_table
    from bmi_sdk.optics import get_lens, lens_report
    from bmi_sdk.optics.gallery import psf_gallery

    out = Path(args.out)
    lens = get_lens("bmi_monocentric")
    _print_table(lens_report(lens))
    gallery = out / "psf_gallery.png"
    psf_gallery(lens, gallery)
    print(f"wrote {gallery}")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("demo", help="run the SDK's main job on the embedded default scene",
                              description=__doc__)
    p.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    p.set_defaults(handler=_run)
