"""Placement of pinhole dataset images on the curved sensor (paper §4.1), checked with the sensor geometry."""

import math

import numpy as np
import pytest

from bmi_sdk.geometry import BMI_SENSOR, SensorGeometry
from bmi_sdk.scenes import NYU_RGB_INTRINSICS, PinholeIntrinsics, Scene, generate_scene
from bmi_sdk.scenes.placement import PatchMapping, corner_phi_deg, place_patch, place_wide, tan_vs_angle_relative_error

SMALL = SensorGeometry(width_px=1001, height_px=801)  # odd sizes: a pixel sits exactly on the optical centre


def flat_scene(z_m=3.0, intrinsics=NYU_RGB_INTRINSICS, rgb=None):
    """A fronto-parallel wall at planar depth z_m seen by a pinhole camera."""
    h, w = intrinsics.height_px, intrinsics.width_px
    rgb = np.full((h, w, 3), 0.5, dtype=np.float32) if rgb is None else rgb
    return Scene(rgb, intrinsics.z_to_range(np.full((h, w), z_m, dtype=np.float32)), "wall", intrinsics)


def centre_ray(geometry, theta_deg, phi_deg):
    row, col = geometry.pixel_of_field(theta_deg, phi_deg)
    return geometry.ray_directions(np.array([row]), np.array([col]))[0]


def placed_rays(placed, geometry):
    row0, col0, h, w = placed.roi
    rows, cols = np.nonzero(placed.valid)
    return rows, cols, geometry.ray_directions(rows + row0, cols + col0)


def test_small_angle_discrepancy_of_the_paper():
    # paper §4.1: "at the half angle of 6°, tan α and α differ by ≈0.37 %"
    assert tan_vs_angle_relative_error(6.0) == pytest.approx(0.0036715, abs=1e-6)
    assert tan_vs_angle_relative_error(30.0) == pytest.approx(0.10266, abs=1e-5)


@pytest.mark.parametrize("theta0, phi0, projection", [(0.0, 0.0, "pinhole"), (23.0, -70.0, "pinhole"),
                                                      (48.0, 140.0, "pinhole"), (35.0, 10.0, "equiangular")])
def test_pixel_ray_image_round_trip(theta0, phi0, projection):
    m = PatchMapping(BMI_SENSOR, theta0, phi0, 12.0, 640, 480, roll_deg=7.0, projection=projection)
    row, col = BMI_SENSOR.pixel_of_field(theta0, phi0)
    u, v, cos_a = m.sensor_to_image(np.array([row]), np.array([col]))
    assert (u[0], v[0]) == pytest.approx(((640 - 1) / 2, (480 - 1) / 2), abs=1e-9)
    assert cos_a[0] == pytest.approx(1.0, abs=1e-12)
    uu, vv = np.meshgrid(np.linspace(-0.5, 639.5, 9), np.linspace(-0.5, 479.5, 7))
    rows, cols = m.image_to_sensor(uu, vv)
    u2, v2, _ = m.sensor_to_image(rows, cols)
    np.testing.assert_allclose(u2, uu, atol=1e-7)
    np.testing.assert_allclose(v2, vv, atol=1e-7)


@pytest.mark.parametrize("projection", ["pinhole", "equiangular"])
def test_patch_on_axis_spans_12_degrees(projection):
    placed = place_patch(flat_scene(), SMALL, theta0_deg=0.0, phi0_deg=0.0, projection=projection)
    row0, col0, _, _ = placed.roi
    pixel_deg = math.degrees(SMALL.pitch_um * 1e-3 / SMALL.radius_mm)
    # along the centre row the field angle of the outermost valid pixels, left + right
    centre_row = 400 - row0
    cols = np.nonzero(placed.valid[centre_row])[0] + col0
    theta, _ = SMALL.field_angles(np.full(2, 400.0), cols[[0, -1]].astype(float))
    assert theta.sum() == pytest.approx(12.0, abs=2 * pixel_deg)
    # vertically the 480 rows span 2·atan(tan 6° · 480/640) (pinhole) or 12°·480/640 (equiangular)
    rows = np.nonzero(placed.valid[:, 500 - col0])[0] + row0
    theta, _ = SMALL.field_angles(rows[[0, -1]].astype(float), np.full(2, 500.0))
    expected = (2 * math.degrees(math.atan(math.tan(math.radians(6)) * 480 / 640))
                if projection == "pinhole" else 12.0 * 480 / 640)
    assert theta.sum() == pytest.approx(expected, abs=2 * pixel_deg)
    # nothing of the image was cut: the valid region does not touch the ROI border
    v = placed.valid
    assert not (v[0].any() or v[-1].any() or v[:, 0].any() or v[:, -1].any())


@pytest.mark.parametrize("theta0, phi0", [(30.0, 20.0), (49.0, -143.0)])
def test_patch_off_axis_spans_12_degrees(theta0, phi0):
    placed = place_patch(flat_scene(), BMI_SENSOR, theta0_deg=theta0, phi0_deg=phi0)
    _, _, rays = placed_rays(placed, BMI_SENSOR)
    alpha = np.degrees(np.arccos(np.clip(rays @ centre_ray(BMI_SENSOR, theta0, phi0), -1, 1)))
    t = math.tan(math.radians(6.0))
    half_diagonal = math.degrees(math.atan(math.hypot(t, t * 480 / 640)))
    assert alpha.max() == pytest.approx(half_diagonal, abs=0.03)


def test_equiangular_vs_pinhole_edge_matches_the_small_angle_number():
    """With equal scale at the centre, the pinhole edge (6°) and the tan-less edge differ by tan α/α − 1."""
    pin = PatchMapping(SMALL, 0.0, 0.0, 12.0, 640, 480, projection="pinhole")
    half_eq = math.degrees(math.tan(math.radians(6.0)))  # same focal_px: (W/2)/tan(6°) = (W/2)/half_eq[rad]
    equi = PatchMapping(SMALL, 0.0, 0.0, 2 * half_eq, 640, 480, projection="equiangular")
    assert equi.focal_px == pytest.approx(pin.focal_px)
    cy, cx = SMALL.centre_px
    edge = (np.array([639.5]), np.array([239.5]))
    r_pin = pin.image_to_sensor(*edge)[1][0] - cx
    r_equi = equi.image_to_sensor(*edge)[1][0] - cx
    assert r_equi / r_pin - 1 == pytest.approx(tan_vs_angle_relative_error(6.0), rel=1e-6)
    assert r_equi / r_pin - 1 == pytest.approx(0.0037, abs=5e-5)


@pytest.mark.parametrize("theta0, phi0", [(0.0, 0.0), (35.0, 120.0), (49.5, -37.0)])
def test_flat_wall_range_is_z_over_cos_alpha_and_planar(theta0, phi0):
    placed = place_patch(flat_scene(3.0), BMI_SENSOR, theta0_deg=theta0, phi0_deg=phi0)
    rows, cols, rays = placed_rays(placed, BMI_SENSOR)
    axis = centre_ray(BMI_SENSOR, theta0, phi0)
    cos_alpha = rays @ axis
    np.testing.assert_allclose(placed.range_m[rows, cols], 3.0 / cos_alpha, rtol=2e-6)
    points = placed.range_m[rows, cols, None].astype(np.float64) * rays
    np.testing.assert_allclose(points @ axis, 3.0, rtol=2e-6)  # one plane, facing the patch axis
    assert np.isnan(placed.range_m[~placed.valid]).all()
    assert np.all(placed.rgb[~placed.valid] == 0) and np.allclose(placed.rgb[placed.valid], 0.5)


@pytest.mark.parametrize("width, height", [(640, 480), (960, 540)])  # 960 px over 12°: the sensor undersamples
def test_rgb_ramp_lands_where_an_independent_pinhole_projection_says(width, height):
    k = PinholeIntrinsics(500.0, 500.0, (width - 1) / 2, (height - 1) / 2, width, height)
    u, v = np.meshgrid(np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32))
    rgb = np.stack([u / width, v / height, np.full_like(u, 0.25)], axis=-1)
    placed = place_patch(flat_scene(2.0, k, rgb), SMALL, theta0_deg=0.0, phi0_deg=0.0)
    rows, cols, rays = placed_rays(placed, SMALL)
    f = (width / 2) / math.tan(math.radians(6.0))
    u_ref = (width - 1) / 2 + f * rays[:, 0] / rays[:, 2]
    v_ref = (height - 1) / 2 + f * rays[:, 1] / rays[:, 2]
    interior = (u_ref > 2) & (u_ref < width - 3) & (v_ref > 2) & (v_ref < height - 3)
    np.testing.assert_allclose(placed.rgb[rows, cols, 0][interior], (u_ref / width)[interior], atol=2e-3)
    np.testing.assert_allclose(placed.rgb[rows, cols, 1][interior], (v_ref / height)[interior], atol=2e-3)


def test_depth_step_is_not_interpolated():
    k = NYU_RGB_INTRINSICS
    z = np.full((480, 640), 2.0, dtype=np.float32)
    z[:, 320:] = 5.0
    scene = Scene(np.zeros((480, 640, 3), np.float32), k.z_to_range(z), "step", k)
    placed = place_patch(scene, BMI_SENSOR, theta0_deg=20.0, phi0_deg=45.0)
    rows, cols, rays = placed_rays(placed, BMI_SENSOR)
    z_placed = placed.range_m[rows, cols] * (rays @ centre_ray(BMI_SENSOR, 20.0, 45.0))
    assert np.all(np.isclose(z_placed, 2.0, rtol=1e-5) | np.isclose(z_placed, 5.0, rtol=1e-5))
    assert 0.4 < np.mean(np.isclose(z_placed, 2.0, rtol=1e-5)) < 0.6


def test_field_edge_placement_is_refused_or_clipped_explicitly():
    phi = corner_phi_deg(BMI_SENSOR)  # the corner is at 59.7°: a 12° patch at 55° runs off it
    with pytest.raises(ValueError, match="outside the 4500×6000 sensor"):
        place_patch(flat_scene(), BMI_SENSOR, theta0_deg=55.0, phi0_deg=phi)
    placed = place_patch(flat_scene(), BMI_SENSOR, theta0_deg=55.0, phi0_deg=phi, on_edge="clip")
    row0, col0, h, w = placed.roi
    assert placed.clipped and row0 + h == 4500 and col0 + w == 6000
    assert placed.valid.any() and placed.valid[-1].any()  # the image reaches the sensor's edge row
    with pytest.raises(ValueError, match="theta0_deg must be in"):
        place_patch(flat_scene(), BMI_SENSOR, theta0_deg=61.0, phi0_deg=phi)


def test_random_placement_respects_theta_range_and_stays_on_sensor():
    rng = np.random.default_rng(4)
    thetas = []
    for _ in range(5):
        placed = place_patch(flat_scene(), BMI_SENSOR, rng=rng, theta_range_deg=(45.0, 60.0))
        row0, col0, h, w = placed.roi
        assert not placed.clipped and row0 >= 0 and col0 >= 0 and row0 + h <= 4500 and col0 + w <= 6000
        assert 45.0 <= placed.mapping.theta0_deg <= 60.0
        v = placed.valid
        assert not (v[0].any() or v[-1].any() or v[:, 0].any() or v[:, -1].any())
        thetas.append(placed.mapping.theta0_deg)
    assert len(set(thetas)) == 5
    a = place_patch(flat_scene(), BMI_SENSOR, rng=np.random.default_rng(9))
    b = place_patch(flat_scene(), BMI_SENSOR, rng=np.random.default_rng(9))
    assert a.roi == b.roi
    with pytest.raises(ValueError, match="no position"):
        place_patch(flat_scene(), BMI_SENSOR, rng=rng, theta_range_deg=(59.5, 60.0))


# the BMI sensor sampled 4× coarser: same radius, field and corners (59.7°), 16× fewer pixels to test on
COARSE = SensorGeometry(width_px=1500, height_px=1125, pitch_um=8.0)


@pytest.mark.parametrize("corner", [0, 2])
def test_wide_protocol_reaches_the_field_edge(corner):
    k = PinholeIntrinsics(1000.0, 1000.0, 370.0, 248.0, 741, 497)  # Middlebury aspect (2964×1988 / 4)
    placed = place_wide(flat_scene(4.0, k), COARSE, phi0_deg=corner_phi_deg(COARSE, corner))
    row0, col0, h, w = placed.roi
    assert not placed.clipped and row0 >= 0 and col0 >= 0 and row0 + h <= 1125 and col0 + w <= 1500
    # pushed against the sensor edge in the corner's direction
    assert min(row0, col0) <= 2 if corner == 2 else (row0 + h >= 1125 - 2 or col0 + w >= 1500 - 2)
    _, _, rays = placed_rays(placed, COARSE)
    theta = np.degrees(np.arccos(rays[:, 2]))
    assert theta.max() > 55.0  # near the ≈60° field edge (the corner is at 59.7°)
    axis = centre_ray(COARSE, placed.mapping.theta0_deg, placed.mapping.phi0_deg)
    alpha = np.degrees(np.arccos(np.clip(rays @ axis, -1, 1)))
    t = math.tan(math.radians(30.0))
    assert alpha.max() == pytest.approx(math.degrees(math.atan(math.hypot(t, t * 497 / 741))), abs=0.03)


def test_placement_errors_are_named():
    with pytest.raises(ValueError, match="no pinhole intrinsics"):
        place_patch(generate_scene(64, 64, 0), BMI_SENSOR, theta0_deg=0.0, phi0_deg=0.0)
    with pytest.raises(ValueError, match="needs rng"):
        place_patch(flat_scene(), BMI_SENSOR)
    with pytest.raises(ValueError, match="both theta0_deg and phi0_deg"):
        place_patch(flat_scene(), BMI_SENSOR, theta0_deg=3.0)
    with pytest.raises(ValueError, match="only applies to random"):
        place_patch(flat_scene(), BMI_SENSOR, theta0_deg=3.0, phi0_deg=0.0, theta_range_deg=(0, 10))
    with pytest.raises(ValueError, match="on_edge"):
        place_patch(flat_scene(), BMI_SENSOR, theta0_deg=3.0, phi0_deg=0.0, on_edge="wrap")
    with pytest.raises(ValueError, match="projection"):
        PatchMapping(BMI_SENSOR, 0.0, 0.0, 12.0, 640, 480, projection="fisheye")
