"""Placing dataset images on the curved sensor: the paper's protocols (§4.1).

A dataset image is a pinhole view. We treat it as a *local tangent plane*: a
virtual pinhole camera whose optical axis is the chief ray of a chosen sensor
position (θ0, φ0), whose field across the image width is ``fov_deg`` and whose
principal point is the image centre. Every sensor pixel of the region of
interest (ROI) looks along its own chief ray (from :class:`SensorGeometry`);
that ray is projected exactly into the virtual image (x'/z', y'/z' — the tan
law), so the scene lands on the sensor with the sensor's real angular sampling.

Depth: the image's planar z (recovered from the scene's range with its *source*
intrinsics) is taken as the planar z of the virtual view, so a fronto-parallel
plane stays a plane facing the patch axis: range along a sensor ray at angle α
from the axis is z / cos α. Lateral scale is not preserved (a 63° NYU view is
squeezed into 12° at unchanged depth); the paper accepts this: the protocol
samples field-dependent PSFs, it is not one geometrically coherent scene.

Protocols:

* :func:`place_patch` — NYUv2 / FlyingThings3D training: ~12° across the image,
  at a given or random (θ0, φ0) (uniform over sensor pixels, optionally within a
  θ range), ROI kept inside the sensor.
* :func:`place_wide` — Middlebury evaluation: ~60° across the image, pushed
  along φ0 (default: towards a sensor corner, where the field reaches ≈60°)
  as far out as the sensor allows.

``projection="equiangular"`` is the small-angle alternative (image radius ∝ α
instead of tan α — what pasting a resized image onto the sensor does); the
two differ at the patch edge by tan α/α − 1, see :func:`tan_vs_angle_relative_error`.
RGB is resampled bilinearly (area-prefiltered first when the sensor samples the
image more coarsely than its pixels); depth takes the nearest image pixel, so
no range is invented across an occlusion edge.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from bmi_sdk.geometry import BMI_SENSOR, SensorGeometry
from bmi_sdk.scenes.scene import Scene

PROJECTIONS = ("pinhole", "equiangular")
_BOUNDARY_SAMPLES = 512  # points per image edge when bounding the patch on the sensor
_CHUNK_PX = 1 << 20  # sensor pixels resampled per block (bounds the float64 temporaries)


def tan_vs_angle_relative_error(half_angle_deg: float) -> float:
    """tan α / α − 1: the small-angle discrepancy between a pinhole and an equiangular patch at its edge."""
    a = math.radians(half_angle_deg)
    return math.tan(a) / a - 1.0


@dataclass(frozen=True)
class PatchMapping:
    """An image of ``width_px``×``height_px`` seen as a pinhole view along the chief ray (θ0, φ0).

    Image axes: u grows to the right, v downwards; with ``roll_deg`` 0 the image's
    "down" is the projection of the camera's y (down) axis, so images stay upright.
    """

    geometry: SensorGeometry
    theta0_deg: float
    phi0_deg: float
    fov_deg: float
    width_px: int
    height_px: int
    roll_deg: float = 0.0
    projection: str = "pinhole"

    def __post_init__(self):
        if self.projection not in PROJECTIONS:
            raise ValueError(f"projection must be one of {PROJECTIONS}, got {self.projection!r}")
        if not 0 < self.fov_deg < 170:
            raise ValueError(f"fov_deg must be in (0, 170), got {self.fov_deg}")
        if not 0 <= self.theta0_deg <= self.geometry.max_field_deg:
            raise ValueError(f"theta0_deg must be in [0, {self.geometry.max_field_deg}] (the sensor's field), "
                             f"got {self.theta0_deg}")
        if self.width_px <= 0 or self.height_px <= 0:
            raise ValueError(f"image size must be positive, got {self.width_px}×{self.height_px}")

    # -- the virtual camera ----------------------------------------------------
    @property
    def focal_px(self) -> float:
        """Image pixels per unit tan α (pinhole) or per radian (equiangular)."""
        half = math.radians(self.fov_deg) / 2
        return (self.width_px / 2) / (math.tan(half) if self.projection == "pinhole" else half)

    @property
    def principal_point_px(self) -> tuple[float, float]:
        """(u, v) of the patch axis: the image centre."""
        return (self.width_px - 1) / 2, (self.height_px - 1) / 2

    def axes(self) -> np.ndarray:
        """3×3 rows (e_u, e_v, e_axis) in the sensor's camera frame (x right, y down, z forward)."""
        t, p = math.radians(self.theta0_deg), math.radians(self.phi0_deg)
        axis = np.array([math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)])
        e_u = np.cross([0.0, 1.0, 0.0], axis)  # ⟂ to camera y and to the axis: the image's horizontal
        e_u /= np.linalg.norm(e_u)
        e_v = np.cross(axis, e_u)
        r = math.radians(self.roll_deg)
        return np.stack([math.cos(r) * e_u + math.sin(r) * e_v, -math.sin(r) * e_u + math.cos(r) * e_v, axis])

    # -- image <-> sensor ------------------------------------------------------
    def image_to_direction(self, u, v) -> np.ndarray:
        """Unit directions (…, 3) in the camera frame of image points (u, v) (pixel centres 0-based)."""
        cu, cv = self.principal_point_px
        x = (np.asarray(u, dtype=np.float64) - cu) / self.focal_px
        y = (np.asarray(v, dtype=np.float64) - cv) / self.focal_px
        if self.projection == "pinhole":
            local = np.stack([x, y, np.ones_like(x)], axis=-1)
            local /= np.linalg.norm(local, axis=-1, keepdims=True)
        else:
            alpha, psi = np.hypot(x, y), np.arctan2(y, x)
            local = np.stack([np.sin(alpha) * np.cos(psi), np.sin(alpha) * np.sin(psi), np.cos(alpha)], axis=-1)
        return local @ self.axes()

    def image_to_sensor(self, u, v) -> tuple[np.ndarray, np.ndarray]:
        """Fractional sensor (row, col) where image point (u, v) lands."""
        d = self.image_to_direction(u, v)
        theta = np.degrees(np.arctan2(np.hypot(d[..., 0], d[..., 1]), d[..., 2]))  # precise near the axis
        phi = np.degrees(np.arctan2(d[..., 1], d[..., 0]))
        return self.geometry.pixel_of_field(theta, phi)

    def directions_to_image(self, directions: np.ndarray):
        """(u, v, cos α) of camera-frame unit directions; u, v NaN for rays behind the image."""
        local = np.asarray(directions, dtype=np.float64) @ self.axes().T
        x, y, z = local[..., 0], local[..., 1], local[..., 2]
        cu, cv = self.principal_point_px
        if self.projection == "pinhole":
            with np.errstate(divide="ignore", invalid="ignore"):
                ahead = z > 0
                u = np.where(ahead, cu + self.focal_px * x / z, np.nan)
                v = np.where(ahead, cv + self.focal_px * y / z, np.nan)
        else:
            alpha, psi = np.arctan2(np.hypot(x, y), z), np.arctan2(y, x)
            u, v = cu + self.focal_px * alpha * np.cos(psi), cv + self.focal_px * alpha * np.sin(psi)
        return u, v, z

    def sensor_to_image(self, rows, cols):
        """(u, v, cos α) of the chief rays of sensor pixels (rows, cols); α is the angle from the patch axis."""
        return self.directions_to_image(self.geometry.ray_directions(rows, cols))

    def bounding_roi(self) -> tuple[int, int, int, int]:
        """(row0, col0, height, width) of sensor pixels the image may cover (not clipped to the sensor)."""
        w, h, n = self.width_px, self.height_px, _BOUNDARY_SAMPLES
        su, sv = np.linspace(-0.5, w - 0.5, n), np.linspace(-0.5, h - 0.5, n)
        u = np.concatenate([su, su, np.full(n, -0.5), np.full(n, w - 0.5)])
        v = np.concatenate([np.full(n, -0.5), np.full(n, h - 0.5), sv, sv])
        rows, cols = self.image_to_sensor(u, v)
        if not (np.all(np.isfinite(rows)) and np.all(np.isfinite(cols))):
            raise ValueError(f"the {self.fov_deg}° patch at θ0={self.theta0_deg:.2f}° reaches beyond the lens's "
                             f"chief-ray table")
        row0, col0 = math.floor(rows.min()) - 1, math.floor(cols.min()) - 1
        return row0, col0, math.ceil(rows.max()) + 1 - row0 + 1, math.ceil(cols.max()) + 1 - col0 + 1

    def fits_sensor(self) -> bool:
        row0, col0, height, width = self.bounding_roi()
        g = self.geometry
        return row0 >= 0 and col0 >= 0 and row0 + height <= g.height_px and col0 + width <= g.width_px


@dataclass(frozen=True)
class PlacedScene:
    """A scene resampled onto the sensor pixels of ``roi`` = (row0, col0, height, width).

    ``rgb`` is linear (0 outside the image), ``range_m`` the range along each
    sensor pixel's chief ray (NaN outside the image or where the source had no
    depth), ``valid`` marks pixels inside the image and the sensor's field.
    ``clipped`` says the image extended past the sensor and lost that part.
    """

    rgb: np.ndarray
    range_m: np.ndarray
    valid: np.ndarray
    roi: tuple[int, int, int, int]
    mapping: PatchMapping
    name: str
    clipped: bool = False


def _sensor_roi(mapping: PatchMapping, on_edge: str) -> tuple[tuple[int, int, int, int], bool]:
    row0, col0, height, width = mapping.bounding_roi()
    g = mapping.geometry
    r0, c0 = max(row0, 0), max(col0, 0)
    r1, c1 = min(row0 + height, g.height_px), min(col0 + width, g.width_px)
    clipped = (r0, c0, r1, c1) != (row0, col0, row0 + height, col0 + width)
    if clipped and on_edge == "raise":
        raise ValueError(
            f"the {mapping.fov_deg}° patch at θ0={mapping.theta0_deg:.2f}°, φ0={mapping.phi0_deg:.2f}° needs "
            f"sensor rows {row0}..{row0 + height - 1}, cols {col0}..{col0 + width - 1}, outside the "
            f"{g.height_px}×{g.width_px} sensor; choose a smaller θ0 or pass on_edge='clip'")
    if r0 >= r1 or c0 >= c1:
        raise ValueError(f"the patch at θ0={mapping.theta0_deg:.2f}° does not fall on the sensor")
    return (r0, c0, r1 - r0, c1 - c0), clipped


def _sensor_px_per_rad(geometry: SensorGeometry, row: float, col: float) -> float:
    """Finest sampling density of the sensor around a pixel: pixels per radian of chief-ray angle."""
    rays = geometry.ray_directions(np.array([row, row, row + 1]), np.array([col, col + 1, col]))
    steps = [math.acos(min(1.0, float(rays[0] @ rays[k]))) for k in (1, 2)]
    return 1.0 / max(min(steps), 1e-12)


def resample_to_sensor(scene: Scene, mapping: PatchMapping, on_edge: str = "raise") -> PlacedScene:
    """Resample ``scene`` (a pinhole image with intrinsics) onto the sensor through ``mapping``."""
    if on_edge not in ("raise", "clip"):
        raise ValueError(f"on_edge must be 'raise' or 'clip', got {on_edge!r}")
    if scene.intrinsics is None:
        raise ValueError(f"scene {scene.name!r} has no pinhole intrinsics; placement needs a dataset image "
                         f"(procedural scenes are generated in sensor pixel space already)")
    h, w = scene.shape
    if (mapping.height_px, mapping.width_px) != (h, w):
        raise ValueError(f"mapping is for {mapping.height_px}×{mapping.width_px}, scene is {h}×{w}")
    (row0, col0, height, width), clipped = _sensor_roi(mapping, on_edge)
    z_image = scene.intrinsics.range_to_z(scene.range_m)

    # RGB anti-aliasing: image pixels per sensor pixel at the patch centre (focal_px is the
    # image's px/rad there for both projections)
    centre_row, centre_col = mapping.geometry.pixel_of_field(mapping.theta0_deg, mapping.phi0_deg)
    shrink = mapping.focal_px / _sensor_px_per_rad(mapping.geometry, float(centre_row), float(centre_col))
    rgb_src = scene.rgb
    if shrink > 1.0:
        size = (max(1, round(w / shrink)), max(1, round(h / shrink)))
        rgb_src = cv2.resize(scene.rgb, size, interpolation=cv2.INTER_AREA)
    scale_u, scale_v = rgb_src.shape[1] / w, rgb_src.shape[0] / h

    rgb = np.zeros((height, width, 3), dtype=np.float32)
    range_m = np.full((height, width), np.nan, dtype=np.float32)
    valid = np.zeros((height, width), dtype=bool)
    cos_field_max = math.cos(math.radians(mapping.geometry.max_field_deg))
    step = max(1, _CHUNK_PX // width)
    cols = np.arange(col0, col0 + width, dtype=np.float64)[None, :]
    for r in range(0, height, step):
        rows = np.arange(row0 + r, row0 + min(r + step, height), dtype=np.float64)[:, None]
        rays = mapping.geometry.ray_directions(rows, cols)
        u, v, cos_alpha = mapping.directions_to_image(rays)
        inside = (np.isfinite(u) & (u >= -0.5) & (u < w - 0.5) & (v >= -0.5) & (v < h - 0.5)
                  & (rays[..., 2] >= cos_field_max))
        u, v = np.where(inside, u, -10.0), np.where(inside, v, -10.0)
        block = slice(r, r + rows.shape[0])
        sampled = cv2.remap(rgb_src, ((u + 0.5) * scale_u - 0.5).astype(np.float32),
                            ((v + 0.5) * scale_v - 0.5).astype(np.float32),
                            cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        sampled[~inside] = 0.0
        rgb[block] = sampled
        iu = np.clip(np.rint(u), 0, w - 1).astype(np.intp)
        iv = np.clip(np.rint(v), 0, h - 1).astype(np.intp)
        with np.errstate(divide="ignore", invalid="ignore"):  # cos α ≤ 0 only outside the image
            rng_block = (z_image[iv, iu] / cos_alpha).astype(np.float32)
        rng_block[~inside] = np.nan
        range_m[block] = rng_block
        valid[block] = inside
    return PlacedScene(rgb=rgb, range_m=range_m, valid=valid, roi=(row0, col0, height, width), mapping=mapping,
                       name=scene.name, clipped=clipped)


def _random_fitting_mapping(make, geometry: SensorGeometry, rng: np.random.Generator,
                            theta_range_deg: tuple[float, float], max_tries: int = 2000) -> PatchMapping:
    """Draw sensor positions uniformly over the pixels until the patch there fits (θ within range)."""
    lo, hi = theta_range_deg
    if not 0 <= lo <= hi <= geometry.max_field_deg:
        raise ValueError(f"theta_range_deg must satisfy 0 ≤ lo ≤ hi ≤ {geometry.max_field_deg}, got {theta_range_deg}")
    for _ in range(max_tries):
        row, col = rng.uniform(0, geometry.height_px - 1), rng.uniform(0, geometry.width_px - 1)
        theta, phi = geometry.field_angles(row, col)
        if not lo <= theta <= hi:
            continue
        mapping = make(float(theta), float(phi))
        if mapping.fits_sensor():
            return mapping
    raise ValueError(f"no position with θ in [{lo}, {hi}]° keeps the patch on the sensor "
                     f"(tried {max_tries} random positions)")


def place_patch(scene: Scene, geometry: SensorGeometry = BMI_SENSOR, *, theta0_deg: float | None = None,
                phi0_deg: float | None = None, fov_deg: float = 12.0, rng: np.random.Generator | None = None,
                theta_range_deg: tuple[float, float] | None = None, roll_deg: float = 0.0,
                projection: str = "pinhole", on_edge: str = "raise") -> PlacedScene:
    """Map ``scene`` to a local ``fov_deg`` patch (across its width) centred on the chief ray (θ0, φ0).

    Give ``theta0_deg`` and ``phi0_deg``, or neither and an ``rng``: then the
    centre is drawn uniformly over the sensor's pixels, restricted to
    ``theta_range_deg`` (default the whole field) and to positions where the
    whole patch stays on the sensor. ``on_edge``: "raise" (default) if an
    explicit placement runs off the sensor, or "clip" to keep what lands on it.
    """
    h, w = scene.shape

    def make(theta, phi):
        return PatchMapping(geometry, theta, phi, fov_deg, w, h, roll_deg, projection)

    if theta0_deg is None and phi0_deg is None:
        if rng is None:
            raise ValueError("random placement needs rng (a numpy.random.Generator), or give theta0_deg and phi0_deg")
        mapping = _random_fitting_mapping(make, geometry, rng, theta_range_deg or (0.0, geometry.max_field_deg))
    elif theta0_deg is None or phi0_deg is None:
        raise ValueError("give both theta0_deg and phi0_deg, or neither (random placement)")
    else:
        if theta_range_deg is not None:
            raise ValueError("theta_range_deg only applies to random placement")
        mapping = make(theta0_deg, phi0_deg)
    return resample_to_sensor(scene, mapping, on_edge)


def corner_phi_deg(geometry: SensorGeometry, corner: int = 0) -> float:
    """Azimuth of a sensor corner seen from the optical centre (0 bottom-right, 1 bottom-left, 2 top-left, 3 top-right)."""
    cy, cx = geometry.centre_px
    row = (geometry.height_px - 1) if corner in (0, 1) else 0
    col = (geometry.width_px - 1) if corner in (0, 3) else 0
    return math.degrees(math.atan2(row - cy, col - cx))


def place_wide(scene: Scene, geometry: SensorGeometry = BMI_SENSOR, *, fov_deg: float = 60.0,
               theta0_deg: float | None = None, phi0_deg: float | None = None,
               rng: np.random.Generator | None = None, projection: str = "pinhole",
               on_edge: str = "raise") -> PlacedScene:
    """Spread a large image over ``fov_deg`` (across its width) near the field edge (the Middlebury protocol).

    φ0 defaults to the bottom-right corner direction (a random corner with
    ``rng``): only the corners reach the ≈60° field edge. Without
    ``theta0_deg`` the patch centre is pushed along φ0 to the largest θ0 at
    which the whole image stays on the sensor (bisection to 0.01°).
    """
    h, w = scene.shape
    if phi0_deg is None:
        phi0_deg = corner_phi_deg(geometry, int(rng.integers(4)) if rng is not None else 0)

    def make(theta):
        return PatchMapping(geometry, theta, phi0_deg, fov_deg, w, h, 0.0, projection)

    if theta0_deg is None:
        if not make(0.0).fits_sensor():
            raise ValueError(f"a {w}×{h} image over {fov_deg}° does not fit on the sensor even at its centre; "
                             f"use a smaller fov_deg")
        lo, hi = 0.0, geometry.max_field_deg
        while hi - lo > 0.01:
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if make(mid).fits_sensor() else (lo, mid)
        theta0_deg = lo
    return resample_to_sensor(scene, make(theta0_deg), on_edge)
