"""The user-facing job: a raw frame (``RawFrame`` or DNG path) in, output files and a JSON report out.

``run_job`` reads the frame, builds the camera that took it (``BuiltCamera.for_frame``, with a calibration
loaded once), opens a decoder for it (``decoders.open_decoder``) unless given one, decodes, and writes the
outputs and ``report.json`` as one set.
"""

from __future__ import annotations

import os
import time
import warnings

from ..built_camera import BuiltCamera
from ..resources import peak_rss_mb
from .decoders import DecodedFrame, DecoderOptions, decoder_kind, open_decoder
from .output_set import OutputSet
from .outputs import check_depth_range, write_frame_files, write_report
from .pipeline import frame_lens_name
from .provenance import input_path_of, provenance
from .quality import FrameQualityWarning, quality_gate


def _read_checked(frame_or_path, allow_test_pattern: bool):
    """(frame, quality, timings): the frame read (if a path) and passed through ``quality_gate``, whose
    findings go to ``warnings.warn`` (``FrameQualityWarning``); a test pattern is refused unless allowed."""
    from devices import load_raw

    t0 = time.perf_counter()
    frame = load_raw(frame_or_path) if isinstance(frame_or_path, (str, os.PathLike)) else frame_or_path
    timings = {"read_raw_s": time.perf_counter() - t0}
    quality = quality_gate(frame, allow_test_pattern)
    for message in quality.warnings:
        warnings.warn(message, FrameQualityWarning, stacklevel=4)
    return frame, quality, timings


def _write_and_report(out_dir, result, frame, quality, timings: dict, head: dict, ply_step_px: int,
                      depth_range_m, camera) -> dict:
    """Write a decoded frame's files into ``out_dir`` and return its report, whichever decoder ran: the
    decoder's own ``head`` entries, the frame, its quality, the result's summary, timings, memory and files.
    The point cloud and ``depth_z`` follow the chief rays of ``camera`` (a ``BuiltCamera``: a calibrated
    camera's traced rays, ``BuiltCamera.ray_geometry``). ``run_job`` completes the report and writes it once."""
    t0 = time.perf_counter()
    rays = camera.ray_geometry()
    timings["ray_geometry_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    written = write_frame_files(out_dir, result, frame, geometry=rays, ply_step_px=ply_step_px,
                                  depth_range_m=depth_range_m)
    timings["write_outputs_s"] = time.perf_counter() - t0
    return {
        "schema": "bmi-infer-report/1",
        **head,
        "rays": ray_summary(rays, frame.geometry),
        "frame_calibration_id": getattr(frame, "calibration_id", None),
        "frame": {"frame_id": frame.frame_id, "shape": list(frame.data.shape), "roi": vars(frame.roi),
                  "lens": frame.lens, "device": frame.device, "source": frame.source},
        "frame_quality": quality.to_dict(),
        **result.summary(),
        **depth_statistics(result),
        "stage_timings_s": timings,
        "peak_rss_mb": peak_rss_mb(),
        **written,
    }


CONFIDENT_RELATIVE_SIGMA = 0.1
"""A pixel's depth is confident when its 1σ is at most this share of the depth (``confident_coverage``)."""


def depth_statistics(decoded: DecodedFrame) -> dict:
    """The report's plain account of a decoded depth map: the share of the frame with a depth
    (``valid_fraction``), the range its valid pixels span (``depth_range_m``: 1st and 99th percentile, metres;
    None without one) and ``confident_coverage``, the share of valid pixels whose 1σ is at most
    ``CONFIDENT_RELATIVE_SIGMA`` of their depth (None for a decoder that reports no 1σ)."""
    import numpy as np

    depth = decoded.depth_m
    valid = decoded.valid & np.isfinite(depth) & (depth > 0)
    values = depth[valid]
    span = [round(float(v), 4) for v in np.percentile(values, [1, 99])] if values.size else None
    coverage = None
    if decoded.depth_sigma_m is not None and values.size:
        coverage = float(np.mean(decoded.depth_sigma_m[valid] <= CONFIDENT_RELATIVE_SIGMA * values))
    return {"valid_fraction": float(valid.mean()), "depth_range_m": span, "confident_coverage": coverage}


def ray_summary(rays, sensor) -> dict:
    """The report's account of the rays the point cloud used: the frame's sensor geometry, or a built
    camera's traced one (its optical centre, and how far its rays land from the symmetric mapping)."""
    if rays == sensor:
        return {"source": "sensor geometry", "centre_px": list(sensor.centre_px)}
    return {"source": "traced through the calibrated camera", "centre_px": list(rays.centre_px),
            "nominal_centre_px": list(sensor.centre_px),
            "max_asymmetric_displacement_px": getattr(rays, "max_displacement_px", 0.0)}


def check_calibration(frame, calibration) -> dict:
    """Check a loaded calibration (``calibration.io.Calibration``) against ``frame``; returns its identity for the
    report. It is refused when it contradicts the frame: another lens, or another camera serial."""
    frame_lens = frame_lens_name(frame)
    calib_lens = calibration.doc.get("lens", {}).get("name")
    if frame_lens is not None and calib_lens is not None and frame_lens != calib_lens:
        raise ValueError(f"calibration {calibration.id} is for lens {calib_lens!r}; the frame was taken through "
                         f"{frame_lens!r}")
    frame_serial = (getattr(frame, "device", None) or {}).get("serial")
    calib_serial = calibration.doc["device"].get("serial")
    if frame_serial is not None and calib_serial is not None and frame_serial != calib_serial:
        raise ValueError(f"calibration {calibration.id} was made on camera {calib_serial!r}; "
                         f"the frame comes from {frame_serial!r}")
    return {"path": str(calibration.path), "id": calibration.id, "device": calibration.doc["device"],
            "lens": calib_lens, "corrected_tensor_sha256": calibration.doc["corrected_tensor"]["npz_sha256"]}


def load_calibration(calibration):
    """A ``calibration.io.Calibration``: ``calibration`` itself when loaded, else the file it names, read and
    validated once (schema, parameters, content id, corrected-tensor hash); None stays None."""
    if calibration is None or not isinstance(calibration, (str, os.PathLike)):
        return calibration
    from calibration.io import load_calibration as load

    return load(calibration)


def camera_for(frame, calibration=None):
    """(BuiltCamera, calibration identity or None) that took ``frame``: the nominal camera of the frame's lens, or
    with ``calibration`` (a loaded ``Calibration`` or its file) the calibrated one, after ``check_calibration``."""
    calibration = load_calibration(calibration)
    identity = None if calibration is None else check_calibration(frame, calibration)
    return BuiltCamera.for_frame(frame, calibration), identity


def run_job(frame_or_path, out_dir: str | os.PathLike, *, overwrite: bool = False, decoder=None,
            model=None, model_path: str | os.PathLike | None = None, calibration=None,
            calibration_path: str | os.PathLike | None = None, classical_config=None, tile_px: int = 512,
            threads: int | None = None, overlap_px: int | None = None, providers=None, ply_step_px: int = 1,
            progress: bool = False, allow_test_pattern: bool = False,
            depth_range_m: tuple[float, float] | None = None, texture_exponent: str = "prior",
            input_path: str | os.PathLike | None = None) -> tuple[DecodedFrame, dict]:
    """Read (if a path), decode, write outputs and ``report.json`` into ``out_dir``; return (decoded, report).

    ``decoder``: an opened ``Decoder`` (``decoders.open_decoder``; a batch opens one per camera and reuses it),
    or the kind to open for this frame's camera (``decoders.DECODERS``; None: the kind of ``model`` or
    ``model_path``, else ``DEFAULT_DECODER``) with ``model``/``model_path``, ``classical_config``, the network's
    ``tile_px``, ``threads``, ``providers``, ``overlap_px`` and the texture model (``texture_exponent``,
    ``decode.classical.TEXTURE_EXPONENTS``). ``calibration`` (a loaded ``calibration.io.Calibration``)
    or ``calibration_path`` (its file) makes the camera the calibrated one, after ``check_calibration``.

    The frame passes ``quality_gate`` first: its findings go to ``warnings.warn`` (``FrameQualityWarning``) and
    the report's ``frame_quality``; a test pattern is refused unless ``allow_test_pattern``. ``depth_range_m``
    (near, far): fixed colours for ``depth_preview.png`` (``write_outputs``). The outputs are one set
    (``OutputSet``): ``out_dir`` is checked before any work (writable; no earlier results unless ``overwrite``)
    and changes only once every file is written. The point cloud and ``depth_z`` follow the camera's chief rays
    (``BuiltCamera.ray_geometry``: a calibrated camera's traced rays).

    The report records the software versions, the execution provider (None for a decoder without a network)
    and the input path: ``frame_or_path`` when it is a path, else ``input_path`` (the file a caller read the
    frame from), else None.
    """
    opened = not isinstance(decoder, (str, type(None)))
    if not opened:
        decoder_kind(decoder, model if model is not None else model_path)  # an unknown kind fails before any work
    _check_counts({"ply_step_px": ply_step_px, "threads": threads})
    if depth_range_m is not None:
        check_depth_range(depth_range_m)  # before any work
    calibration = load_calibration(calibration if calibration is not None else calibration_path)
    with OutputSet(out_dir, overwrite=overwrite) as output_set:
        frame, quality, timings = _read_checked(frame_or_path, allow_test_pattern)
        camera, identity = camera_for(frame, calibration)
        _warn_calibration_mismatch(frame, identity, quality)
        if opened:
            if decoder.camera != camera:
                raise ValueError(f"the {decoder.kind} decoder was opened for camera {decoder.camera.sha256()[:12]}; "
                                 f"this frame's is {camera.sha256()[:12]}")
        else:
            t0 = time.perf_counter()
            decoder = open_decoder(camera, decoder, model if model is not None else model_path, classical_config,
                                   DecoderOptions(tile_px, threads, providers, overlap_px, texture_exponent))
            loaded = getattr(decoder, "model", None)
            if loaded is not None and loaded is not model:
                timings["load_model_s"] = loaded.load_s
                timings["warmup_s"] = loaded.warmup_s
            else:
                timings["open_decoder_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        decoded = decoder.decode(frame, progress=progress)
        timings["decode_s"] = time.perf_counter() - t0
        report = _write_and_report(output_set.folder, decoded, frame, quality, timings,
                                   {**decoder.head(), "calibration_file": identity}, ply_step_px, depth_range_m,
                                   camera)
        provider = report["model"]["execution_provider"] if "model" in report else None
        source = input_path_of(frame_or_path) or (os.path.abspath(input_path) if input_path is not None else None)
        report.update(provenance(source, provider))
        report["files"] = {name: os.path.join(out_dir, name) for name in report["files"]}
        if output_set.removed_staging:
            report["removed_staging"] = output_set.removed_staging
        write_report(output_set.folder, report)  # with the paths the files will have
        output_set.commit()
    return decoded, report


def _warn_calibration_mismatch(frame, identity: dict | None, quality) -> None:
    """Warn (stderr and the report's ``frame_quality``) when the frame names a calibration other than the one it is
    decoded with: its camera's fitted errors are then not the decoder's."""
    named = getattr(frame, "calibration_id", None)
    used = None if identity is None else identity["id"]
    if named and named != used:
        message = (f"the frame was captured with calibration {named}; it is decoded with "
                   + (f"calibration {used}" if used else "nominal PSFs (pass --calibration with that calibration's file)"))
        quality.warnings.append(message)
        warnings.warn(message, FrameQualityWarning, stacklevel=3)


def _check_counts(options: dict) -> None:
    """Refuse, before any work, a point-cloud step or thread count that the end of a decode would trip over (a
    full frame's minutes spent first) or that onnxruntime would take silently."""
    for name, value in (("ply_step_px", options.get("ply_step_px", 1)), ("threads", options.get("threads"))):
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
            raise ValueError(f"{name} must be a whole number >= 1{' (None: all cores)' if name == 'threads' else ''}, "
                             f"got {value!r}")
