"""`bmi bench learned`: the learned refinement against its own classical stage on textured planes, and its cost.

* Planes: the textured fronto-parallel planes of ``bmi bench decoder`` (1–8 m, θ 0° and 50°, σ 0.005,
  the nominal tensor kernels render and decode), decoded by the classical decoder with the learned
  model's knobs, by the refinement network on top of it, and by the learned decoder (the two fused with
  the weights of the model's manifest, ``decode.fusion``, as ``bmi infer`` returns it): depth AbsRel per
  distance.
* Cost: CPU and wall seconds per 192² tile of each stage (classical; network with its fusion and AiF step), median
  of the plane runs.
* ``--full``: a 6000×4500 procedural frame through ``bmi infer --decoder learned``'s runtime steps
  (classical stage over the whole frame, the network tile by tile, the fusion, the AiF's consistency step): wall
  and CPU time per stage,
  and the AbsRel of the classical stage alone, the network alone and the fused depth. The frame is rendered
  with the tensor kernels and decoded with them (as ``bmi bench decoder --full`` and ``bmi bench pooling
  --full`` do): the runtime's exact kernels would read it through a render-model mismatch (the classical stage
  0.086 against 0.058).
"""

from __future__ import annotations

import time

import numpy as np

from . import cpu_seconds, markdown_table, peak_rss_mb, register_target
from .decoder import PLANE_DEPTHS_M, PLANE_FIELDS_DEG, classical_depth, full_frame_raw, plane_absrel


def _learned_depth(tiles, geometry, costs: dict, fuse: bool):
    """``plane_absrel``'s ``decode`` for a ``nn.evaluate.NetworkTiles`` refinement, timing its two stages; ``fuse``:
    the depth fused with the classical stage's (``decode.fusion``), else the network's own."""

    def decode(raw, row0, col0, noise):
        w0, c0 = time.perf_counter(), cpu_seconds()
        decoded = tiles.classical_read(raw, geometry, row0, col0, noise)
        w1, c1 = time.perf_counter(), cpu_seconds()
        _, depth, _ = tiles.network_read(raw, geometry, row0, col0, decoded, fuse)
        costs.setdefault("classical", []).append((w1 - w0, c1 - c0))
        costs.setdefault("network", []).append((time.perf_counter() - w1, cpu_seconds() - c1))
        return depth, decoded.valid

    return decode


def _full_frame(model_path, nominal, geometry) -> str:
    from bmi_sdk.decode import ClassicalDecoder
    from bmi_sdk.nn.data import STANDARD_SIGMA
    from bmi_sdk.render import PsfMap
    from bmi_sdk.runtime.learned import model_classical_config, refine_decoded
    from bmi_sdk.runtime.model import Model
    from bmi_sdk.sensor import BLACK_LEVEL_DN, WHITE_LEVEL_DN, NoiseProfile

    range_m, raw, _ = full_frame_raw(nominal, geometry)
    model = Model(model_path)
    decoder = ClassicalDecoder.for_psf_map(PsfMap(nominal, geometry, mode="tensor"), model_classical_config(model))
    w0, c0 = time.perf_counter(), cpu_seconds()
    decoded = decoder.decode(raw, BLACK_LEVEL_DN, WHITE_LEVEL_DN, geometry,
                             noise_profile=NoiseProfile.additive(STANDARD_SIGMA))
    w1, c1 = time.perf_counter(), cpu_seconds()
    result = refine_decoded(model, decoder, decoded, raw, black_level_dn=BLACK_LEVEL_DN,
                            white_level_dn=WHITE_LEVEL_DN, geometry=geometry, keep_network_read=True)
    w2, c2 = time.perf_counter(), cpu_seconds()
    ok = result.valid & decoded.valid & np.isfinite(range_m)

    def absrel_of(depth_m: np.ndarray) -> float:
        return float(np.mean(np.abs(depth_m[ok] - range_m[ok]) / range_m[ok]))

    fusion = result.report["fusion"]
    fusion_s = fusion["fusion_s"]
    network_s = sum(result.parts["network"].timings_s.values())
    rows = [["classical stage", f"{w1 - w0:.1f}", f"{c1 - c0:.1f}"],
            ["channels + network + fusion + AiF step", f"{w2 - w1:.1f}", f"{c2 - c1:.1f}"],
            ["of which the network's tiles (input, ONNX, blend)", f"{network_s:.1f}", ""],
            ["of which the fusion", f"{fusion_s:.1f}", ""],
            ["of which the AiF's consistency step", f"{result.parts['stats']['timings_s']['aif_consistency_s']:.1f}",
             ""],
            ["total", f"{w2 - w0:.1f}", f"{c2 - c0:.1f}"]]
    classical_absrel, network_absrel, absrel = (absrel_of(d) for d in (decoded.depth_m, result.parts["network_depth_m"],
                                                                       result.depth_m))
    share = fusion["classical_weight_mean"]
    return "\n".join([f"Full 6000×4500 procedural frame (seed 7, tensor-mode render, decoded with the same kernels), "
                      f"learned decoder {model_path.name}; peak RSS {peak_rss_mb():.0f} MB (render included); depth "
                      f"AbsRel over {int(ok.sum())} valid pixels: classical stage alone {classical_absrel:.3f}, "
                      f"network alone {network_absrel:.3f}, fused (the decoder's output, {fusion['weights']} "
                      f"weights) {absrel:.3f}, the classical read's mean weight {share:.2f}.", "",
                      markdown_table(["stage", "wall s", "CPU s"], rows)])


def run(full: bool = False) -> str:
    from bmi_sdk.lenses import lens_geometry, lens_tensor
    from bmi_sdk.nn.evaluate import NetworkTiles
    from bmi_sdk.render import PsfMap
    from bmi_sdk.runtime.model import LEARNED_MODEL

    nominal = lens_tensor("bmi_monocentric")
    geometry = lens_geometry("bmi_monocentric")
    psf_map = PsfMap(nominal, geometry, mode="tensor")
    tiles = NetworkTiles(LEARNED_MODEL, 192, 2, psf_map)
    costs: dict = {}
    network = _learned_depth(tiles, geometry, costs, fuse=False)
    learned = _learned_depth(tiles, geometry, {}, fuse=True)
    rows = []
    for depth_m in PLANE_DEPTHS_M:
        row = [f"{depth_m:g} m"]
        for field_deg in PLANE_FIELDS_DEG:
            row += [plane_absrel(nominal, geometry, decode, field_deg, depth_m)
                    for decode in (classical_depth(tiles.stage, geometry), network, learned)]
        rows.append(row)
    head = ["range"] + [f"θ {f:g}° {d}" for f in PLANE_FIELDS_DEG for d in ("classical", "network", "learned")]
    out = [f"Textured fronto-parallel planes (192² window, φ 30°, σ 0.005, nominal tensor kernels render and "
           f"decode), {LEARNED_MODEL.name}: its classical stage, its network alone and the two fused (the learned "
           f"decoder's output): depth AbsRel", "",
           markdown_table(head, rows), ""]
    cost_rows = [[stage, f"{np.median([w for w, _ in v]):.2f}", f"{np.median([c for _, c in v]):.2f}"]
                 for stage, v in costs.items()]
    out += ["Cost per 192² tile (median over the plane runs):", "", markdown_table(["stage", "wall s", "CPU s"],
                                                                                   cost_rows)]
    if full:
        out += ["", _full_frame(LEARNED_MODEL, nominal, geometry)]
    return "\n".join(out)


def register(subparsers) -> None:
    register_target(subparsers, "learned", "learned refinement: planes against its classical stage, cost, full frame",
                    __doc__, "Learned refinement", run)
