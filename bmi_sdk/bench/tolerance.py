"""`bmi bench tolerance`: how much of the field edge's depth information a built camera's errors take away,
over the benchmark's depths, whatever decodes it.

The decoding issue's perturbed camera (decenter 10 µm, PSF shift 0.5 px, stray light 3 %, sensor radius
+0.5 %) is to read the benchmark's edge within 10 % of the nominal camera's AbsRel once calibrated. This
target asks how much information the errors leave, which no decoder can exceed. Per camera, at θ
``TOLERANCE_FIELD_DEG`` (the middle of the benchmark's edge band), φ 30°:

* the AbsRel of an estimator at the Cramér–Rao bound of one tapered window (√(2/π) σ_d / d,
  ``decoder.window_depth_bound``) on a 1/f² plane at each range of ``TOLERANCE_DEPTHS_M``;
* the classical decoder's AbsRel on the same planes (each window's evidence pooled, so a large plane can read
  below one window's bound);

both rendered (on ``RENDER_ZONE_PX`` render zones) and decoded with the camera's own exact kernels (its optical
centre calibrated, as ``bmi eval`` renders its hardware rows), then averaged over the true ranges of the benchmark's
edge tiles (``benchmark_edge_ranges_m``), interpolated linearly in 1/d between the planes (``depth_weighted``). The
cameras: the nominal one, sensor-radius errors alone (``SENSOR_RADIUS_ERRORS_PCT``), the issue's camera, and it
without its radius error.

The physics being measured: the sensor sphere's vertex is held, so a radius error defocuses the field by an
amount growing with θ. At the edge a larger radius moves the focus from beyond 10 m into the working range
(+0.5 %: to ~3.4 m), where the blur's first-order change with depth vanishes and the blur grows both ways from
focus; a smaller one pushes the focus further out, where the far blur changes faster with depth.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from . import markdown_table, register_target
from .decoder import MEAN_ABS_PER_SIGMA, classical_depth, decoded_absrel, plane_raw, window_depth_bound

TOLERANCE_FIELD_DEG = 55.0
TOLERANCE_DEPTHS_M = (0.8, 1.0, 1.25, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 5.0, 6.0, 7.0, 8.0, 9.5)
SENSOR_RADIUS_ERRORS_PCT = (-0.5, -0.25, 0.05, 0.1, 0.2, 0.3, 0.5)
RENDER_ZONE_PX = 64
"""The planes' render zones (±0.25° of field around each zone's kernels): a sensor-radius error changes the edge's
kernels fast with θ, and on the renderer's default 512-px zones (±4°) a +0.5 % camera's 3–7 m planes are drawn
with kernels of other field angles and read 0.28–0.46 instead of 0.03–0.05 (docs/results.md)."""


def benchmark_edge_ranges_m(bench) -> np.ndarray:
    """The finite true ranges (m) of every pixel of the benchmark's edge tiles (its scenes only; nothing rendered)."""
    m = bench.margin_px
    ranges = [bench.scene("edge", i)[1][m:-m, m:-m] for i in range(bench.tiles)]
    flat = np.concatenate([r.ravel() for r in ranges])
    return flat[np.isfinite(flat) & (flat > 0)]


def depth_weighted(values, depths_m, ranges_m: np.ndarray) -> float:
    """Mean over ``ranges_m`` of a quantity known at ``depths_m`` (increasing), interpolated linearly in 1/d and
    held at the nearest plane beyond the ends."""
    inv = 1.0 / np.asarray(depths_m, np.float64)
    return float(np.mean(np.interp(1.0 / np.asarray(ranges_m, np.float64), inv[::-1],
                                   np.asarray(values, np.float64)[::-1])))


def tolerance_cameras() -> list[tuple[str, object]]:
    """(name, ``BuiltCamera``) of the table's rows (module doc)."""
    from bmi_sdk.built_camera import BuiltCamera
    from bmi_sdk.nn.evaluate import EXACT
    from bmi_sdk.optics.perturb import Perturbation

    issue = EXACT["built_camera"]
    cameras = [("nominal", BuiltCamera())]
    cameras += [(f"sensor radius {pct:+g} %", BuiltCamera(perturbation=Perturbation(sensor_radius_error_pct=pct)))
                for pct in SENSOR_RADIUS_ERRORS_PCT]
    cameras.append(("the issue's perturbed camera", BuiltCamera(perturbation=issue)))
    cameras.append(("it without its radius error",
                    BuiltCamera(perturbation=replace(issue, sensor_radius_error_pct=0.0))))
    return cameras


def camera_curves(camera, depths_m=TOLERANCE_DEPTHS_M, field_deg: float = TOLERANCE_FIELD_DEG
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(window-bound AbsRel, classical decoder's AbsRel) on 1/f² planes at each of ``depths_m`` at ``field_deg``,
    rendered and decoded with ``camera``'s exact kernels (module doc)."""
    from bmi_sdk.decode import ClassicalConfig, ClassicalDecoder

    psf_map = camera.psf_map(mode="exact", centre_calibrated=True)
    decoder = ClassicalDecoder.for_psf_map(psf_map, ClassicalConfig())
    decode = classical_depth(decoder, psf_map.geometry)
    bound, decoded = [], []
    for depth_m in depths_m:
        raw, row0, col0 = plane_raw(psf_map.tensor, psf_map.geometry, field_deg, depth_m, texture="pink",
                                    psf_map=psf_map, zone_px=RENDER_ZONE_PX)
        bound.append(MEAN_ABS_PER_SIGMA * window_depth_bound(decoder, raw, row0, col0, field_deg, depth_m))
        decoded.append(decoded_absrel(decode, raw, row0, col0, depth_m))
    return np.array(bound), np.array(decoded)


def run() -> str:
    from bmi_sdk.nn.evaluate import Benchmark

    bench = Benchmark()
    ranges = benchmark_edge_ranges_m(bench)
    curves, rows = {}, []
    for name, camera in tolerance_cameras():
        start = time.process_time()
        curves[name] = camera_curves(camera)
        cpu_s = time.process_time() - start
        bound, decoded = (depth_weighted(c, TOLERANCE_DEPTHS_M, ranges) for c in curves[name])
        if not rows:
            reference = bound, decoded
        rows.append([name, bound, f"{bound / reference[0]:.2f}×", decoded, f"{decoded / reference[1]:.2f}×", cpu_s])
    quartiles = np.percentile(ranges, [5, 25, 50, 75, 95])
    spread = " / ".join(f"{q:.2f}" for q in quartiles)
    out = [f"Depth information at the field edge (θ {TOLERANCE_FIELD_DEG:g}°, φ 30°, σ 0.005; 1/f² planes, each "
           f"camera's own exact kernels render (on {RENDER_ZONE_PX}-px zones) and decode, its optical centre "
           f"calibrated), averaged over the true ranges of the `bmi eval` benchmark's {bench.tiles} edge tiles (seed "
           f"{bench.seed}; {len(ranges)} pixels, 5 / 25 / 50 / 75 / 95 % at {spread} m) in 1/d between the planes. "
           "At bound: the AbsRel of an estimator at one tapered window's Cramér–Rao bound (√(2/π) σ_d / d); "
           "decoded: the classical decoder's on the same planes (pooled windows). CPU s: the camera's kernels "
           "traced, its planes rendered and decoded.", ""]
    out.append(markdown_table(["camera", "AbsRel at bound", "× nominal", "AbsRel decoded", "× nominal", "CPU s"],
                              rows))
    names = ["nominal", "sensor radius +0.5 %", "the issue's perturbed camera"]
    out += ["", "Per range, the nominal camera, the sensor radius +0.5 % and the issue's perturbed camera "
                "(at bound · decoded):", ""]
    per_depth = [[f"{d:g} m"] + [f"{curves[n][0][k]:.3f} · {curves[n][1][k]:.3f}" for n in names]
                 for k, d in enumerate(TOLERANCE_DEPTHS_M)]
    out.append(markdown_table(["range"] + names, per_depth))
    return "\n".join(out)


def register(subparsers) -> None:
    register_target(subparsers, "tolerance", "depth information a built camera's errors take from the field edge",
                    __doc__, "Hardware tolerance at the field edge", run, full=False)
