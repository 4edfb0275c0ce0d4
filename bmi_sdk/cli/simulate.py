"""`bmi simulate`: render a scene through the lens and the simulated sensor into a raw DNG.

The scene (RGB + range) is shown to the simulated camera (firmware_sim) as an
optical source and read out exactly like a capture, so the DNG, its sidecar
and its region of interest are those of the device layer. A scene smaller
than the sensor is a region-of-interest frame centred at (--field-deg,
--azimuth-deg), its offset recorded in the metadata.
"""

from __future__ import annotations

import time
from pathlib import Path

from ..option_values import SEED, OptionError, number, whole
from ._logging import bars_shown

MAX_SCENE_LEVEL = 1e6
"""The brightest linear level a float .npy scene may hold, in units of the sensor's white: a highlight (a lamp, a
glint, the sky in a window) is brighter than white and clips at the sensor after the blur, which spreads it over
its neighbours; 10⁶ bounds it well inside float32 through the blur and the noise model."""


def _load_rgb(path: str):
    import cv2
    import numpy as np

    from bmi_sdk.color import srgb_uint_to_linear

    p = Path(path)
    if not p.exists():
        raise OptionError(f"--rgb {path}: no such file", "--rgb")
    if p.suffix == ".npy":
        try:
            rgb = np.load(p, allow_pickle=False)
        except (ValueError, OSError, EOFError):
            raise OptionError(f"--rgb {path}: not a NumPy .npy array (float H×W×3 linear RGB)", "--rgb") from None
        if rgb.ndim != 3 or rgb.shape[2] != 3 or not np.issubdtype(rgb.dtype, np.floating):
            raise OptionError(f"--rgb {path}: a .npy scene must be float H×W×3 linear RGB, got {rgb.dtype} "
                              f"{rgb.shape}", "--rgb")
        if rgb.size == 0 or not np.all(np.isfinite(rgb)) or rgb.min() < 0 or rgb.max() > MAX_SCENE_LEVEL:
            raise OptionError(f"--rgb {path}: linear RGB must be finite and within [0, {MAX_SCENE_LEVEL:g}] (1 is "
                              "the sensor's white; brighter highlights clip at the sensor)", "--rgb")
        return rgb.astype(np.float32)
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if img is None or img.ndim != 3 or img.shape[2] not in (3, 4) or img.dtype not in (np.uint8, np.uint16):
        raise OptionError(f"--rgb {path}: need an 8- or 16-bit RGB image file or a float .npy", "--rgb")
    return srgb_uint_to_linear(cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2RGB))


def _load_depth(path: str, shape, nearest_m: float):
    """The ``--depth`` map: float H×W range in metres. Unknown pixels (NaN, ±inf, ≤ 0) render as far
    background: a map with no known pixel is refused, one with some gets a warning; a known range nearer than
    ``nearest_m`` (the PSF tensor's nearest depth) is refused."""
    import numpy as np

    p = Path(path)
    if not p.is_file():
        raise OptionError(f"--depth {path}: no such file", "--depth")
    try:
        depth = np.load(p, allow_pickle=False)
    except (ValueError, OSError, EOFError):
        raise OptionError(f"--depth {path}: not a NumPy .npy array (a float32 H×W range in metres is needed)",
                          "--depth") from None
    if depth.ndim != 2 or not (np.issubdtype(depth.dtype, np.floating) or np.issubdtype(depth.dtype, np.integer)):
        raise OptionError(f"--depth {path}: a range map is a float H×W array in metres, got {depth.dtype} "
                          f"{depth.shape}", "--depth")
    if depth.shape != tuple(shape):
        raise OptionError(f"--depth {path}: shape {depth.shape} does not match the image {tuple(shape)}", "--depth")
    depth = depth.astype(np.float32)
    known = np.isfinite(depth) & (depth > 0)
    if not known.any():
        raise OptionError(f"--depth {path}: no pixel holds a finite range > 0 m (all NaN, inf, 0 or negative); "
                          "the frame would show nothing but far background", "--depth")
    if depth[known].min() < nearest_m:
        raise OptionError(f"--depth {path}: {int((depth[known] < nearest_m).sum())} pixels are nearer than "
                          f"{nearest_m:g} m (nearest {float(depth[known].min()):.3g} m), the nearest depth the PSF "
                          f"tensor holds; clip the map to [{nearest_m:g} m, inf)", "--depth")
    if not known.all():
        _log().warning(f"--depth {path}: {1 - known.mean():.1%} of the pixels have no finite range > 0 m; they "
                       "render as far background")
    depth[~known] = np.nan  # unknown
    return depth


def _log():
    import logging

    return logging.getLogger("bmi.simulate")


def _window(geometry, height, width, field_deg, azimuth_deg):
    """Even (row0, col0) so the scene's centre lands at (θ, φ); a clear error if it does not fit."""
    row_c, col_c = geometry.pixel_of_field(field_deg, azimuth_deg)
    row0 = int(round((float(row_c) - height / 2) / 2)) * 2
    col0 = int(round((float(col_c) - width / 2) / 2)) * 2
    if row0 < 0 or col0 < 0 or row0 + height > geometry.height_px or col0 + width > geometry.width_px:
        option = "--size" if height > geometry.height_px or width > geometry.width_px else "--field-deg"
        raise OptionError(f"a {width}×{height} scene centred at θ={field_deg}°, φ={azimuth_deg}° "
                          f"(pixel {float(row_c):.0f}, {float(col_c):.0f}) does not fit the "
                          f"{geometry.width_px}×{geometry.height_px} sensor; lower --size or --field-deg", option)
    return row0, col0


def _write_preview(path: Path, linear_rgb) -> None:
    import cv2
    import numpy as np

    from bmi_sdk.color import linear_to_srgb
    from bmi_sdk.io_atomic import atomic_path

    srgb = linear_to_srgb(linear_rgb)
    with atomic_path(path, suffix=".png") as tmp:
        if not cv2.imwrite(str(tmp), cv2.cvtColor((srgb * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGB2BGR)):
            raise OSError(f"could not write {path}")


def _save_truth(out: Path, rgb, range_m, frame_shape) -> tuple[Path, Path]:
    """``<stem>_truth_range.npy`` (float32 range in metres along each ray, NaN unknown) and
    ``<stem>_truth_rgb.npy`` (float32 linear RGB) of the scene window the frame shows, pixel for pixel."""
    import numpy as np

    from bmi_sdk.io_atomic import save_npy

    if tuple(range_m.shape) != tuple(frame_shape) or tuple(rgb.shape[:2]) != tuple(frame_shape):
        raise RuntimeError(f"the frame ({frame_shape}) does not show the scene window ({range_m.shape})")
    paths = out.with_name(out.stem + "_truth_range.npy"), out.with_name(out.stem + "_truth_rgb.npy")
    save_npy(paths[0], np.asarray(range_m, np.float32))
    save_npy(paths[1], np.asarray(rgb, np.float32))
    return paths


def _show(bar, done: int, total: int) -> None:
    """Move the render bar to the device's heartbeat (blocks of the scene rendered so far)."""
    bar.total = total
    bar.update(done - bar.n)


def _outputs(args) -> list[Path]:
    """Every file this command line writes: the DNG, its sidecar, and the truth and previews asked for."""
    from devices.dng import sidecar_path

    out = Path(args.out)
    paths = [out, sidecar_path(out)]
    if args.save_truth:
        paths += [out.with_name(out.stem + "_truth_range.npy"), out.with_name(out.stem + "_truth_rgb.npy")]
    if args.preview:
        paths += [out.with_name(out.stem + "_coded.png"), out.with_name(out.stem + "_scene.png")]
    return paths


SCENE_BYTES_PER_PX = 140
"""Peak memory of ``bmi simulate`` per scene pixel: 188 MB at 256² and 317 MB at 1024² px (procedural, exact
mode, ``ru_maxrss``), 131 B for each added pixel; a full 6000×4500 frame needs about 3.8 GB."""


def _scene(args, geometry, tensor):
    """(rgb, range_m, label, row0, col0) of the scene, its size checked against the sensor and the memory limit
    before a procedural scene is generated."""
    from bmi_sdk.memory_budget import check_allocation

    if args.procedural is not None:
        from bmi_sdk.scenes import generate_scene

        if args.rgb is not None or args.depth is not None:
            raise OptionError("--procedural renders its own scene: give it, or --rgb and --depth, not both",
                              "--procedural")

        if args.full_frame:
            height, width, option, value = geometry.height_px, geometry.width_px, "--full-frame", \
                f"({geometry.width_px}×{geometry.height_px} px)"
        else:
            height, width, option, value = args.size, args.size, "--size", args.size
        check_allocation(option, value, SCENE_BYTES_PER_PX * height * width, "lower --size")
        even = (height // 2) * 2, (width // 2) * 2  # whole RGGB cells
        row0, col0 = (0, 0) if even == (geometry.height_px, geometry.width_px) else \
            _window(geometry, *even, args.field_deg, args.azimuth_deg)
        scene = generate_scene(height, width, args.procedural)
        rgb, depth, label = scene.rgb[:even[0], :even[1]], scene.range_m[:even[0], :even[1]], \
            f"procedural seed {args.procedural}"
        return rgb, depth, label, row0, col0
    if args.rgb is None or args.depth is None:
        raise OptionError("give --rgb IMG and --depth DEPTH.npy, or --procedural SEED", "--procedural")
    rgb = _load_rgb(args.rgb)
    height, width = (rgb.shape[0] // 2) * 2, (rgb.shape[1] // 2) * 2  # whole RGGB cells
    if not (height and width):
        raise OptionError(f"--rgb {args.rgb}: a {rgb.shape[1]}×{rgb.shape[0]} image holds no whole 2×2 RGGB cell",
                          "--rgb")
    row0, col0 = (0, 0) if (height, width) == (geometry.height_px, geometry.width_px) else \
        _window(geometry, height, width, args.field_deg, args.azimuth_deg)
    check_allocation("--rgb", args.rgb, SCENE_BYTES_PER_PX * height * width)
    depth = _load_depth(args.depth, rgb.shape[:2], nearest_m=min(tensor.spec.depth_m))
    return rgb[:height, :width], depth[:height, :width], Path(args.rgb).name, row0, col0


def _run(args) -> int:
    from tqdm import tqdm

    from bmi_sdk.lenses import lens_geometry, lens_tensor
    from bmi_sdk.sensor import SensorModel
    from devices import Roi, open_camera
    from firmware_sim import FirmwareDevice, RenderedScene

    from ._options import check_output_file, perturbation_option
    from ._outputs import refuse_existing

    check_output_file("--out", args.out, (".dng",))  # a wrong name or folder fails before minutes of rendering
    if not args.overwrite:
        refuse_existing(_outputs(args))
    t0 = time.perf_counter()
    lens_name = "fisheye" if args.lens == "fisheye" else "bmi_monocentric"
    # The lens profile: the fisheye images on a plane sensor with its own chief-ray mapping, with wider kernels.
    geometry = lens_geometry(lens_name)
    tensor = lens_tensor(lens_name)
    perturbation = None
    if args.perturb:
        if args.psf_mode != "exact":
            raise OptionError("--perturb needs --psf-mode exact: the radial tensor cannot hold a built camera's "
                              "errors", "--perturb")
        perturbation = perturbation_option("--perturb", args.perturb, lens_name)
    rgb, depth, label, row0, col0 = _scene(args, geometry, tensor)
    height, width = depth.shape
    source = RenderedScene(rgb, depth, row0, col0, lens=lens_name, geometry=geometry, tensor=tensor, label=label,
                           psf_mode=args.psf_mode, perturbation=perturbation)
    model = SensorModel(additive_sigma=args.noise)
    device = FirmwareDevice(source=source, geometry=geometry, model=model, seed=args.seed, lens=lens_name)
    # The device renders as it reads out (minutes for a large scene or a cold PSF cache); its heartbeats
    # keep the capture alive and move this bar, so a slow render is told apart from a dead device.
    with tqdm(desc="render", unit="block", disable=not bars_shown()) as bar, \
            open_camera("sim://", device=device, on_progress=lambda _id, done, total: _show(bar, done, total)) as cam:
        cam.settings.roi = Roi(col0, row0, width, height)
        frame = cam.capture()
        _show(bar, bar.total or 1, bar.total or 1)
        frame.save_dng(args.out, overwrite=args.overwrite)
    if args.save_truth:
        truth = _save_truth(Path(args.out), rgb, depth, frame.data.shape)
        print(f"wrote ground truth {truth[0].name} (range, m) and {truth[1].name} (linear RGB)")
    print(f"wrote {args.out} (+ .json sidecar): {width}×{height} at sensor offset (row {row0}, col {col0}), "
          f"noise {'photon model' if args.noise is None else f'σ = {args.noise}'}, {time.perf_counter() - t0:.1f} s")
    if args.preview:
        out = Path(args.out)
        coded = source.irradiance(row0, col0, height, width)
        _write_preview(out.with_name(out.stem + "_coded.png"), coded)
        _write_preview(out.with_name(out.stem + "_scene.png"), rgb)
        print(f"wrote previews {out.stem}_coded.png and {out.stem}_scene.png")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("simulate", help="render an RGB + depth scene (or a procedural one) into a raw DNG",
                              description=__doc__)
    p.add_argument("--rgb", help="8/16-bit image file (sRGB, decoded to linear) or float32 .npy H×W×3 linear RGB")
    p.add_argument("--depth", help="float32 .npy H×W range in metres along each ray, ≥ 0.7 m (the PSF tensor's "
                                   "nearest depth); NaN or 0: unknown, rendered as far background")
    p.add_argument("--procedural", type=SEED, metavar="SEED",
                   help="render the embedded procedural scene of this seed (0 … 2³²−1) instead")
    p.add_argument("--full-frame", action="store_true", help="with --procedural: the full 6000×4500 frame")
    p.add_argument("--size", type=whole(2, unit="px"), default=512,
                   help="with --procedural and no --full-frame: square size (px; at most the sensor's 4500, less "
                        "off axis)")
    p.add_argument("--out", required=True, help="output DNG (a JSON sidecar is written beside it)")
    p.add_argument("--field-deg", type=number(0, 60, unit="°"), default=0.0,
                   help="field angle of the scene's centre, 0–60° (the sensor's field; default 0)")
    p.add_argument("--azimuth-deg", type=number(-360, 360, unit="°"), default=0.0,
                   help="azimuth of the scene's centre, -360–360° (default 0)")
    p.add_argument("--noise", type=number(0, 1), default=None,
                   help="the paper's additive Gaussian σ on the [0,1] signal, 0–1 (0, 0.005, 0.01, 0.02, 0.05); "
                        "default: the sensor's photon model (shot + read noise)")
    p.add_argument("--lens", choices=("monocentric", "fisheye"), default="monocentric")
    p.add_argument("--psf-mode", choices=("exact", "tensor"), default="exact",
                   help="exact: trace each zone's field; tensor: interpolate the radial tensor (faster)")
    p.add_argument("--perturb", action="append", metavar="NAME=VALUE",
                   help="render through a built camera with this hardware error (repeat; the names and units of "
                        "bmi calibrate --simulate, e.g. decenter_um=10,0 stray_light_fraction=0.03); exact mode")
    p.add_argument("--seed", type=SEED, default=0, help="noise seed (0 … 2³²−1)")
    p.add_argument("--save-truth", action="store_true",
                   help="also write the ground truth of the frame's window: <stem>_truth_range.npy (float32 range "
                        "in metres along each ray, NaN unknown) and <stem>_truth_rgb.npy (float32 linear RGB)")
    p.add_argument("--preview", action="store_true", help="also write PNG previews of the coded image and scene")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the files of an earlier run (default: refuse them, before rendering)")
    p.set_defaults(handler=_run)
