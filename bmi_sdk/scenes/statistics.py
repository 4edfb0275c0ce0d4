"""Image statistics of scenes: the amplitude spectrum slope that natural images share.

Natural images have a radially averaged amplitude spectrum A(f) ∝ 1/f^α with α ≈ 1 (Field 1987; van der Schaaf &
van Hateren 1996, Vision Research 36: a power-spectrum exponent near 2α ≈ 1.9 with an image-to-image spread of about
±0.4, over 276 natural images). ``spectral_slope`` measures α of a grey image (``import`` it from this module):

1. subtract the mean and multiply by a 2-D Hann window (the image is not periodic: its borders would add a
   1/f² cross to the spectrum);
2. |FFT| at every frequency, f = √(fx² + fy²) in cycles per pixel;
3. average the amplitude in ``bins`` logarithmically spaced frequency bins over ``band_cpp`` (default 0.02–0.25
   cycles/px: above the lowest few frequencies, which the window smooths, and below the octave where the Bayer
   mosaic, the renderer's resampling and the sensor noise act);
4. fit log A = c − α log f by least squares over the bins' mean log frequency; return α.

``power_law_levels`` asks whether one power law holds across a band, not only on average: the radially averaged
power P(f) times f^2α, per logarithmic bin, relative to its geometric mean over the bins (1 in every bin for a
1/f^α image). The depth evidence decides dark, faint surfaces by the lowest frequencies of a 64-px window
(docs/decoder.md), so a dip or a bump in the 1/200–1/50 cycles/px octaves matters there even where α is right.

``python -m bmi_sdk.scenes.statistics`` prints α for procedural scenes and for ``bmi eval``'s tiles, and the levels
of a large scene (docs/scenes.md).
"""

from __future__ import annotations

import numpy as np

SLOPE_BAND_CPP = (0.02, 0.25)
"""The frequency band (cycles/px) ``spectral_slope`` fits over by default."""


def _binned_spectrum(image: np.ndarray, band_cpp: tuple[float, float], bins: int, name: str) -> tuple:
    """(log f, log mean amplitude, log mean power) per non-empty logarithmic bin of ``band_cpp`` of a grey image, or
    its channel mean, after the mean is removed and a 2-D Hann window applied (module doc, steps 1–3)."""
    image = np.asarray(image, np.float64)
    if image.ndim == 3:
        image = image.mean(axis=2)
    if image.ndim != 2:
        raise ValueError(f"{name} reads an H × W or H × W × C image, got shape {image.shape}")
    lo, hi = band_cpp
    if not 0.0 < lo < hi <= 0.5:
        raise ValueError(f"band_cpp must satisfy 0 < low < high <= 0.5 cycles/px, got {band_cpp}")
    height, width = image.shape
    if min(height, width) * lo < 2.0:
        raise ValueError(f"a {height} × {width} image holds fewer than 2 cycles at {lo:g} cycles/px: use at least "
                         f"{int(np.ceil(2.0 / lo))} px or a higher low end of band_cpp")
    window = np.hanning(height)[:, None] * np.hanning(width)[None, :]
    amplitude = np.abs(np.fft.fft2((image - image.mean()) * window)).ravel()
    f = np.hypot(np.fft.fftfreq(height)[:, None], np.fft.fftfreq(width)[None, :]).ravel()
    which = np.digitize(f, np.geomspace(lo, hi, bins + 1))
    rows = [(np.log(f[inside]).mean(), np.log(amplitude[inside].mean()), np.log((amplitude[inside] ** 2).mean()))
            for inside in (which == i for i in range(1, bins + 1)) if inside.any()]
    if len(rows) < 3:
        raise ValueError(f"a {height} × {width} image has frequencies in fewer than 3 bins of {band_cpp}")
    log_f, log_a, log_p = (np.array(column) for column in zip(*rows))
    return log_f, log_a, log_p


def spectral_slope(image: np.ndarray, band_cpp: tuple[float, float] = SLOPE_BAND_CPP, bins: int = 12) -> float:
    """α of an H × W (grey) or H × W × C (its channel mean) image's amplitude spectrum A(f) ∝ 1/f^α (module doc)."""
    log_f, log_a, _ = _binned_spectrum(image, band_cpp, bins, "spectral_slope")
    return float(-np.polyfit(log_f, log_a, 1)[0])


LEVELS_BAND_CPP = (1.0 / 256.0, 0.25)
"""The band (cycles/px) ``power_law_levels`` reads by default: from below a 64-px window's first DFT bin up."""


def power_law_levels(image: np.ndarray, band_cpp: tuple[float, float] = LEVELS_BAND_CPP, bins: int = 12,
                     alpha: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(f_cpp, level): per logarithmic bin of ``band_cpp``, its mean frequency and the mean power times f^(2 ``alpha``)
    relative to the bins' geometric mean (module doc): 1 in every bin for an image whose amplitude falls as 1/f^α."""
    log_f, _, log_p = _binned_spectrum(image, band_cpp, bins, "power_law_levels")
    whitened = log_p + 2.0 * alpha * log_f
    return np.exp(log_f), np.exp(whitened - whitened.mean())


SCENE_SCALES = (1, 4, 16)
"""Scene scales measured by ``python -m bmi_sdk.scenes.statistics``: those ``bmi eval`` names (×1 its stress test)."""

MAX_SCENE_PX = 8192
"""The largest scene side the command line draws (about 2 GB at 8192² px)."""


def _main() -> None:
    """Print α of procedural scenes: whole ones, and the centre crop of one drawn ×1, ×4, ×16 larger than the crop,
    as ``bmi eval`` draws its tiles (``nn.data.scene_crop``); then the power-law levels of large scenes' centres."""
    import argparse

    from bmi_sdk.scenes import generate_scene

    parser = argparse.ArgumentParser(description="amplitude spectrum slope α of procedural scenes (A ∝ 1/f^α)")
    parser.add_argument("--seeds", type=int, default=8, help="scenes per row (seeds 0 … N−1)")
    parser.add_argument("--px", type=int, default=512, help="side of the whole scenes measured")
    parser.add_argument("--crop-px", type=int, default=240,
                        help="side of the crops (default: a bmi eval tile of 192 px with its 24-px margins)")
    parser.add_argument("--levels-scene-px", type=int, default=3840,
                        help="side of the scenes whose power-law levels are read (default: a ×16 bmi eval tile's)")
    parser.add_argument("--levels-crop-px", type=int, default=1024, help="side of their centre crop that is read")
    parser.add_argument("--surface-px", type=int, default=256,
                        help="side of the windows on one surface whose levels are read in the same scenes")
    args = parser.parse_args()
    if args.seeds < 1:
        parser.error(f"--seeds must be at least 1, got {args.seeds}")
    for name in ("px", "crop_px", "levels_crop_px", "surface_px"):
        if getattr(args, name) < 64:
            parser.error(f"--{name.replace('_', '-')} must be at least 64 px, got {getattr(args, name)}")
    # memory: a scene costs ~30 bytes per pixel (rgb, range and the drawing's buffers), ~2 GB at 8192² px
    if args.px > MAX_SCENE_PX or args.crop_px * max(SCENE_SCALES) > MAX_SCENE_PX:
        parser.error(f"--px and --crop-px × {max(SCENE_SCALES)} must not exceed {MAX_SCENE_PX} px, "
                     f"got {args.px} and {args.crop_px}")
    if not args.levels_crop_px <= args.levels_scene_px <= MAX_SCENE_PX:
        parser.error(f"--levels-scene-px must lie in [--levels-crop-px, {MAX_SCENE_PX}], got {args.levels_scene_px}")
    if args.surface_px > args.levels_scene_px:
        parser.error(f"--surface-px must not exceed --levels-scene-px, got {args.surface_px}")

    def report(label: str, values: list[float]) -> None:
        print(f"| {label} | {np.mean(values):.2f} | {np.std(values):.2f} | {min(values):.2f}–{max(values):.2f} |")

    def crop(scale: int, seed: int) -> np.ndarray:
        side = args.crop_px * scale
        top = (side - args.crop_px) // 2
        return generate_scene(side, side, seed).rgb[top:top + args.crop_px, top:top + args.crop_px]

    print(f"| images ({args.seeds} seeds each; α over {SLOPE_BAND_CPP[0]:g}–{SLOPE_BAND_CPP[1]:g} cycles/px) | mean α "
          "| std | range |")
    print("|---|---|---|---|")
    report(f"whole scenes, {args.px}² px", [spectral_slope(generate_scene(args.px, args.px, seed).rgb)
                                            for seed in range(args.seeds)])
    for scale in SCENE_SCALES:
        report(f"centre {args.crop_px}² px of a scene drawn ×{scale} larger",
               [spectral_slope(crop(scale, seed)) for seed in range(args.seeds)])

    # each large scene is drawn once: its centre crop's levels, and those of its windows on one surface (no depth
    # step), read against 1/f noise through the same windows (the estimator's own bias at the band's low end)
    from bmi_sdk.scenes.procedural import pink_noise

    side, keep, n = args.levels_scene_px, args.levels_crop_px, args.surface_px
    top = (side - keep) // 2
    band = (2.0 / n, 0.25)
    crops, surfaces = [], []
    for seed in range(args.seeds):
        scene = generate_scene(side, side, seed)
        crops.append(power_law_levels(scene.rgb[top:top + keep, top:top + keep], bins=8))
        surfaces += [power_law_levels(scene.rgb[r:r + n, c:c + n], band, bins=6)[1]
                     for r, c in _surface_windows(scene.range_m, n)]

    def head(label: str, f_cpp: np.ndarray) -> None:
        print(f"\n| {label} | " + " | ".join(f"{f:.4f}" for f in f_cpp) + " |")
        print("|---|" + "---|" * len(f_cpp))

    def row(label: str, values) -> None:
        print(f"| {label} | " + " | ".join(values) + " |")

    level = np.array([lv for _, lv in crops])
    head(f"power × f² relative to its band mean: centre {keep}² px of {side}² px scenes ({args.seeds} seeds)",
         crops[0][0])
    row("mean (1 for a 1/f image)", (f"{v:.2f}" for v in level.mean(axis=0)))
    row("seeds' range", (f"{a:.2f}–{b:.2f}" for a, b in zip(level.min(axis=0), level.max(axis=0))))

    if not surfaces:
        print(f"\nno {n}² px window of these scenes lies on one surface")
        return
    noise_reads = [power_law_levels(pink_noise((n, n), np.random.default_rng(seed)), band, bins=6) for seed in range(64)]
    reference = np.mean([lv for _, lv in noise_reads], axis=0)
    surface_mean = np.mean(surfaces, axis=0)
    head(f"power × f² relative to its band mean, {n}² px windows on one surface ({len(surfaces)} windows of "
         f"{args.seeds} {side}² px scenes)", noise_reads[0][0])
    row("1/f noise (64 draws)", (f"{v:.2f}" for v in reference))
    row("surfaces, mean", (f"{v:.2f}" for v in surface_mean))
    row("surfaces / 1/f noise", (f"{v:.2f}" for v in surface_mean / reference))


def _surface_windows(range_m: np.ndarray, n: int):
    """(row, col) of the non-overlapping n × n windows of ``range_m`` that lie on one surface: no step between
    neighbouring pixels larger than 1 % of the window's nearest range."""
    for r in range(0, range_m.shape[0] - n + 1, n):
        for c in range(0, range_m.shape[1] - n + 1, n):
            depth = range_m[r:r + n, c:c + n]
            step = max(np.abs(np.diff(depth, axis=0)).max(), np.abs(np.diff(depth, axis=1)).max())
            if step < 0.01 * depth.min():
                yield r, c

if __name__ == "__main__":
    _main()
