"""`bmi bench aif-step`: the learned decoder's AiF step on a built camera, its AiF against the step's run time.

On a built camera the learned decoder pulls its network's AiF to the frame through the camera's own kernels
(``runtime.learned.consistent_aif``, docs/decoder.md); its one knob is the candidate step it blurs and deconvolves
on. This measures it where it matters: the ``bmi eval`` benchmark's tiles of the issue's perturbed camera
(``nn.evaluate.EXACT["built_camera"]``: decenter 10 µm, PSF shift 0.5 px, stray light 3 %, sensor radius +0.5 %),
rendered with its exact kernels on its own render zones at σ 0.005, and decoded by the learned decoder with the same
kernels (a perfect calibration, the ``learned_calibrated`` rows of ``bmi eval``). Each tile's classical stage,
network and fusion run once; the step then runs at each setting on the same fused depth. Rows: AiF PSNR (mean over a
region's tiles, as ``bmi eval``) and the step's wall seconds per 192² tile (both cores), beside the network's own AiF
and the classical stage's.

4 tiles per region (~2 min of rendering); ``--full``: the benchmark's 12 (~7 min).
"""

from __future__ import annotations

import time

import numpy as np

from . import markdown_table, register_target

STEPS = (16, 8, 4)
"""Candidate steps measured: every 16th, every 8th (shipped, ``CONSISTENCY_AIF_STEP``), every 4th (the classical
AiF's)."""


def run(full: bool = False) -> str:
    from bmi_sdk.built_camera import BuiltCamera
    from bmi_sdk.lenses import lens_geometry
    from bmi_sdk.metrics import image_metrics
    from bmi_sdk.nn.data import STANDARD_SIGMA
    from bmi_sdk.nn.evaluate import EXACT, Benchmark, NetworkTiles, tile_raw
    from bmi_sdk.runtime.learned import CONSISTENCY_AIF_STEP
    from bmi_sdk.runtime.model import LEARNED_MODEL
    from bmi_sdk.sensor import NoiseProfile

    bench = Benchmark(tiles=12 if full else 4)
    geometry = lens_geometry(bench.lens)
    camera = BuiltCamera(bench.lens, EXACT["built_camera"])
    renders = bench.renders(camera.psf_tensor(), psf_mode="exact", zone_px=camera.render_zone_px("exact"))
    learned = NetworkTiles(LEARNED_MODEL, bench.tile_px, 2, camera.psf_map(mode="exact", centre_calibrated=True))
    noise = NoiseProfile.additive(STANDARD_SIGMA)
    psnr: dict[tuple, list] = {}
    step_s: dict[int, list] = {}
    for k, item in enumerate(renders):
        raw = tile_raw(bench, item, k, STANDARD_SIGMA)
        row0, col0 = item["row0"], item["col0"]
        decoded = learned.classical_read(raw, geometry, row0, col0, noise)
        network_aif, depth_m, sigma_m = learned.network_read(raw, geometry, row0, col0, decoded, fuse=False)
        learned.fuse_read(decoded, depth_m, sigma_m)
        valid = (geometry.valid_mask(row0, col0, bench.tile_px, bench.tile_px) & np.isfinite(item["range_m"])
                 & np.isfinite(depth_m))
        reads = {"network": network_aif, "classical": decoded.aif}
        for step in STEPS:
            t0 = time.perf_counter()
            reads[step] = learned.consistent_read(raw, geometry, row0, col0, decoded, network_aif, depth_m, step)
            step_s.setdefault(step, []).append(time.perf_counter() - t0)
        for name, aif in reads.items():
            psnr.setdefault((name, item["region"]), []).append(image_metrics(aif, item["rgb"], valid)["psnr_db"])

    def row(label: str, name, seconds: str) -> list:
        return [label] + [f"{np.mean(psnr[(name, region)]):.2f}" for region in ("centre", "edge")] + [seconds]

    rows = [row("none (the network's AiF)", "network", "0"),
            *(row(f"every {step}th candidate" + (" (shipped)" if step == CONSISTENCY_AIF_STEP else ""), step,
                  f"{np.mean(step_s[step]):.3f}") for step in STEPS),
            row("the classical stage's AiF (no network)", "classical", "—")]
    per_region = len(renders) // 2
    return "\n".join([f"The learned decoder's AiF step on the issue's perturbed camera ({per_region} `bmi eval` tiles "
                      f"per region, seed {bench.seed}, σ 0.005, exact renders on {camera.render_zone_px('exact')}-px "
                      f"zones, decoded with the camera's own kernels): AiF PSNR and the step's wall seconds per "
                      f"{bench.tile_px}² tile", "",
                      markdown_table(["AiF step", "PSNR dB centre", "PSNR dB edge", "step s per tile"], rows)])


def register(subparsers) -> None:
    register_target(subparsers, "aif-step", "learned decoder's AiF step on a built camera: AiF against run time",
                    __doc__, "Learned AiF step on a built camera", run)
