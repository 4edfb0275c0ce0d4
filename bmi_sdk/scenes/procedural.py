"""Procedural RGB + range scenes in sensor pixel space: the embedded default for training, demo and tests.

Each output pixel is one sensor pixel's ray; ``range_m`` is the distance along
it (no camera model is assumed: a surface whose inverse range is affine in the
pixel coordinates is what a plane looks like through a pinhole, and to first
order through the sensor's own mapping). The scene is built like a z-buffered
drawing, nearest surface wins, so occlusion is exact per pixel:

* a far, slanted back wall and (usually) a floor receding to a horizon;
* opaque objects (ellipses, boxes, polygons, organic blobs) whose inverse range
  is an affine slanted plane across the object, at ranges from ``near_m`` to
  just before the wall; their silhouettes are sharp (depth edges are steps);
* thin structures (poles, wires) 1 px to ~0.3 % of the frame wide;
* textures with ≈1/f amplitude spectra: a low-resolution 1/f field (1/32 of
  the frame, cheap at any size) upsampled, plus a periodic 1/f detail tile
  high-passed above 1/64 cycle/px and cropped at random offsets; reflectance is
  log-normal (``base colour · exp(texture)``), with per-channel colour noise.
  With ``exponent_spread`` s > 0 each surface's luminance texture has its own
  power spectrum 1/f^p, p drawn from N(2, s²) (clipped to [1, 3]), as natural
  images' exponents scatter about 2 (van der Schaaf & van Hateren, Vision
  Research 36, 1996: s ≈ 0.4); the draws come from a generator spawned from
  the scene's, so the scene's layout, colours and ranges are those of s = 0;
* a smooth illumination field (exp of 1/f noise) that makes dark regions, a few
  polygonal shadows, and specular spots that saturate (clipped at 1).

Cost is proportional to the painted area: shapes are drawn with OpenCV into
their bounding boxes and textures are generated per box, so the full
6000×4500 frame takes a few seconds.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from bmi_sdk.scenes.scene import Scene

_LOW_RES_FACTOR = 32  # low-resolution texture field: one sample per 32×32 output pixels
_DETAIL_TILE_PX = 1024  # periodic detail tile (frequencies above _DETAIL_CUTOFF)
_DETAIL_CUTOFF = 1.0 / 64  # cycles/px: where the detail tile takes over from the upsampled low field
POWER_EXPONENT_RANGE = (1.0, 3.0)  # a surface's drawn power-spectrum exponent is clipped to this range
_EXPONENT_STEP = 0.04  # drawn power exponents are rounded to this step, so a scene makes few detail tiles


def pink_noise(shape: tuple[int, int], rng: np.random.Generator, highpass_cpp: float = 0.0,
               exponent: float = 1.0) -> np.ndarray:
    """Zero-mean, unit-std periodic noise with amplitude spectrum ∝ 1/f^exponent (float32).

    ``highpass_cpp`` (cycles/px) softly removes frequencies below it (Gaussian
    high-pass), so a tile can carry only the detail band.
    """
    h, w = shape
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    f = np.hypot(fy, fx)
    f[0, 0] = 1.0
    amplitude = f ** -exponent
    amplitude[0, 0] = 0.0
    if highpass_cpp > 0:
        amplitude *= 1.0 - np.exp(-((f / highpass_cpp) ** 2))
    spectrum = np.fft.rfft2(rng.standard_normal((h, w))) * amplitude
    field = np.fft.irfft2(spectrum, s=(h, w))
    std = field.std()
    return (field / std if std > 0 else field).astype(np.float32)


def _add_periodic(field: np.ndarray, tile: np.ndarray, weight: float, oy: int, ox: int) -> None:
    """field[y, x, :] += weight · tile[(y + oy) mod T, (x + ox) mod T], block by block (no gather)."""
    h, w = field.shape[:2]
    th, tw = tile.shape
    y = 0
    while y < h:
        ty = (y + oy) % th
        dy = min(th - ty, h - y)
        x = 0
        while x < w:
            tx = (x + ox) % tw
            dx = min(tw - tx, w - x)
            field[y:y + dy, x:x + dx] += (weight * tile[ty:ty + dy, tx:tx + dx])[:, :, None]
            x += dx
        y += dy


class _Painter:
    """Z-buffered drawing into the output arrays, one bounding box at a time."""

    def __init__(self, height: int, width: int, rng: np.random.Generator, near_m: float, far_m: float,
                 exponent_spread: float = 0.0):
        self.h, self.w, self.rng = height, width, rng
        self.near_m, self.far_m = near_m, far_m
        self.rgb = np.zeros((height, width, 3), dtype=np.float32)
        self.range_m = np.full((height, width), np.inf, dtype=np.float32)
        self.tile = pink_noise((_DETAIL_TILE_PX, _DETAIL_TILE_PX), rng, highpass_cpp=_DETAIL_CUTOFF)
        # Share of the 1/f variance above the cutoff for a frame-sized texture: the
        # log-bandwidth of each part (an octave of 1/f noise holds equal power).
        size = max(height, width)
        low_band, high_band = math.log(max(size * _DETAIL_CUTOFF, 1.0) + 1.0), math.log(0.5 / _DETAIL_CUTOFF)
        self.detail_weight = math.sqrt(high_band / (low_band + high_band))
        self.low_weight = math.sqrt(low_band / (low_band + high_band))
        self.exponent_spread = exponent_spread
        # spawned, not drawn: the main generator's stream (layout, colours, ranges) is that of a 1/f² scene
        self.exponent_rng = rng.spawn(1)[0] if exponent_spread > 0 else None
        self.bands: dict[float, tuple[float, float, np.ndarray]] = {}

    def power_exponent(self) -> float:
        """The next surface's power-spectrum exponent p (module doc): 2, or drawn from N(2, spread²), clipped to
        ``POWER_EXPONENT_RANGE`` and rounded to ``_EXPONENT_STEP``."""
        if self.exponent_rng is None:
            return 2.0
        p = float(np.clip(2.0 + self.exponent_spread * self.exponent_rng.standard_normal(), *POWER_EXPONENT_RANGE))
        return round(p / _EXPONENT_STEP) * _EXPONENT_STEP

    def texture_bands(self, p: float) -> tuple[float, float, np.ndarray]:
        """(low-field weight, detail weight, detail tile) of a 1/f^p texture: the weights split its variance between
        the low field (1/size to ``_DETAIL_CUTOFF`` cycles/px) and the detail tile (beyond, to 0.5) as the 2-D power
        ∝ f^−p distributes it, ∫ f^(1−p) df over each band; p = 2 is the 1/f² split made at construction."""
        if p == 2.0:
            return self.low_weight, self.detail_weight, self.tile
        if p not in self.bands:
            assert self.exponent_rng is not None
            size = max(self.h, self.w)
            k = 2.0 - p
            low = abs((_DETAIL_CUTOFF ** k - (1.0 / size) ** k) / k)
            high = abs((0.5 ** k - _DETAIL_CUTOFF ** k) / k)
            tile = pink_noise((_DETAIL_TILE_PX, _DETAIL_TILE_PX), self.exponent_rng, highpass_cpp=_DETAIL_CUTOFF,
                              exponent=p / 2.0)
            self.bands[p] = (math.sqrt(low / (low + high)), math.sqrt(high / (low + high)), tile)
        return self.bands[p]

    # -- textures -----------------------------------------------------------
    def texture(self, h: int, w: int, contrast: float, chroma: float, out: np.ndarray | None = None) -> np.ndarray:
        """h×w×3 log-reflectance variation: luminance of power spectrum 1/f^p (low field + detail tile; p 2, or drawn
        per surface, ``power_exponent``) + 1/f colour noise."""
        rng = self.rng
        p = self.power_exponent()
        low_weight, detail_weight, tile = self.texture_bands(p)
        lh, lw = max(2, -(-h // _LOW_RES_FACTOR)), max(2, -(-w // _LOW_RES_FACTOR))
        low = pink_noise((lh, lw), rng, exponent=p / 2.0)
        colour = np.stack([pink_noise((lh, lw), rng) for _ in range(3)], axis=2)
        low3 = (contrast * low_weight) * low[:, :, None] + chroma * colour
        field = cv2.resize(np.ascontiguousarray(low3), (w, h), dst=out, interpolation=cv2.INTER_LINEAR)
        _add_periodic(field, tile, contrast * detail_weight, *rng.integers(0, _DETAIL_TILE_PX, size=2))
        return field

    def random_colour(self) -> np.ndarray:
        """A linear base reflectance: log-uniform brightness, moderate saturation."""
        value = math.exp(self.rng.uniform(math.log(0.03), math.log(0.7)))
        tint = np.exp(self.rng.normal(0.0, 0.35, size=3))
        return (value * tint / tint.mean()).astype(np.float32)

    # -- depth --------------------------------------------------------------
    def plane_range(self, h: int, w: int, range0_m: float, slant: float) -> np.ndarray:
        """h×w range of a slanted plane: inverse range affine in pixels, ±``slant`` relative over the box."""
        a, b = self.rng.uniform(-1, 1, size=2)
        a, b = slant * a / (abs(a) + abs(b) + 1e-9), slant * b / (abs(a) + abs(b) + 1e-9)
        y = (1.0 + b * np.linspace(-1, 1, h, dtype=np.float32)[:, None]) / range0_m
        x = (a / range0_m) * np.linspace(-1, 1, w, dtype=np.float32)[None, :]
        inverse = y + x
        np.reciprocal(inverse, out=inverse)
        return np.clip(inverse, self.near_m, self.far_m, out=inverse)

    # -- drawing ------------------------------------------------------------
    def box(self, y0: int, x0: int, h: int, w: int):
        """Clip a box to the frame: (slices, offset of the clipped box inside the original)."""
        ya, xa, yb, xb = max(y0, 0), max(x0, 0), min(y0 + h, self.h), min(x0 + w, self.w)
        if ya >= yb or xa >= xb:
            return None
        return (slice(ya, yb), slice(xa, xb)), (ya - y0, xa - x0)

    def paint(self, sl, mask: np.ndarray, range_m: np.ndarray, rgb: np.ndarray) -> None:
        """Write rgb/range where ``mask`` holds and the surface is nearer than what is there."""
        current = self.range_m[sl]
        hit = np.less(range_m, current)
        hit &= mask
        np.copyto(current, range_m, where=hit)
        np.copyto(self.rgb[sl], rgb, where=hit[:, :, None])

    def background(self, range0_m: float, slant: float) -> None:
        """Fill the whole frame with one textured slanted surface, in place (no temporaries of frame size × 3)."""
        rgb = self.texture(self.h, self.w, self.rng.uniform(0.15, 0.6), self.rng.uniform(0.02, 0.1), out=self.rgb)
        np.exp(rgb, out=rgb)
        rgb *= self.random_colour()
        self.range_m[:] = self.plane_range(self.h, self.w, range0_m, slant)

    def pixels(self, ys: np.ndarray, xs: np.ndarray, range_m: np.ndarray, rgb: np.ndarray) -> None:
        """Z-buffered write of a sparse set of pixels (thin structures)."""
        hit = range_m < self.range_m[ys, xs]
        ys, xs = ys[hit], xs[hit]
        self.range_m[ys, xs] = range_m[hit]
        self.rgb[ys, xs] = rgb[hit]

    def surface(self, y0: int, x0: int, mask: np.ndarray, range0_m: float, slant: float,
                contrast: float | None = None) -> None:
        """A textured slanted surface whose silhouette is ``mask`` (box at y0, x0)."""
        clipped = self.box(y0, x0, *mask.shape)
        if clipped is None:
            return
        sl, (oy, ox) = clipped
        h, w = sl[0].stop - sl[0].start, sl[1].stop - sl[1].start
        full_shape = mask.shape
        mask = mask[oy:oy + h, ox:ox + w].astype(bool)
        if not mask.any():
            return
        rng = self.rng
        contrast = rng.uniform(0.15, 0.8) if contrast is None else contrast
        rgb = self.texture(h, w, contrast, chroma=rng.uniform(0.02, 0.15))
        np.exp(rgb, out=rgb)
        rgb *= self.random_colour()
        full_range = self.plane_range(*full_shape, range0_m, slant)[oy:oy + h, ox:ox + w]
        self.paint(sl, mask, full_range, rgb)


def _shape_mask(kind: str, size: int, rng: np.random.Generator) -> np.ndarray:
    """A size×size uint8 silhouette of the given kind, centred, filling most of the box."""
    mask = np.zeros((size, size), dtype=np.uint8)
    c = (size - 1) / 2
    shift = 4  # OpenCV sub-pixel bits
    scale = 1 << shift
    if kind == "ellipse":
        axes = (int(c * scale), int(c * rng.uniform(0.25, 1.0) * scale))
        cv2.ellipse(mask, (int(c * scale), int(c * scale)), axes, rng.uniform(0, 180), 0, 360, 1, -1,
                    cv2.LINE_8, shift)
    elif kind in ("box", "polygon"):
        if kind == "box":
            aspect = rng.uniform(0.15, 1.0)
            corners = np.array([[-1, -aspect], [1, -aspect], [1, aspect], [-1, aspect]]) / math.hypot(1, aspect)
            t = rng.uniform(0, math.pi)
            corners = corners @ np.array([[math.cos(t), math.sin(t)], [-math.sin(t), math.cos(t)]])
        else:
            n = int(rng.integers(3, 9))
            angles = np.sort(rng.uniform(0, 2 * math.pi, size=n))
            radii = rng.uniform(0.55, 1.0, size=n)
            corners = np.stack([radii * np.cos(angles), radii * np.sin(angles)], axis=1)
        points = np.round((c + c * corners) * scale).astype(np.int32)
        cv2.fillPoly(mask, [points], 1, cv2.LINE_8, shift)
    elif kind == "blob":
        n = int(rng.integers(4, 10))
        lobes = cv2.resize(pink_noise((n, n), rng, exponent=2.0), (size, size), interpolation=cv2.INTER_CUBIC)
        r = np.linspace(-1, 1, size, dtype=np.float32)
        falloff = 1.0 - (r[:, None] ** 2 + r[None, :] ** 2)
        mask[:] = (0.6 * lobes + 2.0 * falloff > 0.9)
    else:
        raise ValueError(f"unknown shape kind {kind!r}")
    return mask


def generate_scene(height_px: int, width_px: int, rng: np.random.Generator | int, *,
                   near_m: float = 0.7, far_m: float = 10.0, n_objects: int | None = None,
                   n_thin: int | None = None, name: str | None = None, exponent_spread: float = 0.0) -> Scene:
    """A random layered scene of ``height_px``×``width_px`` (linear RGB, range along each pixel's ray).

    ``rng`` is a ``numpy.random.Generator`` or a seed; the same seed gives the
    same scene. ``n_objects``/``n_thin`` default to random counts (10–24, 2–7).
    Ranges lie in [near_m, far_m]; every pixel is valid (no NaN). ``exponent_spread``: the std of the surfaces'
    texture power exponents about 2 (module doc; 0: every surface 1/f²).
    """
    if not 0.0 <= exponent_spread <= 1.0:
        raise ValueError(f"exponent_spread must be in [0, 1] (the std of the power exponents about 2), got "
                         f"{exponent_spread}")
    if height_px < 8 or width_px < 8:
        raise ValueError(f"scene must be at least 8×8 px, got {height_px}×{width_px}")
    if not 0 < near_m < far_m:
        raise ValueError(f"need 0 < near_m < far_m, got {near_m}, {far_m}")
    seed_name = f"seed{rng}" if isinstance(rng, (int, np.integer)) else "rng"
    rng = np.random.default_rng(rng) if not isinstance(rng, np.random.Generator) else rng
    H, W = height_px, width_px
    s = min(H, W)
    p = _Painter(H, W, rng, near_m, far_m, exponent_spread)

    # back wall: the whole frame, far, gently slanted
    wall_m = math.exp(rng.uniform(math.log(0.45 * far_m), math.log(far_m)))
    p.background(wall_m, slant=0.3)
    wall_min_m = float(p.range_m.min())

    # floor: inverse range grows linearly below a horizon (a ground plane seen from above it)
    if rng.uniform() < 0.75:
        horizon = int(rng.uniform(0.35, 0.75) * H)
        floor_h = H - horizon
        bottom_m = rng.uniform(near_m, min(2.5, wall_min_m))
        rows = (np.arange(floor_h, dtype=np.float32) + 0.5) / floor_h
        floor_range = np.broadcast_to(np.clip(bottom_m / rows, near_m, far_m)[:, None], (floor_h, W))
        rgb = p.texture(floor_h, W, contrast=rng.uniform(0.2, 0.6), chroma=0.05)
        np.exp(rgb, out=rgb)
        rgb *= p.random_colour()
        p.paint((slice(horizon, H), slice(0, W)), np.ones((floor_h, W), dtype=bool), floor_range, rgb)

    # objects: sizes log-uniform, ranges log-uniform in front of the wall
    n_objects = int(rng.integers(10, 25)) if n_objects is None else n_objects
    kinds = ("ellipse", "box", "polygon", "blob")
    for _ in range(n_objects):
        size = max(4, int(s * math.exp(rng.uniform(math.log(0.04), math.log(0.6)))))
        y0 = int(rng.integers(-size // 3, H - 2 * size // 3))
        x0 = int(rng.integers(-size // 3, W - 2 * size // 3))
        mask = _shape_mask(kinds[int(rng.integers(len(kinds)))], size, rng)
        range0 = math.exp(rng.uniform(math.log(near_m), math.log(max(near_m * 1.01, 0.95 * wall_min_m))))
        p.surface(y0, x0, mask, range0, slant=rng.uniform(0.0, 0.4))

    # thin structures: long lines 1 px to ~0.3 % of the frame wide, depth varying along them
    n_thin = int(rng.integers(2, 8)) if n_thin is None else n_thin
    max_thickness = max(1, round(0.003 * s))
    for _ in range(n_thin):
        thickness = int(rng.integers(1, max_thickness + 1))
        a = rng.uniform((0, 0), (W, H))
        angle, length = rng.uniform(0, math.pi), rng.uniform(0.3, 1.2) * s
        b = a + length * np.array([math.cos(angle), math.sin(angle)])
        lo = np.floor(np.minimum(a, b)).astype(int) - thickness
        hi = np.ceil(np.maximum(a, b)).astype(int) + thickness + 1
        x0, y0 = int(max(lo[0], 0)), int(max(lo[1], 0))
        x1, y1 = int(min(hi[0], W)), int(min(hi[1], H))
        if x0 >= x1 or y0 >= y1:
            continue
        mask = np.zeros((y1 - y0, x1 - x0), dtype=np.uint8)
        cv2.line(mask, (int(round(a[0])) - x0, int(round(a[1])) - y0),
                 (int(round(b[0])) - x0, int(round(b[1])) - y0), 1, thickness)
        ys, xs = np.nonzero(mask)
        if ys.size == 0:
            continue
        # range varies linearly in inverse along the line; texture from the detail tile
        t = ((xs + x0 - a[0]) * math.cos(angle) + (ys + y0 - a[1]) * math.sin(angle)) / length
        range0 = math.exp(rng.uniform(math.log(near_m), math.log(max(near_m * 1.01, 0.8 * wall_min_m))))
        inverse = (1.0 + rng.uniform(-0.3, 0.3) * (2 * t - 1)) / range0
        range_m = np.clip(1.0 / inverse, near_m, far_m).astype(np.float32)
        shade = np.exp(0.15 * p.tile[(ys + y0) % _DETAIL_TILE_PX, (xs + x0) % _DETAIL_TILE_PX])
        p.pixels(ys + y0, xs + x0, range_m, shade[:, None] * p.random_colour())

    rgb = p.rgb
    # illumination: smooth log-normal shading (dark and bright regions) ...
    lh, lw = max(2, H // 64), max(2, W // 64)
    light = cv2.resize(pink_noise((lh, lw), rng, exponent=1.5), (W, H), interpolation=cv2.INTER_LINEAR)
    light *= rng.uniform(0.3, 0.7)
    np.exp(light, out=light)
    rgb *= light[:, :, None]
    del light
    # ... a few hard shadows ...
    for _ in range(int(rng.integers(0, 4))):
        size = max(4, int(s * rng.uniform(0.1, 0.5)))
        y0, x0 = int(rng.integers(0, H)), int(rng.integers(0, W))
        clipped = p.box(y0, x0, size, size)
        if clipped is not None:
            sl, (oy, ox) = clipped
            m = _shape_mask("polygon", size, rng)[oy:oy + sl[0].stop - sl[0].start, ox:ox + sl[1].stop - sl[1].start]
            rgb[sl][m.astype(bool)] *= rng.uniform(0.05, 0.3)
    # ... and specular spots that saturate
    for _ in range(int(rng.integers(2, 9))):
        radius = max(1.0, s * rng.uniform(0.002, 0.02))
        cy, cx = rng.uniform(0, H), rng.uniform(0, W)
        r = int(math.ceil(3 * radius))
        clipped = p.box(int(cy) - r, int(cx) - r, 2 * r + 1, 2 * r + 1)
        if clipped is None:
            continue
        sl = clipped[0]
        yy = np.arange(sl[0].start, sl[0].stop, dtype=np.float32)[:, None] - cy
        xx = np.arange(sl[1].start, sl[1].stop, dtype=np.float32)[None, :] - cx
        spot = rng.uniform(1.5, 4.0) * np.exp(-(yy ** 2 + xx ** 2) / (2 * radius ** 2))
        rgb[sl] += spot[:, :, None]
    np.clip(rgb, 0.0, 1.0, out=rgb)
    return Scene(rgb=rgb, range_m=p.range_m, name=name or f"procedural/{seed_name}/{H}x{W}")
