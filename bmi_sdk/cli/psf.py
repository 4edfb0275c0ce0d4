"""`bmi psf export|build|warm|cache`: one pixel-integrated PSF, the whole PSF tensor, a camera's decoder kernels traced
ahead of its first frame, or what the PSF cache holds (and pruning it)."""

from __future__ import annotations

import time
from pathlib import Path

from ..option_values import OptionError, number, whole
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


def _cache(args) -> int:
    import json
    import time

    from bmi_sdk.optics.cache_store import cache_entries, prune
    from bmi_sdk.optics.tensor import default_cache_dir

    root = default_cache_dir()
    if args.prune and args.older_than_days is None and args.max_gb is None:
        raise OptionError("--prune needs --older-than-days DAYS, --max-gb GB or both", "--prune")
    if not args.prune and (args.older_than_days is not None or args.max_gb is not None or args.dry_run):
        raise OptionError("--older-than-days, --max-gb and --dry-run go with --prune", "--prune")
    removed = []
    if args.prune:
        removed = prune(root, None if args.older_than_days is None else args.older_than_days * 86400.0,
                        None if args.max_gb is None else int(args.max_gb * 1e9), dry_run=args.dry_run)
    gone = {e.path for e in removed}  # a dry run's are still listed
    kept = [e for e in cache_entries(root) if e.path not in gone]
    if args.json:
        print(json.dumps({"cache_dir": str(root), "entries": [e.to_dict(root) for e in kept],
                          "size_bytes": sum(e.size_bytes for e in kept),
                          "removed": [e.to_dict(root) for e in removed], "dry_run": args.dry_run,
                          "removed_bytes": sum(e.size_bytes for e in removed)}))
        return 0
    now = time.time()
    verb = "would remove" if args.dry_run else "removed"
    for e in removed:
        print(f"{verb} {e.path.relative_to(root)} ({e.kind}, {e.size_bytes / 1e6:.1f} MB, last used "
              f"{(now - e.last_used) / 86400:.1f} days ago)")
    for e in kept:
        print(f"{e.size_bytes / 1e6:9.1f} MB  {(now - e.last_used) / 86400:7.1f} days  {e.kind:7s} "
              f"{e.path.relative_to(root)}")
    print(f"{root}: {len(kept)} folders, {sum(e.size_bytes for e in kept) / 1e6:.1f} MB"
          + (f"; {verb} {len(removed)}, {sum(e.size_bytes for e in removed) / 1e6:.1f} MB" if args.prune else ""))
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
    c = sub.add_parser("cache", help="list the PSF cache's folders with their size and last use, or prune them",
                       description="Lists every folder of the PSF cache ($BMI_CACHE_DIR/psf): a lens's PSF tensor, a "
                                   "camera's exact kernels, a camera's evidence models of one kind and model code; "
                                   "each with its size and the days since a decode last read or wrote it. --prune "
                                   "removes whole folders, least recently used first; a decode running meanwhile "
                                   "recomputes what it no longer finds.")
    c.add_argument("--prune", action="store_true", help="remove folders (needs --older-than-days, --max-gb or both)")
    c.add_argument("--older-than-days", type=number(0, 1e5, unit="days"), metavar="DAYS",
                   help="with --prune: remove the folders unused for more than DAYS days")
    c.add_argument("--max-gb", type=number(0, 1e6, unit="GB"), metavar="GB",
                   help="with --prune: then remove the least recently used folders until the rest hold at most GB")
    c.add_argument("--dry-run", action="store_true", help="with --prune: say what would go, remove nothing")
    c.add_argument("--json", action="store_true", help="print the listing (and what was removed) as JSON")
    c.set_defaults(handler=_cache)
    p.set_defaults(handler=lambda args: p.print_help() or 2)
