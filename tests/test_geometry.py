"""Sensor geometry: the one pixel ↔ field ↔ ray mapping."""

import numpy as np
import pytest

from bmi_sdk.geometry import BMI_SENSOR, IDEAL_BMI_SENSOR, SENSOR_MAPPING_FILE, SensorGeometry
from bmi_sdk.optics import get_lens
from bmi_sdk.optics.report import sensor_mapping


def test_corners_reach_the_half_field_and_the_centre_is_the_axis():
    corners = (np.array([0, 4499]), np.array([0, 5999]))
    theta, _ = IDEAL_BMI_SENSOR.field_angles(*corners)
    assert theta == pytest.approx([59.68, 59.68], abs=0.01)  # 3750 px × 2 µm / 7.199 mm
    # the design lens lands its chief rays inside R·θ, so the same corners see 60.06°: just outside the circle
    assert BMI_SENSOR.field_angles(*corners)[0] == pytest.approx([60.06, 60.06], abs=0.01)
    cy, cx = BMI_SENSOR.centre_px
    assert BMI_SENSOR.field_angles(cy, cx)[0] == 0.0
    assert IDEAL_BMI_SENSOR.valid_mask().all()  # the ideal 60° circle covers the whole array
    assert 0 < (~BMI_SENSOR.valid_mask()).sum() < 200  # a few corner pixels beyond 60°


def test_default_sensor_carries_the_traced_chief_ray_table():
    """The shipped mapping is the design lens's trace (re-traced here) and differs from R·θ as measured."""
    doc = sensor_mapping(get_lens())
    import json

    shipped = json.loads(SENSOR_MAPPING_FILE.read_text())
    assert shipped["lens_sha256"] == doc["lens_sha256"], "lens changed: bmi lens --write-sensor-mapping"
    assert np.allclose(shipped["radial_mm"], doc["radial_mm"], rtol=0, atol=1e-9)
    assert BMI_SENSOR.field_table_deg == tuple(shipped["field_deg"])
    # chief ray of 30° lands 13.8 px inside the ideal R·θ position (0.73 %): the lens is not concentric
    ideal_px = np.radians(30.0) * 7.199e3 / 2.0
    landed_px = BMI_SENSOR.radial_mm_from_field_deg(30.0) * 1e3 / 2.0
    assert ideal_px - landed_px == pytest.approx(13.8, abs=0.1)
    assert BMI_SENSOR != IDEAL_BMI_SENSOR  # geometries with different tables are different sensors


def test_pixel_field_round_trip_and_azimuth_convention():
    rng = np.random.default_rng(0)
    theta, phi = rng.uniform(0, 59, 50), rng.uniform(-180, 180, 50)
    rows, cols = BMI_SENSOR.pixel_of_field(theta, phi)
    t2, p2 = BMI_SENSOR.field_angles(rows, cols)
    assert t2 == pytest.approx(theta, abs=1e-9) and np.cos(np.radians(p2 - phi)) == pytest.approx(1.0)
    r, c = BMI_SENSOR.pixel_of_field(30.0, 90.0)  # φ = 90°: straight down the image (rows grow)
    assert r > BMI_SENSOR.centre_px[0] and c == pytest.approx(BMI_SENSOR.centre_px[1])


def test_ray_directions_and_depth_conversions():
    d = BMI_SENSOR.ray_directions(np.array([0, 2250]), np.array([0, 3000]))
    assert np.linalg.norm(d, axis=-1) == pytest.approx([1.0, 1.0])
    corner_theta = BMI_SENSOR.field_angles(0, 0)[0]
    assert d[0, 0] < 0 and d[0, 1] < 0 and d[0, 2] == pytest.approx(np.cos(np.radians(corner_theta)), abs=1e-9)
    assert BMI_SENSOR.z_to_range(BMI_SENSOR.range_to_z(5.0, 60.0), 60.0) == pytest.approx(5.0)
    assert BMI_SENSOR.range_to_z(5.0, 60.0) == pytest.approx(2.5)


def test_lens_mapping_and_serialisation():
    real = SensorGeometry.for_lens(get_lens())
    assert real.field_deg_from_radial_mm(np.radians(59.62) * 7.199) == pytest.approx(60.0, abs=0.01)
    # The printed lens lands 60° at 59.62° on the sensor, so the array's corners (59.68°) lie just
    # outside its 60° image circle: no field, not valid.
    assert np.isnan(real.field_angles(0, 0)[0]) and not real.valid_mask(0, 0, 2, 2).any()
    again = SensorGeometry.from_dict(real.to_dict())
    assert again.field_angles(100, 100)[0] == pytest.approx(real.field_angles(100, 100)[0])
    plane = SensorGeometry.for_lens(get_lens("fisheye"))
    assert plane.radius_mm is None
    assert plane.field_angles(*plane.pixel_of_field(45.0, 10.0))[0] == pytest.approx(45.0, abs=1e-6)
    with pytest.raises(ValueError, match="radius_mm must be > 0"):
        SensorGeometry(radius_mm=0.0)


def test_repr_summarises_the_chief_ray_table():
    """The table's ~640 floats made ``help(FirmwareDevice)`` (a geometry default) unreadable."""
    import pydoc
    import re

    from firmware_sim import FirmwareDevice

    text = repr(BMI_SENSOR)
    assert len(text) < 250 and "radius_mm=7.199" in text
    assert f"<{len(BMI_SENSOR.field_table_deg)} points, 0–" in text
    assert repr(SensorGeometry()) == ("SensorGeometry(width_px=6000, height_px=4500, pitch_um=2.0, radius_mm=7.199, "
                                      "cx_px=None, cy_px=None, max_field_deg=60.0)")
    doc = pydoc.render_doc(FirmwareDevice, renderer=pydoc.plaintext)
    assert len(re.findall(r"\d\.\d", doc)) < 50


def test_a_built_camera_s_rays_land_where_its_traced_chief_rays_do():
    """BuiltCamera.ray_geometry (traced on a coarse grid, symmetric part + displacement table) against chief rays
    traced independently (full pupil fit) at fields and azimuths off its grid, both ways; the nominal geometry
    misses them by pixels. Glare and scale move no ray."""
    import math

    from bmi_sdk.built_camera import BuiltCamera
    from bmi_sdk.optics import get_lens
    from bmi_sdk.optics.perturb import Perturbation, trace_spots

    p = Perturbation(decenter_um=(10.0, -4.0), tilt_arcmin=(0.5, 0.0), psf_shift_px=(0.3, -0.2),
                     sensor_radius_error_pct=0.5, stray_light_fraction=0.02)
    camera = BuiltCamera(perturbation=p)
    rays, sensor = camera.ray_geometry(), camera.sensor()
    theta = np.array([7.3, 21.9, 33.1, 52.7, 57.4])
    phi = np.array([131.0, 203.0, 277.0, 30.0, 145.0])  # all on the 6000 × 4500 sensor
    _, land, _ = trace_spots(get_lens(), p, theta, phi, math.inf, 0.5876, sensor.centre_px, sensor.pitch_um)
    land = land + np.array([p.psf_shift_px[1], p.psf_shift_px[0]])
    row, col = rays.pixel_of_field(theta, phi)
    assert np.hypot(row - land[:, 0], col - land[:, 1]).max() < 0.03
    nominal_row, nominal_col = sensor.pixel_of_field(theta, phi)
    assert np.hypot(nominal_row - land[:, 0], nominal_col - land[:, 1]).mean() > 3.0
    back_theta, back_phi = rays.field_angles(land[:, 0], land[:, 1])
    np.testing.assert_allclose(back_theta, theta, atol=1e-3)
    np.testing.assert_allclose((back_phi - phi + 180.0) % 360.0 - 180.0, 0.0, atol=5e-3)
    assert SensorGeometry.from_dict(rays.to_dict()) == rays
    assert BuiltCamera(perturbation=Perturbation(stray_light_fraction=0.03, psf_scale_pct=2.0)).ray_geometry() is \
        BuiltCamera().sensor()


def test_valid_mask_by_distance_equals_the_field_test_at_every_pixel():
    """valid_mask decides by the squared distance from the centre and evaluates θ only at the rim; the brute-force
    reference evaluates θ ≤ max_field_deg at every pixel. They agree on whole sensors (traced table, R·θ, the
    fisheye's plane, an off-centre axis, a displaced built camera) and on a rim drawn exactly through a pixel, where
    only θ itself can decide; a field table that does not rise falls back to the reference."""
    from dataclasses import replace

    from bmi_sdk.built_camera import BuiltCamera
    from bmi_sdk.optics.perturb import Perturbation

    small = dict(width_px=1200, height_px=900)
    geometries = [replace(BMI_SENSOR, **small, max_field_deg=11.0), replace(IDEAL_BMI_SENSOR, **small, max_field_deg=10.0),
                  replace(SensorGeometry.for_lens(get_lens("fisheye")), **small, max_field_deg=10.0),
                  replace(BMI_SENSOR, **small, cx_px=601.3, cy_px=440.0, max_field_deg=10.0),
                  BuiltCamera(perturbation=Perturbation(decenter_um=(10.0, -4.0))).ray_geometry()]
    for g in geometries:
        np.testing.assert_array_equal(g.valid_mask(), g.valid_mask_by_field())
        assert 0 < g.valid_mask().sum() < g.width_px * g.height_px
    # a rim through pixel (450, 999): dy 0.5, dx 399.5 px from the centre (449.5, 599.5)
    rim_deg = float(np.degrees(np.hypot(0.5, 399.5) * 2e-3 / 7.199))
    for nudge in (-1e-13, 0.0, 1e-13):
        g = replace(IDEAL_BMI_SENSOR, **small, max_field_deg=rim_deg + nudge)
        assert abs(g.image_circle_radius_px - np.hypot(0.5, 399.5)) < 1e-9  # the pixel lies in the evaluated band
        np.testing.assert_array_equal(g.valid_mask(440, 980, 20, 40), g.valid_mask_by_field(440, 980, 20, 40))
    falling = replace(BMI_SENSOR, **small, field_table_deg=(0.0, 20.0, 15.0), radial_table_mm=(0.0, 1.0, 2.0),
                      max_field_deg=17.0)
    assert falling.image_circle_radius_px is None
    np.testing.assert_array_equal(falling.valid_mask(), falling.valid_mask_by_field())
