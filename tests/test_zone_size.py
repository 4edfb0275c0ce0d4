"""Render zones per camera (``render.zone_size``): a built camera is drawn no worse than the design is."""

import numpy as np

from bmi_sdk.built_camera import BuiltCamera
from bmi_sdk.optics.perturb import Perturbation
from bmi_sdk.render import DEFAULT_ZONE_PX, render_coded
from bmi_sdk.render.zone_size import ZONE_CHOICES_PX, kernel_change, zone_field_ends_deg

RADIUS = BuiltCamera(perturbation=Perturbation(sensor_radius_error_pct=0.5))


def test_a_zone_spans_the_field_its_pixels_see():
    """A 512-px zone at 55° spans about 8° of field (2 µm pixels on a sphere of ~7.2 mm), centred on 55°, and
    halving the zone halves the span."""
    geometry = BuiltCamera().sensor()
    lo, hi = zone_field_ends_deg(geometry, 512)
    lo2, hi2 = zone_field_ends_deg(geometry, 256)
    assert 7.0 < hi - lo < 9.5 and abs(0.5 * (lo + hi) - 55.0) < 0.3
    assert abs((hi2 - lo2) / (hi - lo) - 0.5) < 0.02


def test_the_design_keeps_its_zones_and_a_radius_error_gets_finer_ones():
    assert BuiltCamera().render_zone_px("tensor") == DEFAULT_ZONE_PX
    assert BuiltCamera(perturbation=Perturbation(stray_light_fraction=0.03)).render_zone_px("tensor") == DEFAULT_ZONE_PX
    zone = RADIUS.render_zone_px("tensor")
    assert zone <= 64
    changes = [kernel_change(RADIUS.psf_map("tensor"), z) for z in ZONE_CHOICES_PX]
    assert all(a > b for a, b in zip(changes, changes[1:]))  # the change grows with the zone's field span
    design = kernel_change(BuiltCamera().psf_map("tensor"), DEFAULT_ZONE_PX)
    assert changes[0] > 3 * design  # on 512-px zones the +0.5 % camera would be drawn far worse than the design


def test_the_chosen_zones_draw_a_radius_error_like_fine_zones_do():
    """A +0.5 % camera's 1/f²-textured plane at 5 m, 55°: drawn on its chosen zones it agrees with a drawing on
    32-px zones (each pixel within 0.13° of its kernels' field) to a small part of what 512-px zones miss."""
    from bmi_sdk.bench.decoder import plane_texture

    psf_map = RADIUS.psf_map("tensor")
    geometry = psf_map.geometry
    size = 160
    row, col = geometry.pixel_of_field(55.0, 30.0)
    row0, col0 = int(row - size / 2) // 2 * 2, int(col - size / 2) // 2 * 2
    rgb = plane_texture(size, "pink", np.random.default_rng(3))
    depth = np.full((size, size), 5.0, np.float32)

    def draw(zone_px):
        return render_coded(rgb, depth, psf_map.tensor, geometry, row0, col0, psf_map=psf_map, zone_px=zone_px)[20:-20, 20:-20]

    fine = draw(32)
    chosen = np.abs(draw(RADIUS.render_zone_px("tensor")) - fine).mean()
    coarse = np.abs(draw(DEFAULT_ZONE_PX) - fine).mean()
    assert chosen < 0.3 * coarse
