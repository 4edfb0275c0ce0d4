"""Exact real-ray tracing through rotationally symmetric sequential systems.

Vectorised over rays (numpy, float64). Surfaces are spheres or planes written
in vertex-local form F = c(x² + y² + z²) − 2z = 0; the intersection uses the
numerically stable root t = g / (b + √(b² − c g)), which selects the sheet
through the vertex and reduces to the plane case when c → 0. The unit normal
(−cx, −cy, 1 − cz) is exact on the surface. Refraction is the vector form of
Snell's law; a negative discriminant is total internal reflection.

Clear apertures are *recorded*, not enforced: every ray carries its height
relative to each surface's semi-diameter, so callers decide what vignettes
(the PSF code fits these heights smoothly across the pupil to draw a sharp,
anti-aliased aperture). Rays that miss a sphere or are totally reflected are
dead (``alive`` False) with the surface index in ``fail_surface``.

The image surface may be displaced and turned rigidly (``ImagePose``): a
decentred or tilted lens assembly seen from the lens, and what the calibration
fits. The ray is mapped into the nominal image surface's frame, intersected
there, and the hit point mapped back (a rigid motion keeps path lengths). With
no pose, the arithmetic is the nominal one, bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .paraxial import indices
from .prescription import Lens


class RayTraceError(ValueError):
    """A ray the caller needs (chief ray, marginal ray) cannot pass the lens."""


@dataclass
class RayBundle:
    """Rays after tracing. Arrays have a leading ray axis (any batch shape)."""

    position: np.ndarray  # (..., 3) on the last surface reached (image surface if traced to it)
    direction: np.ndarray  # (..., 3) unit, in the last medium
    opl_mm: np.ndarray  # (...) optical path from the launch reference
    alive: np.ndarray  # (...) bool
    fail_surface: np.ndarray  # (...) int, -1 when alive
    rel_height: np.ndarray  # (n_surfaces, ...) radial height / semi-diameter at each lens surface
    stop_xy_mm: np.ndarray  # (..., 2) intersection with the stop surface


@dataclass(frozen=True)
class ImagePose:
    """Rigid placement of the image surface relative to its nominal one, in the lens frame.

    A point y of the nominal surface moves to ``pivot + offset_mm + rotation (y − pivot)``,
    ``pivot = (0, 0, pivot_z_mm)`` (the lens centre for a lens tilted about its centre).
    ``offset_mm`` (..., 3) and ``rotation`` (..., 3, 3) broadcast against the ray batch.
    """

    offset_mm: np.ndarray
    rotation: np.ndarray
    pivot_z_mm: float

    def to_nominal(self, point, direction=None):
        """Map lens-frame points (and directions) into the nominal image surface's frame."""
        pivot = np.array([0.0, 0.0, self.pivot_z_mm])
        rel = np.asarray(point, dtype=np.float64) - pivot - self.offset_mm
        y = np.einsum("...ji,...j->...i", self.rotation, rel) + pivot
        if direction is None:
            return y
        return y, np.einsum("...ji,...j->...i", self.rotation, np.asarray(direction, dtype=np.float64))

    def from_nominal(self, point):
        pivot = np.array([0.0, 0.0, self.pivot_z_mm])
        return np.einsum("...ij,...j->...i", self.rotation, np.asarray(point) - pivot) + pivot + self.offset_mm


def _intersect(p, d, c):
    """Distance t along d from local point p to the vertex sheet of F = c|r|² − 2z."""
    b = d[..., 2] - c * np.einsum("...i,...i->...", p, d)
    g = c * np.einsum("...i,...i->...", p, p) - 2.0 * p[..., 2]
    disc = b * b - c * g
    ok = disc >= 0.0
    denom = b + np.sqrt(np.where(ok, disc, 0.0))
    ok &= denom > 0.0
    t = np.where(ok, g / np.where(ok, denom, 1.0), np.nan)
    return t, ok


def _refract(d, normal, mu):
    cos_i = np.einsum("...i,...i->...", d, normal)
    k = 1.0 - mu * mu * (1.0 - cos_i * cos_i)
    ok = k >= 0.0
    root = np.sqrt(np.where(ok, k, 0.0))
    d_out = mu[..., None] * d + (root - mu * cos_i)[..., None] * normal if np.ndim(mu) else \
        mu * d + (root - mu * cos_i)[..., None] * normal
    return d_out, ok


def trace(lens: Lens, wavelength_um, origin, direction, opl0_mm=None, to_image: bool = True,
          stop_only: bool = False, image_pose: ImagePose | None = None) -> RayBundle:
    """Trace rays from ``origin`` along unit ``direction`` (object space, index of air).

    ``image_pose`` places the image surface rigidly (see :class:`ImagePose`);
    None is the nominal surface.

    ``wavelength_um`` is a scalar or an array broadcastable to the ray batch
    shape (one wavelength per ray group). The launch points must lie before
    the first surface. With ``stop_only`` the trace ends at the stop.
    """
    origin = np.asarray(origin, dtype=np.float64)
    direction = np.asarray(direction, dtype=np.float64)
    shape = origin.shape[:-1]
    lam = np.broadcast_to(np.asarray(wavelength_um, dtype=np.float64), shape)
    lam_values = np.unique(lam)
    n_media = np.stack([indices(lens, float(v)) for v in lam_values])  # (n_lambda, n_media)
    lam_index = np.searchsorted(lam_values, lam)
    n_of = n_media[lam_index]  # (..., n_media)

    z_vertex = lens.vertex_z_mm
    p = origin.copy()
    d = direction / np.linalg.norm(direction, axis=-1, keepdims=True)
    opl = np.zeros(shape) if opl0_mm is None else np.broadcast_to(np.asarray(opl0_mm, dtype=np.float64), shape).copy()
    alive = np.ones(shape, dtype=bool)
    fail = np.full(shape, -1, dtype=np.int64)
    n_surf = len(lens.surfaces)
    rel_height = np.zeros((n_surf,) + shape)
    stop_xy = np.zeros(shape + (2,))
    last = lens.stop_index + 1 if stop_only else n_surf
    for j in range(last):
        s = lens.surfaces[j]
        local = p - np.array([0.0, 0.0, z_vertex[j]])
        t, ok = _intersect(local, d, s.curvature_per_mm)
        newly_dead = alive & ~ok
        fail[newly_dead] = j
        alive &= ok
        t = np.where(alive, t, 0.0)
        local = local + t[..., None] * d
        opl += n_of[..., j] * t
        c = s.curvature_per_mm
        normal = np.stack([-c * local[..., 0], -c * local[..., 1], 1.0 - c * local[..., 2]], axis=-1)
        mu = n_of[..., j] / n_of[..., j + 1]
        d, ok = _refract(d, normal, mu)
        newly_dead = alive & ~ok
        fail[newly_dead] = j
        alive &= ok
        rel_height[j] = np.hypot(local[..., 0], local[..., 1]) / s.semi_diameter_mm
        if j == lens.stop_index:
            stop_xy = local[..., :2].copy()
        p = local + np.array([0.0, 0.0, z_vertex[j]])
    if to_image and not stop_only:
        c_img = lens.image.curvature_per_mm
        p_img, d_img = (p, d) if image_pose is None else image_pose.to_nominal(p, d)
        local = p_img - np.array([0.0, 0.0, z_vertex[-1]])
        t, ok = _intersect(local, d_img, c_img)
        fail[alive & ~ok] = n_surf
        alive &= ok
        t = np.where(alive, t, 0.0)
        opl += n_of[..., -1] * t
        p = local + t[..., None] * d_img + np.array([0.0, 0.0, z_vertex[-1]])
        if image_pose is not None:
            p = image_pose.from_nominal(p)
    return RayBundle(position=p, direction=d, opl_mm=opl, alive=alive, fail_surface=fail,
                     rel_height=rel_height, stop_xy_mm=stop_xy)


def image_normal(lens: Lens, point, image_pose: ImagePose | None = None):
    """Normal of the image surface at ``point`` (pointing along +z, the light's way; unit on the surface)."""
    c = lens.image.curvature_per_mm
    y = np.asarray(point, dtype=np.float64) if image_pose is None else image_pose.to_nominal(point)
    local = y - np.array([0.0, 0.0, lens.vertex_z_mm[-1]])
    n = np.stack([-c * local[..., 0], -c * local[..., 1], 1.0 - c * local[..., 2]], axis=-1)
    return n if image_pose is None else np.einsum("...ij,...j->...i", image_pose.rotation, n)
