"""The learned refinement at run time: classical decode with the camera's own kernels, then a network.

``--decoder learned`` runs the classical decoder (``runtime.classical``: the evidence of the built
camera's kernels, nominal or calibrated) with the knobs the model was trained with (its manifest's
``classical_config``), turns its result into per-pixel channels (``decode.features``) and runs the
refinement network tile by tile (``pipeline.infer_raw`` with ``extra``), which returns depth, AiF and a
depth 1σ. The depth returned is the network's read fused with the classical stage's (``decode.fusion``), by
their σs, their disagreement and the classical depth's local variation, with the weights the model's manifest
carries (``bmi fit-fusion``; else the inverse-variance ones): the physics decides where it is confident and
the surface is larger than its windows, the network elsewhere. On a built camera (kernels with hardware
errors, e.g. ``--calibration``'s) the AiF returned is the network's made consistent with the raw frame
through that camera's kernels at the fused depth (``consistent_aif``): a network trained on the design
draws a built camera's image shifted and reshaped, and the camera's own kernels pull it back. The
calibration reaches the network through the evidence, the fusion and that step: the model is not retrained.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from ..built_camera import BuiltCamera
from ..decode import ClassicalConfig, ClassicalDecoder
from ..decode.classical import DecodeResult, log_depth_variation_px
from ..decode.features import FeatureTiles, extra_channels
from ..decode.fusion import INVERSE_VARIANCE, FusionWeights, fuse_log_depth
from ..model_io import INPUT_CHANNELS
from ..model_manifest import ModelError
from ..parallel import map_threads
from ..sensor import NoiseProfile
from .classical import classical_decoder, decode_frame
from .decoders import DecodedFrame
from .model import Model
from .pipeline import infer_raw


def model_classical_config(model: Model, threads: int | None = None) -> ClassicalConfig:
    """The classical decoder's knobs a learned model was trained with (its manifest), on ``threads`` threads."""
    if model.decoder != "learned":
        raise ValueError(f"model {model.path.name} is a {model.decoder} model, not a learned refinement")
    knobs = dict(model.manifest["classical_config"])
    knobs.setdefault("aif_model_error", 0.0)
    knobs.setdefault("pool_sigma_px", 0.0)  # and each window read alone
    knobs["slopes"] = tuple(knobs.get("slopes", (2.0,)))
    return replace(ClassicalConfig(**knobs), threads=threads)


def learned_decoder(model: Model, camera: BuiltCamera, threads: int | None = None) -> ClassicalDecoder:
    """The classical stage for ``model`` over ``camera``'s kernels, checked to give the channels it reads."""
    decoder = classical_decoder(camera, model_classical_config(model, threads))
    given = INPUT_CHANNELS + extra_channels(decoder)
    if given != model.input_channels:
        raise ValueError(f"model {model.path.name} reads {model.input_channels} channels; the classical decoder "
                         f"over camera {camera.sha256()[:12]} gives {given} (another candidate grid)")
    return decoder


def decode_learned(model: Model, decoder: ClassicalDecoder, frame, camera: BuiltCamera,
                   overlap_px: int | None = None, progress: bool = False) -> DecodedFrame:
    """Decode a ``devices.RawFrame`` taken by ``camera``: classical stage, then the refinement network."""
    classical = decode_frame(decoder, frame, camera, progress=progress)
    return refine_decoded(model, decoder, classical.parts["classical"], frame.data, black_level_dn=frame.black_level_dn,
                          white_level_dn=frame.white_level_dn, cfa=frame.cfa, geometry=frame.geometry,
                          row0=frame.roi.y_px, col0=frame.roi.x_px, stats=classical.parts["stats"], overlap_px=overlap_px,
                          progress=progress, reuse_classical_aif=True)


def refine_decoded(model: Model, decoder: ClassicalDecoder, decoded: DecodeResult, raw: np.ndarray, *,
                   black_level_dn: float, white_level_dn: float, cfa: str = "RGGB", geometry, row0: int = 0,
                   col0: int = 0, stats: dict | None = None, overlap_px: int | None = None, progress: bool = False,
                   keep_network_read: bool = False, reuse_classical_aif: bool = False) -> DecodedFrame:
    """The refinement's second stage over an H × W raw window that ``decoder`` decoded into ``decoded``: its
    channels, the network tile by tile, the fusion of the two reads and, on a built camera, the AiF's step.

    A pixel is valid where the network reads it (inside the image circle); where the classical stage has no
    read there, the network's is the output (``decode.fusion``). ``keep_network_read`` keeps the network's
    depth before the fusion (``parts["network_depth_m"]``, a copy: 108 MB for a full frame) for benchmarks. The
    result's ``parts`` also hold the network's read (``"network"``, an ``InferenceResult``) and the classical
    stage's statistics with this stage's timings (``"stats"``).
    ``reuse_classical_aif`` writes the AiF step's output into ``decoded.aif`` (read by the network, then no longer
    needed: 324 MB of a full frame), which then no longer holds the classical AiF.
    """
    stats = dict(decoded.stats if stats is None else stats)
    t0 = time.perf_counter()
    features = FeatureTiles(decoded, decoder.config.stride_px)
    stats["timings_s"] = dict(stats["timings_s"], features_s=time.perf_counter() - t0)
    net = infer_raw(model, raw, black_level_dn=black_level_dn, white_level_dn=white_level_dn, cfa=cfa,
                    geometry=geometry, row0=row0, col0=col0, overlap_px=overlap_px, progress=progress,
                    extra=features)
    network_depth_m = net.depth_m.copy() if keep_network_read else None
    t0 = time.perf_counter()
    weights = model.fusion_weights
    if weights is None or net.depth_sigma_m is None:
        raise ModelError(f"model {model.path.name} was loaded without its fusion weights or returned no depth 1σ: "
                         "the learned decoder fuses both")
    noise_sigma = decoded.stats.get("noise_sigma")
    classical_share = fuse_into(decoded, decoder.config.stride_px, net.depth_m, net.depth_sigma_m, weights,
                                noise_sigma, decoder.threads)
    fusion = {"classical_weight_mean": classical_share, "fusion_s": time.perf_counter() - t0,
              "weights": "inverse-variance" if weights == INVERSE_VARIANCE else "fitted", "noise_sigma": noise_sigma,
              "coefficients": [float(c) for c in weights.coefficients(noise_sigma)], **weights.to_dict()}
    t0 = time.perf_counter()
    aif = consistent_aif(decoder, decoded, raw, net.aif, net.depth_m, black_level_dn=black_level_dn,
                         white_level_dn=white_level_dn, cfa=cfa, geometry=geometry, row0=row0, col0=col0,
                         out=decoded.aif if reuse_classical_aif else None)
    stats["timings_s"] = dict(stats["timings_s"], aif_consistency_s=time.perf_counter() - t0)
    stats["aif_consistency"] = aif is not net.aif
    valid = net.valid & np.isfinite(net.depth_m)
    skipped = stats["candidate_evaluations_exhaustive"] - stats["candidate_evaluations"]
    report = {"valid_fraction": float(valid.mean()), "tiles_run": net.tiles_run, "tiles_skipped": net.tiles_skipped,
              "tiling": net.plan.to_dict(), "blocks_run": stats["blocks_run"], "blocks_skipped": stats["blocks_skipped"],
              "candidate_evaluations_skipped": int(skipped), "decoder_stats": stats, "fusion": fusion,
              "aif_consistency_step": stats["aif_consistency"],
              "timings_s": {"classical": stats["timings_s"], "network": net.timings_s}}
    return DecodedFrame(aif, net.depth_m, valid, net.depth_sigma_m, report,
                        {"network": net, "classical": decoded, "stats": stats, "network_depth_m": network_depth_m})


CONSISTENCY_AIF_STEP = 8
"""The AiF step blurs and deconvolves on every 8th candidate, where the classical AiF uses every 4th: on the
``bmi eval`` built camera's calibrated edge 23.78 dB against 23.79 at every 4th, for 0.75 of the time (every 16th:
23.70 dB, 0.57; docs/benchmarks.md, "The AiF's step on a built camera"; ``bmi bench aif-step``)."""


def consistent_aif(decoder: ClassicalDecoder, decoded: DecodeResult, raw: np.ndarray, aif: np.ndarray,
                   depth_m: np.ndarray, *, black_level_dn: float, white_level_dn: float, cfa: str = "RGGB", geometry,
                   row0: int = 0, col0: int = 0, out: np.ndarray | None = None,
                   aif_step: int | None = None) -> np.ndarray:
    """The network's ``aif`` of a raw window made consistent with it through ``decoder``'s kernels at ``depth_m`` (the
    fused depth), with the noise the classical stage ``decoded`` read (``ClassicalDecoder.restore_aif``; into ``out``
    when given; on every ``aif_step``-th candidate, default ``CONSISTENCY_AIF_STEP``); ``aif`` itself when those
    kernels are the design's, which the network was trained on.

    Measured on the ``bmi eval`` tiles (docs/results.md): the built camera's calibrated edge 20.5 → 23.8 dB; on the
    design camera the step moves the AiF by ≤ 0.05 dB and costs a full frame 11 s, so it is left out there."""
    if decoder.zones.psf_map.perturbation is None:
        return aif
    noise = NoiseProfile(**decoded.stats["noise_profile"])
    return decoder.restore_aif(raw, black_level_dn, white_level_dn, geometry, depth_m, aif, noise, row0, col0, cfa,
                               out, aif_step or CONSISTENCY_AIF_STEP)


FUSION_ROWS = 256
"""Rows fused at a time: a full frame's temporaries stay a few tens of MB."""


def fuse_into(classical: DecodeResult, stride_px: int, depth_m: np.ndarray, sigma_m: np.ndarray,
              weights: FusionWeights = INVERSE_VARIANCE, noise_sigma: float | None = None, threads: int = 1) -> float:
    """Replace the network's ``depth_m`` and ``sigma_m`` (NaN where invalid) by their fusion with the ``classical``
    read of the same window (``decode.fusion`` with ``weights`` at the frame's ``noise_sigma``, and the classical
    read's log-depth variation when the weights read it), band by band on ``threads`` threads; returns the classical
    read's mean weight over the valid pixels."""

    def fuse_band(top: int) -> tuple[float, int]:
        band = slice(top, top + FUSION_ROWS)
        valid = np.isfinite(depth_m[band])
        variation = (log_depth_variation_px(classical, stride_px, top, valid.shape[0])
                     if weights.reads_variation else None)
        fused, sigma, weight = fuse_log_depth(classical.depth_m[band], classical.depth_sigma_m[band], depth_m[band],
                                              sigma_m[band], weights, noise_sigma, variation)
        depth_m[band] = np.where(valid, fused, np.nan)
        sigma_m[band] = np.where(valid, sigma, np.nan)
        return float(weight[valid].sum()), int(valid.sum())

    tops = range(0, depth_m.shape[0], FUSION_ROWS)
    bands = [band for _, band in map_threads(fuse_band, tops, threads, "fusion")]
    weight_sum, count = 0.0, 0
    for band_sum, band_count in bands:  # in band order: the same sum as one thread's
        weight_sum += band_sum
        count += band_count
    return weight_sum / count if count else float("nan")
