"""`bmi psf export|build|warm`: one pixel-integrated PSF, the whole PSF tensor, or a camera's decoder kernels traced
ahead of its first frame."""

from __future__ import annotations

import time
from pathlib import Path

from ..option_values import number, whole
from ._logging import bars_shown


def kernel_png(kernel):
    """uint16 image of a kernel normalised to its peak (peak → 65535): a view, not the kernel's values."""
    import numpy as np

    peak = float(kernel.max())
    if not peak > 0:
        raise ValueError("the kernel has no positive value to normalise to")
    return np.round(np.clip(kernel / peak, 0, 1) * 65535).astype(np.uint16)


def _kernel_format(path: str) -> str:
    """"npy" or "png" from the output's name; any other name is refused (checked before the PSF is traced)."""
    for fmt in ("npy", "png"):
        if path.lower().endswith("." + fmt):
            return fmt
    raise ValueError(f"--out {path}: name it .npy (the float kernel) or .png (a 16-bit view of it)")


def _write_kernel(path: str, kernel) -> str:
    """``.npy``: the float32 kernel (sum 1); ``.png``: ``kernel_png``. Returns what was written, in words."""
    import numpy as np

    from bmi_sdk.io_atomic import atomic_path, save_npy

    if _kernel_format(path) == "npy":
        save_npy(path, kernel.astype(np.float32))
        return "float32 kernel, sum 1"
    import cv2

    with atomic_path(path, suffix=".png") as tmp:
        if not cv2.imwrite(str(tmp), kernel_png(kernel)):
            raise OSError(f"OpenCV could not write {path}")
    return "16-bit PNG normalised to the peak (a view; the .npy keeps the values)"


def _export(args) -> int:
    from bmi_sdk.optics import fit_pupil, get_lens, psf_from_pupil
    from bmi_sdk.optics.export_limits import check_export_request, check_kernel

    from ._outputs import refuse_existing

    _kernel_format(args.out)  # a wrong name fails before the PSF is traced
    if not args.overwrite:
        refuse_existing([args.out])
    lens = get_lens(args.lens)
    check_export_request(lens, args.field_deg, args.depth_m, args.wavelength_nm, args.pitch_um)
    fit = fit_pupil(lens, args.field_deg, args.depth_m, args.wavelength_nm * 1e-3)
    psf = psf_from_pupil(fit, args.kernel_px, args.pitch_um, args.oversample)
    check_kernel(psf, args.kernel_px)
    what = _write_kernel(args.out, psf.kernel)
    print(f"wrote {args.out}: {args.kernel_px}×{args.kernel_px} {what}, energy captured {psf.energy_captured:.5f}, "
          f"pupil fit residual {fit.fit_rms_waves:.1e} waves")
    return 0


def _build(args) -> int:
    from bmi_sdk.optics import PsfTensor, TensorSpec, get_lens, spectral_channels

    from ._outputs import refuse_existing

    lens = get_lens(args.lens)
    out = Path(args.out or f"psf_tensor_{lens.name}.npz").with_suffix(".npz")
    if not args.overwrite:  # before minutes of tracing; the metadata X.json could be another file's (a calibration)
        refuse_existing([out, out.with_suffix(".json")])
    channels = spectral_channels(args.spectral)
    spec = TensorSpec(channels=channels, kernel_px=args.kernel_px)
    tensor = PsfTensor(lens, spec, use_cache=False)  # from scratch, ignoring any cache
    start = time.perf_counter()
    tensor.ensure_all(progress=bars_shown())
    elapsed = time.perf_counter() - start
    out = tensor.save(out, float16=args.float16)
    print(f"wrote {out} and {out.with_suffix('.json')}: {tensor.data.shape} in {elapsed:.1f} s")
    return 0


def _warm(args) -> int:
    import json

    from bmi_sdk.built_camera import BuiltCamera
    from bmi_sdk.cli.infer import check_texture_exponent
    from bmi_sdk.runtime.classical import warm_kernels
    from bmi_sdk.runtime.decoders import DecoderOptions, open_decoder

    roi = None
    if args.frame is not None:  # the camera that took the frame, as `bmi infer` builds it
        from bmi_sdk.runtime.job import camera_for
        from devices.dng import load_raw

        frame = load_raw(args.frame)
        camera, _ = camera_for(frame, args.calibration)
        roi = (frame.roi.y_px, frame.roi.x_px, *frame.data.shape)
    elif args.calibration is not None:
        from calibration.io import load_calibration

        camera = BuiltCamera.from_calibration(load_calibration(args.calibration))
    else:
        camera = BuiltCamera(lens_name=args.lens)
    check_texture_exponent(args.decoder, args.texture_exponent)
    options = DecoderOptions(texture_exponent=args.texture_exponent)
    stage = getattr(open_decoder(camera, args.decoder, args.model, options=options), "stage", None)  # as bmi infer
    if stage is None:
        raise ValueError(f"--decoder {args.decoder} reads no kernels of the camera: nothing to warm")
    report = warm_kernels(camera, stage.config, roi=roi, workers=args.workers, progress=bars_shown(args.quiet))
    print(json.dumps(report) if args.json else
          f"camera {report['camera_sha256'][:12]}…: {report['zones']} zones, {report['kernel_sets_traced']} of "
          f"{report['kernel_sets']} kernel sets traced ({report['kernel_sets'] - report['kernel_sets_traced']} "
          f"already cached), {report['evidence_models_made']} evidence models made, in {report['wall_s']:.1f} s → "
          f"{report['cache_dir']}")
    return 0


def register(subparsers) -> None:
    from bmi_sdk.decode.classical import TEXTURE_EXPONENTS
    from bmi_sdk.lenses import DEFAULT_LENS, LENS_KERNEL_PX
    from bmi_sdk.runtime.decoders import DECODERS, DEFAULT_DECODER

    p = subparsers.add_parser("psf", help="export one PSF or build the PSF tensor",
                              description="Pixel-integrated PSFs computed from the exact traced wavefront.")
    sub = p.add_subparsers(dest="psf_command", metavar="ACTION")
    e = sub.add_parser("export", help="write one PSF (.npy float, or a .png view; odd size, centred on the chief ray)",
                       description="One pixel-integrated PSF on the sensor's tangent plane: rows sagittal, "
                                   "columns radial (+col away from the optical centre).")
    e.add_argument("--wavelength-nm", type=number(365, 1014, unit="nm"), required=True,
                   help="365–1014 nm (where the glass catalogue's dispersion formulas hold)")
    e.add_argument("--depth-m", type=number(0, lo_open=True, unit="m (or inf)", allow_inf=True), required=True,
                   help="range from the lens centre in metres, or 'inf'")
    e.add_argument("--field-deg", type=number(0, 80, unit="°"), required=True,
                   help="0–80° (beyond, the traced PSF is not valid)")
    e.add_argument("--out", required=True,
                   help="output: NAME.npy, the float32 kernel (sum 1); or NAME.png, a viewable 16-bit image of "
                        "the kernel normalised to its peak (peak = 65535; not the kernel's values)")
    e.add_argument("--lens", default=DEFAULT_LENS)
    e.add_argument("--kernel-px", type=whole(1, unit="px", odd=True), default=41,
                   help="odd kernel size (default 41: ≥ 99 %% energy at 0.7 m)")
    e.add_argument("--pitch-um", type=number(0.5, 5, unit="µm"), default=2.0, help="pixel pitch, 0.5–5 µm (default 2)")
    e.add_argument("--oversample", type=whole(1, odd=True), default=3,
                   help="odd sub-samples per pixel for pixel integration")
    e.add_argument("--overwrite", action="store_true", help="replace an existing --out (default: refuse it)")
    e.set_defaults(handler=_export)
    b = sub.add_parser("build", help="build the whole default tensor from scratch and write it",
                       description="PSF(c, θ, d): 3 channels × θ 0–60° every 0.6° × d 0.7–10 m every 0.1 m, "
                                   "ignoring any cache; writes PATH (.npz) and PATH's .json metadata.")
    b.add_argument("--lens", default=DEFAULT_LENS)
    b.add_argument("--out", help="output .npz (default psf_tensor_<lens>.npz)")
    b.add_argument("--kernel-px", type=whole(1, unit="px", odd=True), default=41)
    b.add_argument("--spectral", action="store_true",
                   help="integrate each channel over 13 wavelengths of the RGB response instead of one")
    b.add_argument("--float16", action="store_true", help="store float16 at rest (half the size)")
    b.add_argument("--overwrite", action="store_true",
                   help="replace an existing --out and its .json (default: refuse them, before tracing)")
    b.set_defaults(handler=_build)
    w = sub.add_parser("warm", help="trace a camera's decoder kernels (and make their evidence models) into the PSF "
                       "cache before its first frame",
                       description="Traces every kernel a frame's decode can read, at every zone of the sensor (or "
                                   "of --frame's window), and makes their evidence models, into the PSF cache "
                                   "($BMI_CACHE_DIR/psf): the first full frame then decodes as fast as later ones. "
                                   "A second run traces and makes nothing.")
    w.add_argument("--calibration", metavar="FILE", help="calibration from bmi calibrate (default: nominal PSFs)")
    w.add_argument("--frame", metavar="RAW.dng",
                   help="warm for this frame's camera and window, exactly as bmi infer builds them")
    w.add_argument("--decoder", choices=tuple(DECODERS), default=DEFAULT_DECODER,
                   help=f"whose knobs (candidates) to trace for, e.g. the learned model's classical stage or the "
                        f"classical decoder's (default {DEFAULT_DECODER})")
    w.add_argument("--model", help="learned model whose manifest names its classical knobs (default: the packaged one)")
    w.add_argument("--texture-exponent", choices=tuple(TEXTURE_EXPONENTS), default="prior",
                   help="bmi infer's --texture-exponent: profiled makes the exact models of its three slopes "
                        "(default prior)")
    w.add_argument("--lens", default=DEFAULT_LENS, choices=tuple(LENS_KERNEL_PX),
                   help="lens of a nominal camera (without --calibration)")
    w.add_argument("--workers", type=whole(1, 64), default=1, help="processes tracing zones side by side (default 1)")
    w.add_argument("--json", action="store_true", help="print the report as JSON")
    w.add_argument("--quiet", action="store_true", help="no progress bar")
    w.set_defaults(handler=_warm)
    p.set_defaults(handler=lambda args: p.print_help() or 2)
