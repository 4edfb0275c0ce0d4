"""`bmi bench decoder`: the classical decoder's error against run time, per knob; textured planes; a full frame.

* Knobs (``bmi eval``'s benchmark, ``standard`` condition, σ = 0.005, ``tiles`` tiles per region): the
  number of depth candidates, the window size, the stride and the prior-slope set, one at a
  time around the default ``ClassicalConfig``. Error: AbsRel, δ1, RMSE, PSNR averaged over the
  centre and edge regions, and the RMS of (error / reported σ); cost: CPU seconds per 192² tile.
* Where the error comes from (``error_source_rows``): the same tiles' AbsRel per true-range bin, how many pixels sit
  in windows that hold several depths, and an oracle that pools each true segment's reads.
* Planes: a textured fronto-parallel plane (a procedural scene's texture at one range) at 1, 2,
  4, 6 and 8 m, rendered at 0° and 50° with the nominal tensor kernels, decoded with the same
  kernels: AbsRel per distance (the upper bound the issue's prototype measured).
* The edge of a built camera: 1/f² planes at 55° for the nominal camera and one with a +0.5 % sensor radius, each
  rendered and decoded with its own kernels, beside ``window_depth_bound`` (the Cramér–Rao bound of one window).
* Exact kernels against rotated tensor kernels (``exact_kernel_rows``): 1/f² planes at 50° rendered with either,
  decoded with either.
* Each window's own θ (``theta_step_rows``): planes of a built camera read with the zone of a block's centre or
  with zones interpolated to each window's θ.
* Windows that read the wrong side of focus (``window_outlier_rows``): the built camera's edge is focused at ~3 m.
* The tensor kernels' rotation (``rotation_rows``): one far plane read with the kernel models of zones that differ
  in θ or in φ.
* The σ model (``ClassicalConfig`` step 4): (a, b, c) fitted by maximum likelihood on
  ``FIT_TILES`` tiles per region drawn with seed ``FIT_SEED`` (not the benchmark's), and the RMS
  of (error / σ) it gives there; ``ClassicalConfig``'s defaults are these numbers.
* ``--full``: a 6000×4500 procedural frame rendered in tensor mode, decoded whole: wall and CPU
  time, peak memory.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from bmi_sdk.sensor import BLACK_LEVEL_DN, WHITE_LEVEL_DN, NoiseProfile

from . import cpu_seconds, markdown_table, peak_rss_mb, register_target

TILES = 4
PLANE_PX = 192
PLANE_DEPTHS_M = (1.0, 2.0, 4.0, 6.0, 8.0)
PLANE_FIELDS_DEG = (0.0, 50.0)
PLANE_TEXTURES = ("scene", "pink")
FIT_SEED = 777
FIT_TILES = 12


def _knob_rows(bench, renders, nominal_map) -> list[list]:
    from bmi_sdk.decode import ClassicalConfig
    from bmi_sdk.nn.data import STANDARD_SIGMA
    from bmi_sdk.nn.evaluate import ClassicalTiles, score

    base = ClassicalConfig()
    variants = [("default", base)]
    variants += [(f"candidates {n}", replace(base, candidates=n)) for n in (16, 24) if n != base.candidates]
    variants += [(f"window {w} px", replace(base, window_px=w)) for w in (48, 96) if w != base.window_px]
    variants += [(f"stride {s} px", replace(base, stride_px=s)) for s in (8, 32) if s != base.stride_px]
    variants += [("exponent profiled 1.5–2.5 (5 slopes, exact model)",
                  replace(base, slopes=(1.5, 1.75, 2.0, 2.25, 2.5), exact_model_below=1.0)),
                 ("confidence fill 1.5 windows", replace(base, fill_windows=1.5)),
                 ("AiF on every 2nd candidate", replace(base, aif_step=2)),
                 ("AiF on every candidate", replace(base, aif_step=1)),
                 ("AiF model error 0 (sensor noise only)", replace(base, aif_model_error=0.0)),
                 ("AiF model error 0.2", replace(base, aif_model_error=0.2))]
    rows = []
    for name, config in variants:
        decoder = ClassicalTiles(nominal_map, config)
        cpu0 = cpu_seconds()
        out = score(decoder, renders, bench, STANDARD_SIGMA, "standard")
        cpu = (cpu_seconds() - cpu0) / len(renders)
        mean = {k: float(np.mean([r[k] for r in out])) for k in ("absrel", "delta1", "rmse_m", "psnr_db",
                                                                 "sigma_z_rms")}
        rows.append([name, len(decoder.decoder.candidates), mean["absrel"], mean["delta1"], mean["rmse_m"],
                     mean["psnr_db"], mean["sigma_z_rms"], cpu])
    return rows


ERROR_RANGE_BINS_M = (0.0, 1.5, 3.0, 6.0, 20.0)
CLUTTER_RATIO = 3.0


def error_source_rows(bench, renders, psf_map, config=None) -> list[list]:
    """Where the benchmark's depth error comes from, per region and true-range bin: [region, range m, share of the
    region's valid pixels, AbsRel, median read / true range, share of those pixels whose window holds a range
    ratio above ``CLUTTER_RATIO``]; and per region an "all" row whose last two columns are the AbsRel after
    giving each true segment (connected pixels between range steps > 5 %) the median of its read 1/d, an oracle
    that pools perfectly within objects and never across their edges, and the clutter share of the region.
    Decoded as ``score`` decodes the ``standard`` condition (σ 0.005, the same noise draws)."""
    from scipy import ndimage

    from bmi_sdk.decode import ClassicalConfig, ClassicalDecoder
    from bmi_sdk.nn.data import FAR_FILL_M, STANDARD_SIGMA
    from bmi_sdk.nn.evaluate import tile_raw

    decoder = ClassicalDecoder.for_psf_map(psf_map, config or ClassicalConfig())
    span = decoder.config.window_px + 1
    per_region: dict[str, list] = {}
    for k, item in enumerate(renders):
        out = decoder.decode(tile_raw(bench, item, k, STANDARD_SIGMA), BLACK_LEVEL_DN, WHITE_LEVEL_DN,
                             psf_map.geometry, item["row0"], item["col0"],
                             noise_profile=NoiseProfile.additive(STANDARD_SIGMA))
        truth = item["range_m"]
        ok = out.valid & np.isfinite(truth)
        inv_true = 1.0 / np.where(np.isfinite(truth), truth, FAR_FILL_M)
        clutter = ndimage.maximum_filter(inv_true, span) / ndimage.minimum_filter(inv_true, span) > CLUTTER_RATIO
        steps = np.hypot(*np.gradient(np.log(inv_true))) > 0.05
        segments, count = ndimage.label(~steps)
        segments[~ok] = 0  # the oracle reads only decoded pixels with ground truth
        medians = np.asarray(ndimage.median(1.0 / out.depth_m.astype(np.float64), segments, np.arange(1, count + 1)))
        oracle = out.depth_m.astype(np.float64).copy()
        oracle[segments > 0] = 1.0 / medians[segments[segments > 0] - 1]
        per_region.setdefault(item["region"], []).append(
            np.stack([truth[ok], out.depth_m[ok], oracle[ok], clutter[ok]], axis=1))
    rows = []
    for region, parts in per_region.items():
        truth, read, oracle, clutter = np.concatenate(parts).T
        rel = np.abs(read - truth) / truth
        for lo, hi in zip(ERROR_RANGE_BINS_M[:-1], ERROR_RANGE_BINS_M[1:]):
            sel = (truth >= lo) & (truth < hi)
            if sel.any():
                rows.append([region, f"{lo:g}–{hi:g}", float(sel.mean()), float(rel[sel].mean()),
                             float(np.median(read[sel] / truth[sel])), float(clutter[sel].mean())])
        rows.append([region, "all", 1.0, float(rel.mean()), float(np.mean(np.abs(oracle - truth) / truth)),
                     float(clutter.mean())])
    return rows


def plane_texture(size_px: int, texture: str, rng: np.random.Generator) -> np.ndarray:
    """(size, size, 3) float32 linear RGB of a plane: "scene" a procedural scene's picture (objects, shadows, soft
    specular glows: intrinsically smooth features that defocus cannot be told from), "pink" a 1/f² field per channel
    (the evidence's prior, and natural images' average spectrum), mean 0.4, 15 % contrast."""
    from bmi_sdk.scenes import generate_scene

    if texture == "scene":
        return generate_scene(size_px, size_px, rng).rgb
    if texture == "pink":
        return power_law_texture(size_px, 2.0, rng)
    raise ValueError(f"unknown plane texture {texture!r}")


def power_law_texture(size_px: int, power_slope: float, rng: np.random.Generator) -> np.ndarray:
    """(size, size, 3) float32 linear RGB: per channel a field of power spectrum 1/f^``power_slope``, 15 % contrast
    about 0.4, clipped to [0.01, 1] (``power_slope`` 2: ``plane_texture``'s "pink")."""
    from bmi_sdk.scenes.procedural import pink_noise

    rgb = np.stack([pink_noise((size_px, size_px), rng, exponent=power_slope / 2) for _ in range(3)], axis=-1)
    return np.clip(rgb * 0.15 + 0.4, 0.01, 1.0).astype(np.float32)


PLANE_MARGIN_PX = 24


def plane_raw(tensor, geometry, field_deg: float, depth_m: float, seed: int = 3,
              texture: str = "scene", psf_mode: str = "tensor", psf_map=None, size_px: int = PLANE_PX,
              zone_px: int | None = None) -> tuple[np.ndarray, int, int]:
    """(raw, row0, col0): a ``plane_texture`` plane of ``size_px``² at ``depth_m`` centred at ``field_deg`` (φ = 30°),
    rendered with ``tensor``'s kernels (``psf_mode``: rotated tensor kernels, or exact ones; or a given ``psf_map``)
    on the renderer's zones (``zone_px``, default the renderer's), relative illumination applied, as the raw window
    at (row0, col0) of the sensor with the standard noise (σ 0.005)."""
    from bmi_sdk.render import PsfMap

    size = size_px + 2 * PLANE_MARGIN_PX
    rgb = plane_texture(size, texture, np.random.default_rng(seed))
    return window_raw(rgb, np.full((size, size), depth_m, np.float32), tensor, geometry, field_deg, 30.0, seed,
                      psf_map or PsfMap(tensor, geometry, mode=psf_mode), zone_px)


def window_raw(rgb: np.ndarray, range_m: np.ndarray, tensor, geometry, field_deg: float, azimuth_deg: float,
               seed: int, psf_map, zone_px: int | None = None) -> tuple[np.ndarray, int, int]:
    """(raw, row0, col0): a scene (``rgb``, ``range_m``, ``PLANE_MARGIN_PX`` of context on each side) centred at
    (``field_deg``, ``azimuth_deg``), rendered with ``psf_map``'s kernels on the renderer's zones (``zone_px``,
    default the renderer's), relative illumination applied, as the raw window inside the margin, at (row0, col0) of
    the sensor, with the standard noise (σ 0.005) drawn from ``seed``."""
    from bmi_sdk.nn.data import STANDARD_SIGMA, simulate_raw
    from bmi_sdk.render import render_coded
    from bmi_sdk.sensor import relative_illumination

    m, size = PLANE_MARGIN_PX, rgb.shape[0]
    r, c = geometry.pixel_of_field(field_deg, azimuth_deg)
    row0, col0 = int(r - size / 2) // 2 * 2, int(c - size / 2) // 2 * 2
    optical = render_coded(rgb, range_m, tensor, geometry, row0, col0, psf_map=psf_map, zone_px=zone_px)
    optical *= relative_illumination(geometry, row0, col0, size, size)[..., None]
    raw = simulate_raw(optical[m:-m, m:-m], STANDARD_SIGMA, np.random.default_rng(seed), row0 + m, col0 + m)
    return raw, row0 + m, col0 + m


def decoded_absrel(decode, raw: np.ndarray, row0: int, col0: int, depth_m: float) -> float:
    """AbsRel of ``decode(raw, row0, col0, noise)`` → (depth_m, valid) against a plane at ``depth_m``, the raw
    noise being the standard σ's ``sensor.NoiseProfile``."""
    from bmi_sdk.nn.data import STANDARD_SIGMA

    depth, ok = decode(raw, row0, col0, NoiseProfile.additive(STANDARD_SIGMA))
    ok = ok & np.isfinite(depth)
    return float(np.mean(np.abs(depth[ok] - depth_m) / depth_m))


def plane_absrel(nominal, geometry, decode, field_deg: float, depth_m: float, seed: int = 3,
                 texture: str = "scene") -> float:
    """AbsRel of the decoded depth over ``plane_raw``'s plane (``decoded_absrel``)."""
    raw, row0, col0 = plane_raw(nominal, geometry, field_deg, depth_m, seed, texture)
    return decoded_absrel(decode, raw, row0, col0, depth_m)


BUILT_FIELD_DEG = 55.0
MEAN_ABS_PER_SIGMA = float(np.sqrt(2.0 / np.pi))  # E|e| / σ of a Gaussian error: AbsRel at a bound σ_d / d
BUILT_SENSOR_RADIUS_PCT = 0.5


def window_depth_bound(decoder, raw: np.ndarray, row0: int, col0: int, field_deg: float, depth_m: float) -> float:
    """Cramér–Rao bound of σ_d / d for one tapered window of a plane at ``depth_m`` (``plane_raw``) at ``field_deg``.

    The four planes' ``evidence.inverse_depth_information`` at the decoder's candidate nearest ``depth_m`` (the
    decoder's kernels must be the ones the plane was rendered with), each plane's prior level β' the median moment
    estimate of the plane's windows, inflated by the taper (``evidence.taper_variance_inflation``): what the window
    estimator can reach, whatever decodes it.
    """
    from bmi_sdk.decode.bayer import normalised_planes
    from bmi_sdk.decode.evidence import (
        hann_taper,
        inverse_depth_information,
        rfft_multiplicity,
        taper_variance_inflation,
        window_spectra,
    )
    from bmi_sdk.decode.kernels import ZoneKernels
    from bmi_sdk.nn.data import STANDARD_SIGMA

    planes = normalised_planes(raw, BLACK_LEVEL_DN, WHITE_LEVEL_DN, row0, col0)
    n = decoder.config.window_px // 2
    taper = hann_taper(n)
    taper_energy = float((taper ** 2).sum())
    noise_power = NoiseProfile.additive(STANDARD_SIGMA).offset * taper_energy
    cand = decoder.candidates
    models = decoder.zones.models(ZoneKernels.zone(field_deg, 30.0), np.arange(len(cand)))[:, 0] * taper_energy
    true = int(np.argmin(np.abs(cand.depth_m - depth_m)))
    mult = rfft_multiplicity(n)
    info = 0.0
    for p in range(4):
        power = window_spectra(planes[p], n, n // 2, taper)[0] / noise_power
        beta = np.median(((power * mult).sum(axis=(1, 2)) - mult.sum()) / (models[p, true] * mult).sum())
        info += inverse_depth_information(models[p], cand.inv_depth_per_m, max(float(beta), 1e-6))[true]
    return float(np.sqrt(taper_variance_inflation(taper) / info) * cand.depth_m[true])


def _built_camera_rows(nominal, geometry) -> list[list]:
    """Pink planes at the field edge: the nominal camera and one built with a sensor-radius error, each decoded
    with its own kernels; AbsRel, and the AbsRel of an estimator at the window bound (``MEAN_ABS_PER_SIGMA``
    σ_d / d), per range."""
    from bmi_sdk.built_camera import BuiltCamera
    from bmi_sdk.decode import ClassicalConfig, ClassicalDecoder
    from bmi_sdk.optics.perturb import Perturbation
    from bmi_sdk.render import PsfMap

    built = BuiltCamera(perturbation=Perturbation(sensor_radius_error_pct=BUILT_SENSOR_RADIUS_PCT))
    cameras = [(nominal, ClassicalDecoder.for_psf_map(PsfMap(nominal, geometry, mode="tensor"), ClassicalConfig())),
               (built.psf_tensor(), ClassicalDecoder.for_psf_map(built.psf_map(mode="tensor"), ClassicalConfig()))]
    rows = []
    for d in (1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0):
        absrel, bound = [], []
        for tensor, decoder in cameras:
            raw, row0, col0 = plane_raw(tensor, geometry, BUILT_FIELD_DEG, d, texture="pink")
            absrel.append(decoded_absrel(classical_depth(decoder, geometry), raw, row0, col0, d))
            bound.append(MEAN_ABS_PER_SIGMA * window_depth_bound(decoder, raw, row0, col0, BUILT_FIELD_DEG, d))
        rows.append([f"{d:g} m"] + absrel + bound)
    return rows


EXACT_FIELD_DEG = 50.0
KERNEL_MODES = ("tensor", "exact")


def exact_kernel_rows(nominal, geometry) -> list[list]:
    """1/f² planes at ``EXACT_FIELD_DEG`` (φ 30°) rendered with rotated tensor kernels or exact ones, each decoded
    with either: depth AbsRel per range. A lens's frames hold exact kernels; the tensor's bilinear rotation
    smooths the sharp far ones."""
    from bmi_sdk.decode import ClassicalConfig, ClassicalDecoder
    from bmi_sdk.render import PsfMap

    decoders = {mode: classical_depth(ClassicalDecoder.for_psf_map(PsfMap(nominal, geometry, mode=mode),
                                                                   ClassicalConfig()), geometry)
                for mode in KERNEL_MODES}
    rows = []
    for d in PLANE_DEPTHS_M:
        row = [f"{d:g} m"]
        for render_mode in KERNEL_MODES:
            raw, row0, col0 = plane_raw(nominal, geometry, EXACT_FIELD_DEG, d, texture="pink", psf_mode=render_mode)
            row += [decoded_absrel(decoders[mode], raw, row0, col0, d) for mode in KERNEL_MODES]
        rows.append(row)
    return rows


THETA_STEPS_DEG = (None, 1.0)
THETA_PLANE_PX = 384
THETA_ZONE_PX = 32


def theta_step_rows(geometry) -> list[list]:
    """1/f² planes at ``BUILT_FIELD_DEG`` (φ 30°) of ``THETA_PLANE_PX``² (about 3° of field), rendered with exact
    kernels on ``THETA_ZONE_PX`` render zones (each pixel's kernels within 0.25° of its own), for the nominal camera
    and the built one (+0.5 % sensor radius), decoded with exact kernels: a block's windows reading its centre's zone,
    or each window the zones of a 1° θ grid around its own θ (``ClassicalConfig.theta_step_deg``). AbsRel and CPU
    seconds of the decode (its kernels traced on the first plane)."""
    from bmi_sdk.built_camera import BuiltCamera
    from bmi_sdk.decode import ClassicalConfig, ClassicalDecoder
    from bmi_sdk.optics.perturb import Perturbation

    rows = []
    for name, camera in (("nominal", BuiltCamera()),
                         ("built", BuiltCamera(perturbation=Perturbation(sensor_radius_error_pct=BUILT_SENSOR_RADIUS_PCT)))):
        render_map = camera.psf_map(mode="exact")
        decoders = [ClassicalDecoder.for_psf_map(camera.psf_map(mode="exact"), ClassicalConfig(theta_step_deg=step))
                    for step in THETA_STEPS_DEG]
        for d in (2.0, 4.0, 6.0, 8.0):
            raw, row0, col0 = plane_raw(render_map.tensor, geometry, BUILT_FIELD_DEG, d, texture="pink",
                                        psf_map=render_map, size_px=THETA_PLANE_PX, zone_px=THETA_ZONE_PX)
            absrel, cpu = [], []
            for decoder in decoders:
                cpu0 = cpu_seconds()
                absrel.append(decoded_absrel(classical_depth(decoder, geometry), raw, row0, col0, d))
                cpu.append(cpu_seconds() - cpu0)
            rows.append([name, f"{d:g} m"] + absrel + cpu)
    return rows


OUTLIER_DEPTHS_M = (2.0, 3.0, 4.0, 6.0, 8.0)
OUTLIER_FRACTION = 0.25


def window_outlier_rows(nominal_map, built_map, size_px: int = 512, seed: int = 4) -> list[list]:
    """A ``zone_plane_raw`` per camera and range (the kernels of the zone at ``BUILT_FIELD_DEG``, φ 30°), read window
    by window (``window_depths``): AbsRel and the fraction of windows off by more than ``OUTLIER_FRACTION``. A camera
    focused inside the range (the +0.5 % sensor radius moves the edge's focus to ~3 m) is defocused both ways around
    it, and windows there can read the wrong side."""
    from bmi_sdk.decode import ClassicalConfig, ClassicalDecoder

    zone = (BUILT_FIELD_DEG, 30.0)
    rows = []
    for name, psf_map in (("nominal", nominal_map), ("built", built_map)):
        decoder = ClassicalDecoder.for_psf_map(psf_map, ClassicalConfig())
        cand = decoder.candidates
        for d in OUTLIER_DEPTHS_M:
            raw, i = zone_plane_raw(decoder, zone, d, size_px, seed)
            err = np.abs(window_depths(decoder, raw, [zone])[0] / cand.depth_m[i] - 1.0)
            rows.append([name, f"{cand.depth_m[i]:.2g} m", float(err.mean()), float(np.mean(err > OUTLIER_FRACTION))])
    return rows


ROTATION_DEPTH_M = 7.8
ROTATION_ZONES = ((0.0, 0.0), (1.2, 0.0), (1.2, 90.0), (3.0, 0.0), (3.0, 10.0), (1.2, 45.0), (3.0, 45.0))


def blurred_plane_raw(kernels: np.ndarray, size_px: int = 512, seed: int = 3) -> np.ndarray:
    """A ``pink`` plane blurred periodically (by FFT) with one (C, K, K) kernel set, as a raw frame with the standard
    noise: a plane whose kernels are exactly one zone's, with no render zones or image edge."""
    from scipy import fft as sfft

    from bmi_sdk.nn.data import STANDARD_SIGMA, simulate_raw

    k = kernels.shape[-1]
    otf = np.zeros((3, size_px, size_px))
    otf[:, :k, :k] = kernels
    otf = sfft.fft2(np.roll(otf, (-(k // 2), -(k // 2)), (1, 2)), axes=(1, 2))
    rgb = plane_texture(size_px, "pink", np.random.default_rng(seed)).transpose(2, 0, 1)
    optical = sfft.ifft2(sfft.fft2(rgb, axes=(1, 2)) * otf, axes=(1, 2)).real.transpose(1, 2, 0)
    return simulate_raw(optical.astype(np.float32), STANDARD_SIGMA, np.random.default_rng(seed))


def zone_plane_raw(decoder, zone: tuple[float, float], depth_m: float, size_px: int = 512,
                   seed: int = 3) -> tuple[np.ndarray, int]:
    """(raw, candidate index): a ``blurred_plane_raw`` blurred by ``zone``'s kernels of the decoder's candidate nearest
    ``depth_m`` (a plane whose depth the decoder holds exactly)."""
    true = int(np.argmin(np.abs(decoder.candidates.depth_m - depth_m)))
    return blurred_plane_raw(decoder.zones.kernels(zone, np.array([true]))[:, 0], size_px, seed), true


def window_depths(decoder, raw: np.ndarray, zones) -> list[np.ndarray]:
    """Depth of each non-overlapping window of ``raw`` (standard noise) read by the evidence alone with each zone's
    kernel models, every candidate scored: one array per zone (the window spectra are taken once)."""
    from bmi_sdk.decode.bayer import normalised_planes
    from bmi_sdk.decode.evidence import Evidence, hann_taper, profile_exponent, window_spectra
    from bmi_sdk.nn.data import STANDARD_SIGMA

    n = decoder.config.window_px // 2
    taper = hann_taper(n)
    spectra = [window_spectra(p, n, n, taper)[0] for p in normalised_planes(raw, BLACK_LEVEL_DN, WHITE_LEVEL_DN)]
    noise = [np.full(len(spectra[0]), NoiseProfile.additive(STANDARD_SIGMA).offset)] * 4
    no_clip = [np.zeros(len(spectra[0]), bool)] * 4
    cand = decoder.candidates
    depths = []
    for zone in zones:
        models = decoder.zones.models(zone, np.arange(len(cand)))
        nll = profile_exponent(decoder._block_nll(spectra, models, noise, float((taper ** 2).sum()), no_clip),
                               decoder.config.slopes)
        depths.append(Evidence(nll, cand.inv_depth_per_m).refine()[0])
    return depths


def rotation_rows(decoder, size_px: int = 512, seed: int = 3) -> list[list]:
    """Median depth read from one plane against the kernel models of several zones (θ, φ).

    A ``zone_plane_raw`` at ``ROTATION_DEPTH_M`` (the on-axis zone's kernels), read window by window with every
    zone's models (``window_depths``). Zones apart only in θ (up to 3°) hold nearly the same kernels; zones off the multiples of 90° in φ hold tensor kernels rotated by bilinear
    interpolation (``render.psf_map.rotate_kernel``).
    """
    raw, _ = zone_plane_raw(decoder, (0.0, 0.0), ROTATION_DEPTH_M, size_px, seed)
    return [[f"θ {zone[0]:g}°, φ {zone[1]:g}°", float(np.median(depth))]
            for zone, depth in zip(ROTATION_ZONES, window_depths(decoder, raw, ROTATION_ZONES))]


def classical_depth(decoder, geometry):
    """``plane_absrel``'s ``decode`` for a ``ClassicalDecoder``."""

    def decode(raw, row0, col0, noise):
        out = decoder.decode(raw, BLACK_LEVEL_DN, WHITE_LEVEL_DN, geometry, row0, col0, noise_profile=noise)
        return out.depth_m, out.valid

    return decode


def fit_sigma_model(nominal_map, seed: int = FIT_SEED, tiles: int = FIT_TILES) -> tuple[tuple, float, int]:
    """((a, b, c), z RMS at the fit, pixels used): maximum-likelihood σ model on seeded tiles.

    Per pixel (every 4th row and column of each tile's valid pixels): the range error e = d − d_true
    and, from the window grid, σ_L and the spread s of 1/d; minimise Σ e²/σ_d² + log σ_d² with
    σ_d = d² σ(1/d), σ(1/d)² = (a σ_L)² + (b s)² + c² (the decoder's own propagation to range, so the
    fitted σ is honest for the range it reports), a ≥ 1 (the likelihood's own curvature is a lower bound of the
    uncertainty: a model error can add to it, never take from it), b ≥ 0, c ≥ 0.
    """
    from scipy.optimize import minimize

    from bmi_sdk.decode import ClassicalConfig
    from bmi_sdk.decode.classical import upsample_grid
    from bmi_sdk.nn.data import STANDARD_SIGMA, simulate_raw
    from bmi_sdk.nn.evaluate import Benchmark, ClassicalTiles

    bench = Benchmark(tiles=tiles, seed=seed)
    geometry = nominal_map.geometry
    decoder = ClassicalTiles(nominal_map, ClassicalConfig()).decoder
    m, t = bench.margin_px, bench.tile_px
    err, sig_l, spread = [], [], []
    for k, item in enumerate(bench.renders(nominal_map.tensor)):
        rng = np.random.default_rng([seed, 99, k])
        raw = simulate_raw(item["optical_full"][m:m + t, m:m + t], STANDARD_SIGMA, rng, item["row0"], item["col0"])
        out = decoder.decode(raw, BLACK_LEVEL_DN, WHITE_LEVEL_DN, geometry, item["row0"], item["col0"],
                             noise_profile=NoiseProfile.additive(STANDARD_SIGMA))
        stride = decoder.config.stride_px
        ok = out.valid & np.isfinite(item["range_m"])
        ok[np.arange(t) % 4 != 0] = False
        ok[:, np.arange(t) % 4 != 0] = False
        d2 = out.depth_m.astype(np.float64) ** 2
        err.append(((out.depth_m - item["range_m"]) / d2)[ok])  # range error in units of d², as σ_d = d² σ(1/d)
        sig_l.append(upsample_grid(out.grid_sigma_laplace, stride, t, t)[ok])
        spread.append(upsample_grid(out.grid_spread, stride, t, t)[ok])
    e2, l2, s2 = (np.concatenate(x).astype(np.float64) ** 2 for x in (err, sig_l, spread))

    def abc(x):
        return 1.0 + np.exp(x[0]), np.exp(x[1]), np.exp(x[2])

    def nll(x):
        a, b, c = abc(x)
        var = a * a * l2 + b * b * s2 + c * c
        return float(np.mean(e2 / var + np.log(var)))

    best = minimize(nll, np.log([2.0, 1.0, 0.05]), method="Nelder-Mead", options={"xatol": 1e-4, "fatol": 1e-6})
    a, b, c = abc(best.x)
    z_rms = float(np.sqrt(np.mean(e2 / (a * a * l2 + b * b * s2 + c * c))))
    return (float(a), float(b), float(c)), z_rms, int(e2.size)


def full_frame_optical(nominal, geometry, psf_map=None) -> tuple[np.ndarray, np.ndarray, float]:
    """(true range_m, optical image, render wall s) of the benchmarks' full frame: the 6000×4500 procedural scene of
    seed 7, rendered with ``psf_map``'s kernels (default: ``nominal``'s rotated tensor kernels; ``nominal`` must be
    ``psf_map``'s tensor), relative illumination applied: the noiseless signal at the sensor (H × W × 3)."""
    from bmi_sdk.render import PsfMap, render_coded
    from bmi_sdk.scenes import generate_scene
    from bmi_sdk.sensor import relative_illumination

    h, w = geometry.height_px, geometry.width_px
    scene = generate_scene(h, w, np.random.default_rng(7))
    t0 = time.perf_counter()
    optical = render_coded(scene.rgb, scene.range_m, nominal, geometry, 0, 0,
                           psf_map=psf_map or PsfMap(nominal, geometry, mode="tensor"))
    optical *= relative_illumination(geometry, 0, 0, h, w)[..., None]
    return scene.range_m, optical, time.perf_counter() - t0


def full_frame_raw(nominal, geometry, psf_map=None) -> tuple[np.ndarray, np.ndarray, float]:
    """(true range_m, raw frame, render wall s): ``full_frame_optical``'s frame at the standard noise (σ 0.005)."""
    from bmi_sdk.nn.data import STANDARD_SIGMA, simulate_raw

    range_m, optical, render_s = full_frame_optical(nominal, geometry, psf_map)
    return range_m, simulate_raw(optical, STANDARD_SIGMA, np.random.default_rng(7)), render_s


def _full_frame(nominal, geometry) -> str:
    from bmi_sdk.decode import ClassicalConfig, ClassicalDecoder
    from bmi_sdk.nn.data import STANDARD_SIGMA
    from bmi_sdk.render import PsfMap

    range_m, raw, render_s = full_frame_raw(nominal, geometry)
    psf_map = PsfMap(nominal, geometry, mode="tensor")
    config = ClassicalConfig()
    decoder = ClassicalDecoder.for_psf_map(psf_map, config)
    rss0 = peak_rss_mb()
    lines = [f"Full 6000×4500 procedural frame (seed 7), tensor-mode render {render_s:.0f} s; "
             f"peak RSS before decoding {rss0:.0f} MB.", ""]
    rows = []
    for run in ("first (kernels computed)", "second (kernels memoised)"):
        wall, cpu = time.perf_counter(), cpu_seconds()
        out = decoder.decode(raw, BLACK_LEVEL_DN, WHITE_LEVEL_DN, geometry,
                             noise_profile=NoiseProfile.additive(STANDARD_SIGMA))
        t = out.stats["timings_s"]
        rows.append([run, time.perf_counter() - wall, cpu_seconds() - cpu, t["evidence_s"], t["kernels_s"], t["aif_s"],
                     out.stats["blocks_skipped"], peak_rss_mb()])
    ok = out.valid & np.isfinite(range_m)
    absrel = float(np.mean(np.abs(out.depth_m[ok] - range_m[ok]) / range_m[ok]))
    lines.append(markdown_table(["decode", "wall s", "CPU s", "evidence s", "kernels s", "AiF s", "blocks skipped",
                                 "peak RSS MB"], rows))
    lines += ["", f"Depth AbsRel over the frame's {int(ok.sum())} valid pixels: {absrel:.3f}."]
    return "\n".join(lines)


def run(full: bool = False) -> str:
    from bmi_sdk.built_camera import BuiltCamera
    from bmi_sdk.decode import ClassicalConfig, ClassicalDecoder
    from bmi_sdk.lenses import lens_geometry, lens_tensor
    from bmi_sdk.nn.evaluate import Benchmark
    from bmi_sdk.optics.perturb import Perturbation
    from bmi_sdk.render import PsfMap

    bench = Benchmark(tiles=TILES)
    nominal = lens_tensor(bench.lens)
    geometry = lens_geometry(bench.lens)
    nominal_map = PsfMap(nominal, geometry, mode="tensor")
    renders = bench.renders(nominal)
    out = [f"Knobs, one at a time around the default `ClassicalConfig()` (`bmi eval` benchmark, condition "
           f"`standard`, σ 0.005, {TILES} tiles per region; metrics are the mean of centre and edge; "
           "σ z RMS = RMS of (error / reported 1σ), 1 when honest; CPU s per 192² tile):", ""]
    out.append(markdown_table(["configuration", "candidates", "AbsRel", "δ1", "RMSE m", "PSNR dB", "σ z RMS",
                               "CPU s / tile"], _knob_rows(bench, renders, nominal_map)))
    out += ["", f"Where the error comes from (`error_source_rows`, the same tiles, default knobs): per true-range bin, "
                f"its share of the region's pixels, AbsRel, the median of read / true range, and the share of its "
                f"pixels whose window holds a range ratio above {CLUTTER_RATIO:g}; the \"all\" row's fifth column is "
                "the AbsRel after each true segment takes the median of its read 1/d (an oracle pooling within "
                "objects, never across their edges)", ""]
    out.append(markdown_table(["region", "range m", "pixels", "AbsRel", "median read/true · segment oracle",
                               "cluttered windows"], error_source_rows(bench, renders, nominal_map)))
    config = ClassicalConfig()
    decoder = ClassicalDecoder.for_psf_map(nominal_map, config)
    plane_rows = [[f"{d:g} m"] + [plane_absrel(nominal, geometry, classical_depth(decoder, geometry), f, d,
                                               texture=texture)
                                  for texture in PLANE_TEXTURES for f in PLANE_FIELDS_DEG]
                  for d in PLANE_DEPTHS_M]
    out += ["", f"Textured fronto-parallel planes ({PLANE_PX}² window, φ 30°, σ 0.005, the same tensor kernels "
                "render and decode; `plane_texture`: a procedural scene's picture, or a 1/f² field): depth AbsRel",
            ""]
    out.append(markdown_table(["range"] + [f"{t}, θ {f:g}°" for t in PLANE_TEXTURES for f in PLANE_FIELDS_DEG],
                              plane_rows))
    out += ["", f"The edge of a built camera: 1/f² planes at θ {BUILT_FIELD_DEG:g}° (φ 30°, σ 0.005), the nominal camera "
                f"and one with the sensor radius {BUILT_SENSOR_RADIUS_PCT:+g} %, each rendered and decoded with its own "
                "tensor kernels; at bound: the AbsRel of an estimator at the Cramér–Rao bound of one tapered window "
                "(√(2/π) σ_d / d, `window_depth_bound`)", ""]
    out.append(markdown_table(["range", "AbsRel nominal", "AbsRel built", "at bound nominal", "at bound built"],
                              _built_camera_rows(nominal, geometry)))
    out += ["", f"Exact kernels against rotated tensor kernels: 1/f² planes at θ {EXACT_FIELD_DEG:g}° (φ 30°, σ 0.005) "
                "rendered with either, decoded with either (`exact_kernel_rows`): depth AbsRel", ""]
    out.append(markdown_table(["range"] + [f"{r} render, {d} kernels" for r in KERNEL_MODES for d in KERNEL_MODES],
                              exact_kernel_rows(nominal, geometry)))
    out += ["", f"Each window's own θ: 1/f² planes of {THETA_PLANE_PX}² at θ {BUILT_FIELD_DEG:g}° (φ 30°, σ 0.005), "
                f"rendered with exact kernels on {THETA_ZONE_PX}-px render zones, for the nominal camera and the built "
                f"one (sensor radius {BUILT_SENSOR_RADIUS_PCT:+g} %), decoded with exact kernels: a block's windows "
                "reading its centre's zone (θ step off), or each window the zones of a 1° θ grid around its own θ "
                "(`theta_step_rows`); AbsRel and the decode's CPU s (kernels traced on the first plane)", ""]
    out.append(markdown_table(["camera", "range"] + [f"AbsRel, θ step {s or 'off'}" for s in THETA_STEPS_DEG]
                              + [f"CPU s, θ step {s or 'off'}" for s in THETA_STEPS_DEG], theta_step_rows(geometry)))
    built_map = BuiltCamera(perturbation=Perturbation(sensor_radius_error_pct=BUILT_SENSOR_RADIUS_PCT)).psf_map(
        mode="tensor")
    out += ["", f"Windows that read the wrong side of focus: 1/f² planes blurred by one zone's tensor kernels (θ "
                f"{BUILT_FIELD_DEG:g}°, φ 30°, σ 0.005), read window by window (`window_outlier_rows`)", ""]
    out.append(markdown_table(["camera", "range", "AbsRel", f"windows off > {OUTLIER_FRACTION:.0%}"],
                              window_outlier_rows(nominal_map, built_map)))
    out += ["", f"The tensor kernels' rotation: a 1/f² plane at {ROTATION_DEPTH_M:g} m blurred by the on-axis kernels, "
                "read window by window with the kernel models of other zones (`rotation_rows`)", ""]
    out.append(markdown_table(["models of zone", "median depth m"], rotation_rows(decoder)))
    (a, b, c), z_rms, n_px = fit_sigma_model(nominal_map)
    out += ["", f"σ model fitted on {FIT_TILES} tiles per region, seed {FIT_SEED} ({n_px} pixels): "
                f"a = {a:.3g}, b = {b:.3g}, c = {c:.3g} m⁻¹; RMS of (error / σ) there {z_rms:.3f}. "
                "`ClassicalConfig`'s sigma_laplace_scale, sigma_spread_scale and sigma_floor_inv_per_m "
                "carry these values."]
    if full:
        out += ["", _full_frame(nominal, geometry)]
    return "\n".join(out)


def register(subparsers) -> None:
    register_target(subparsers, "decoder", "classical decoder: error against run time per knob, planes, full frame",
                    __doc__, "Classical decoder", run)
