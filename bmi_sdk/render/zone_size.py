"""How large a camera's render zones may be: as faithful to its kernels' change with θ as the design's zones are.

The renderer draws each zone with the kernels of its centre (blended at its borders, ``compose``). Its default,
``DEFAULT_ZONE_PX`` = 512 px, is about 8° of field at the edge. That suits the design, whose kernels change slowly
with θ (``bmi bench render``). A built camera's may not: a sensor sphere of the wrong radius, vertex held,
defocuses the field by an amount that grows with θ. On 512-px zones a +0.5 % camera's planes at 55° are drawn
with kernels of fields up to 4° away and read AbsRel 0.28–0.46 where 64-px zones read 0.03–0.05 (docs/rendering.md).

The measure: the largest L1 difference, over the colour channels and ``PROBE_DEPTHS_M``, between a camera's
kernels at the two radial ends of a zone centred at ``PROBE_FIELD_DEG`` (the benchmark's edge, where the change
is largest). A camera's zone is the largest of ``ZONE_CHOICES_PX`` whose change stays within ``TOLERANCE`` of
the design's across its 512-px zone. The design therefore keeps 512 px, and a camera is drawn no worse than the
design is.
"""

from __future__ import annotations

import numpy as np

PROBE_FIELD_DEG = 55.0
PROBE_AZIMUTH_DEG = 30.0
PROBE_DEPTHS_M = (1.0, 3.0, 6.0, 10.0)
ZONE_CHOICES_PX = (512, 256, 128, 64, 32)
TOLERANCE = 1.1


def zone_field_ends_deg(geometry, zone_px: int) -> tuple[float, float]:
    """θ (degrees) at the two radial ends of a ``zone_px`` zone centred at the probe field."""
    row, col = geometry.pixel_of_field(PROBE_FIELD_DEG, PROBE_AZIMUTH_DEG)
    centre_row, centre_col = geometry.centre_px
    radial = np.array([row - centre_row, col - centre_col], np.float64)
    radial /= np.linalg.norm(radial)
    ends = [np.array([row, col]) + s * 0.5 * zone_px * radial for s in (-1.0, 1.0)]
    return tuple(float(np.asarray(geometry.field_angles(r, c)[0])) for r, c in ends)


def kernel_change(psf_map, zone_px: int) -> float:
    """The largest L1 difference between ``psf_map``'s kernels at the two radial ends of a ``zone_px`` zone at the
    probe field (module doc): every channel, the tensor depths nearest ``PROBE_DEPTHS_M``."""
    depth_m = np.asarray(psf_map.tensor.depth_m)
    depths = np.array([int(np.argmin(np.abs(depth_m - d))) for d in PROBE_DEPTHS_M])
    inner, outer = (psf_map.kernels(theta, PROBE_AZIMUTH_DEG, depths)
                    for theta in zone_field_ends_deg(psf_map.geometry, zone_px))
    return float(np.abs(np.asarray(inner, np.float64) - outer).sum(axis=(-2, -1)).max())


def zone_px_for(psf_map, design_change: float) -> int:
    """The largest of ``ZONE_CHOICES_PX`` over which ``psf_map``'s kernels change no more than ``TOLERANCE`` × the
    design's change over ``DEFAULT_ZONE_PX`` (``design_change``, its ``kernel_change``); the smallest choice if none
    does."""
    limit = TOLERANCE * design_change
    for zone_px in ZONE_CHOICES_PX:
        if kernel_change(psf_map, zone_px) <= limit:
            return zone_px
    return ZONE_CHOICES_PX[-1]
