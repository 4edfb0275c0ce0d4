"""`bmi psf export|build`: one pixel-integrated PSF, or the whole PSF tensor."""

from __future__ import annotations

import math
import time


def _depth(text: str) -> float:
    value = math.inf if text.lower() in ("inf", "infinity") else float(text)
    if not value > 0:
        raise ValueError(f"depth must be > 0 m or 'inf', got {text}")
    return value


def _export(args) -> int:
    import numpy as np

    from bmi_sdk.io_atomic import save_npy
    from bmi_sdk.optics import fit_pupil, get_lens, psf_from_pupil

    from bmi_sdk.optics.export_limits import check_export_request, check_kernel

    lens = get_lens(args.lens)
    check_export_request(lens, args.field_deg, args.depth_m, args.wavelength_nm, args.pitch_um)
    fit = fit_pupil(lens, args.field_deg, args.depth_m, args.wavelength_nm * 1e-3)
    psf = psf_from_pupil(fit, args.kernel_px, args.pitch_um, args.oversample)
    check_kernel(psf, args.kernel_px)
    save_npy(args.out, psf.kernel.astype(np.float32))
    print(f"wrote {args.out}: {args.kernel_px}×{args.kernel_px}, sum 1, energy captured {psf.energy_captured:.5f}, "
          f"pupil fit residual {fit.fit_rms_waves:.1e} waves")
    return 0


def _build(args) -> int:
    from bmi_sdk.optics import PsfTensor, TensorSpec, get_lens, spectral_channels

    lens = get_lens(args.lens)
    channels = spectral_channels(args.spectral)
    spec = TensorSpec(channels=channels, kernel_px=args.kernel_px)
    tensor = PsfTensor(lens, spec, use_cache=False)  # from scratch, ignoring any cache
    start = time.perf_counter()
    tensor.ensure_all(progress=True)
    elapsed = time.perf_counter() - start
    out = tensor.save(args.out or f"psf_tensor_{lens.name}.npz", float16=args.float16)
    print(f"wrote {out} and {out.with_suffix('.json')}: {tensor.data.shape} in {elapsed:.1f} s")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("psf", help="export one PSF or build the PSF tensor",
                              description="Pixel-integrated PSFs computed from the exact traced wavefront.")
    sub = p.add_subparsers(dest="psf_command", metavar="ACTION")
    e = sub.add_parser("export", help="write one PSF (.npy, odd size, centred on the chief ray, sum 1)",
                       description="One pixel-integrated PSF on the sensor's tangent plane: rows sagittal, "
                                   "columns radial (+col away from the optical centre).")
    e.add_argument("--wavelength-nm", type=float, required=True)
    e.add_argument("--depth-m", type=_depth, required=True, help="range from the lens centre in metres, or 'inf'")
    e.add_argument("--field-deg", type=float, required=True)
    e.add_argument("--out", required=True, help="output .npy")
    e.add_argument("--lens", default="bmi_monocentric")
    e.add_argument("--kernel-px", type=int, default=41, help="odd kernel size (default 41: ≥ 99 %% energy at 0.7 m)")
    e.add_argument("--pitch-um", type=float, default=2.0)
    e.add_argument("--oversample", type=int, default=3, help="odd sub-samples per pixel for pixel integration")
    e.set_defaults(handler=_export)
    b = sub.add_parser("build", help="build the whole default tensor from scratch and write it",
                       description="PSF(c, θ, d): 3 channels × θ 0–60° every 0.6° × d 0.7–10 m every 0.1 m, "
                                   "ignoring any cache; writes PATH (.npz) and PATH's .json metadata.")
    b.add_argument("--lens", default="bmi_monocentric")
    b.add_argument("--out", help="output .npz (default psf_tensor_<lens>.npz)")
    b.add_argument("--kernel-px", type=int, default=41)
    b.add_argument("--spectral", action="store_true",
                   help="integrate each channel over 13 wavelengths of the RGB response instead of one")
    b.add_argument("--float16", action="store_true", help="store float16 at rest (half the size)")
    b.set_defaults(handler=_build)
    p.set_defaults(handler=lambda args: p.print_help() or 2)
