"""The user-facing job: a raw frame (``RawFrame`` or DNG path) in, output files and a JSON report out."""

from __future__ import annotations

import os
import time
import warnings

from ..resources import peak_rss_mb
from ..model_manifest import ModelError
from .model import Model, select_model
from .output_set import OutputSet
from .outputs import check_depth_range, write_frame_outputs, write_report
from .pipeline import InferenceResult, frame_lens_name, infer_frame
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
    written = write_frame_outputs(out_dir, result, frame, geometry=rays, ply_step_px=ply_step_px,
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
        "stage_timings_s": timings,
        "peak_rss_mb": peak_rss_mb(),
        **written,
    }


def ray_summary(rays, sensor) -> dict:
    """The report's account of the rays the point cloud used: the frame's sensor geometry, or a built
    camera's traced one (its optical centre, and how far its rays land from the symmetric mapping)."""
    if rays == sensor:
        return {"source": "sensor geometry", "centre_px": list(sensor.centre_px)}
    return {"source": "traced through the calibrated camera", "centre_px": list(rays.centre_px),
            "nominal_centre_px": list(sensor.centre_px),
            "max_asymmetric_displacement_px": getattr(rays, "max_displacement_px", 0.0)}


def load_model_for(frame, model_path: str | os.PathLike | None = None, calibration_id: str | None = None,
                   tile_px: int = 512, threads: int | None = None,
                   providers: str | list[str] | None = None) -> tuple[Model, str | None]:
    """The model for ``frame``: ``model_path`` if given, else the packaged model for the calibration in use.

    The calibration is ``calibration_id`` if given, else the frame's own
    (``RawFrame.calibration_id``); only models trained for the frame's lens are
    candidates. Returns the loaded model and a note when the calibration had no
    model of its own (the nominal one is used instead).
    """
    note = None
    if model_path is None:
        lens = frame_lens_name(frame) or "bmi_monocentric"
        model_path, note = select_model(calibration_id or getattr(frame, "calibration_id", None), lens=lens)
    return Model(model_path, tile_px=tile_px, threads=threads, providers=providers), note


def calibration_for(frame, calibration_path: str | os.PathLike, calibration_id: str | None = None) -> dict:
    """Load and check a calibration file for ``frame``; returns its identity for the report.

    The file is validated by ``calibration.io.load_calibration`` (schema,
    parameters, content id, corrected-tensor hash). It is refused when it
    contradicts the request: another id than an explicit ``calibration_id``,
    another lens than the frame's, or another camera serial than the frame's.
    """
    from calibration.io import load_calibration

    calib = load_calibration(calibration_path)
    if calibration_id is not None and calibration_id != calib.id:
        raise ValueError(f"--calibration-id {calibration_id} contradicts {calibration_path} (id {calib.id})")
    frame_lens = frame_lens_name(frame)
    calib_lens = calib.doc.get("lens", {}).get("name")
    if frame_lens is not None and calib_lens is not None and frame_lens != calib_lens:
        raise ValueError(f"calibration {calib.id} is for lens {calib_lens!r}; the frame was taken through {frame_lens!r}")
    frame_serial = (getattr(frame, "device", None) or {}).get("serial")
    calib_serial = calib.doc["device"].get("serial")
    if frame_serial is not None and calib_serial is not None and frame_serial != calib_serial:
        raise ValueError(f"calibration {calib.id} was made on camera {calib_serial!r}; "
                         f"the frame comes from {frame_serial!r}")
    return {"path": str(calib.path), "id": calib.id, "device": calib.doc["device"], "lens": calib_lens,
            "corrected_tensor_sha256": calib.doc["corrected_tensor"]["npz_sha256"]}


DECODERS = ("cnn", "classical", "learned")
DEFAULT_DECODER = "learned"
"""The learned refinement: on ``bmi eval`` it reads depth and AiF at least as well as the end-to-end network
on every nominal row, better under noise and with a calibration, and reports an honest 1σ
(docs/results.md, "Decoders")."""


def decoder_for(decoder: str | None, model=None, model_path=None) -> str:
    """The decoder a job runs: ``decoder`` if named; else the kind of the model given (its manifest's
    ``decoder``: a refinement model implies ``learned``, an end-to-end one ``cnn``); else ``DEFAULT_DECODER``."""
    if decoder is not None:
        if decoder not in DECODERS:
            raise ValueError(f"unknown decoder {decoder!r}; one of {DECODERS}")
        return decoder
    if model is not None:
        return model.decoder
    if model_path is not None:
        from ..model_manifest import model_decoder, read_manifest

        if not os.path.isfile(model_path):
            raise ModelError(f"no model file at {model_path}")
        return model_decoder(read_manifest(model_path))
    return DEFAULT_DECODER


def run_job(frame_or_path, out_dir: str | os.PathLike, *, overwrite: bool = False, decoder: str | None = None,
            input_path: str | os.PathLike | None = None, **options) -> tuple[InferenceResult, dict]:
    """Read (if a path), decode, write outputs and ``report.json`` into ``out_dir``; return (result, report).

    ``decoder``: ``cnn`` (the shipped end-to-end network; ``options`` are ``_job_into``'s),
    ``classical`` (``runtime.classical``: the evidence of the camera's own kernels, no network,
    writes the depth 1σ too; ``options`` are ``_classical_into``'s) or ``learned`` (the classical
    stage, then the refinement network; ``options`` are ``_learned_into``'s); None: ``decoder_for``. The outputs are one set
    (``OutputSet``): ``out_dir`` is checked before any work (writable; no earlier results
    unless ``overwrite``) and changes only once every file is written.

    The report records the software versions, the execution provider (None for ``classical``) and
    the input path: ``frame_or_path`` when it is a path, else ``input_path`` (the file a caller
    read the frame from), else None.
    """
    decoder = decoder_for(decoder, options.get("model"), options.get("model_path"))
    _check_counts(options)
    job = {"cnn": _job_into, "classical": _classical_into, "learned": _learned_into}[decoder]
    with OutputSet(out_dir, overwrite=overwrite) as output_set:
        result, report = job(frame_or_path, output_set.staging, **options)
        provider = report["model"]["execution_provider"] if "model" in report else None
        source = input_path_of(frame_or_path) or (os.path.abspath(input_path) if input_path is not None else None)
        report.update(provenance(source, provider))
        report["files"] = {name: os.path.join(out_dir, name) for name in report["files"]}
        write_report(output_set.staging, report)  # with the paths the files will have
        output_set.commit()
    return result, report


def _check_counts(options: dict) -> None:
    """Refuse, before any work, a point-cloud step or thread count that the end of a decode would trip over (a
    full frame's minutes spent first) or that onnxruntime would take silently."""
    for name, value in (("ply_step_px", options.get("ply_step_px", 1)), ("threads", options.get("threads"))):
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
            raise ValueError(f"{name} must be a whole number >= 1{' (None: all cores)' if name == 'threads' else ''}, "
                             f"got {value!r}")


def _job_into(frame_or_path, out_dir: str | os.PathLike, *, model: Model | None = None,
              model_path: str | os.PathLike | None = None, calibration_id: str | None = None,
              calibration_path: str | os.PathLike | None = None, tile_px: int = 512,
              threads: int | None = None, overlap_px: int | None = None, ply_step_px: int = 1,
              progress: bool = False, allow_test_pattern: bool = False,
              providers: str | list[str] | None = None,
              depth_range_m: tuple[float, float] | None = None) -> tuple[InferenceResult, dict]:
    """The job, written into ``out_dir`` (``run_job``'s staging folder).

    ``calibration_path`` (a ``bmi calibrate`` file) selects the model trained
    on that calibration's corrected PSF tensor, after ``calibration_for``'s
    checks; without such a model the nominal one runs and the report says so.
    The frame passes ``quality_gate`` first: its findings go to
    ``warnings.warn`` (``FrameQualityWarning``) and the report's
    ``frame_quality``; a test pattern is refused unless ``allow_test_pattern``.
    ``depth_range_m`` (near, far): fixed colours for ``depth_preview.png`` (``write_outputs``).
    """
    if depth_range_m is not None:
        check_depth_range(depth_range_m)  # before any work
    frame, quality, timings = _read_checked(frame_or_path, allow_test_pattern)
    camera, calibration = camera_for(frame, calibration_path, calibration_id)
    if calibration is not None:
        calibration_id = calibration["id"]
    note = None
    if model is None:
        t0 = time.perf_counter()
        model, note = load_model_for(frame, model_path, calibration_id, tile_px, threads, providers)
        timings["load_model_s"] = model.load_s
        timings["warmup_s"] = model.warmup_s
    t0 = time.perf_counter()
    result = infer_frame(model, frame, overlap_px=overlap_px, progress=progress)
    timings["infer_s"] = time.perf_counter() - t0
    head = {"decoder": "cnn", "model": model.describe(), "calibration_id": model.manifest["calibration_id"],
            "calibration_note": note, "calibration_file": calibration}
    return result, _write_and_report(out_dir, result, frame, quality, timings, head, ply_step_px, depth_range_m,
                                     camera)


def camera_for(frame, calibration_path=None, calibration_id: str | None = None):
    """(BuiltCamera, calibration identity or None) that took ``frame``: the nominal camera of the frame's lens,
    or with ``calibration_path`` the calibrated one (after ``calibration_for``'s checks)."""
    from ..built_camera import BuiltCamera

    if calibration_path is None:
        return BuiltCamera(lens_name=frame_lens_name(frame) or "bmi_monocentric", geometry=frame.geometry), None
    from calibration.io import load_calibration

    identity = calibration_for(frame, calibration_path, calibration_id)
    return BuiltCamera.from_calibration(load_calibration(calibration_path), geometry=frame.geometry), identity


def _classical_into(frame_or_path, out_dir, *, calibration_path=None, calibration_id: str | None = None,
                    ply_step_px: int = 1, progress: bool = False, allow_test_pattern: bool = False,
                    classical_config=None, classical_decoder=None, model=None, model_path=None,
                    tile_px: int | None = None, threads: int | None = None, overlap_px: int | None = None,
                    providers=None, depth_range_m: tuple[float, float] | None = None) -> tuple:
    """The classical decoder's job, written into ``out_dir`` (``run_job``'s staging folder).

    ``calibration_path``, after ``calibration_for``'s checks, makes the decoder use that camera's
    corrected kernels at every (θ, φ) (``BuiltCamera.from_calibration``); nothing is retrained.
    ``classical_decoder`` reuses a built decoder (its memoised kernels) across frames of one camera.
    The network's options (``model``, ``model_path``, ``providers``) are refused; its tiling options
    (``tile_px``, ``threads``, ``overlap_px``) do not apply and are ignored.
    """
    from ..decode import ClassicalConfig
    from .classical import classical_decoder as build_decoder
    from .classical import decode_frame

    if model is not None or model_path is not None:
        raise ValueError("--model names a network; the classical decoder uses none (drop --model or use "
                         "--decoder cnn)")
    if providers is not None:
        raise ValueError("--provider picks the network's onnxruntime provider; the classical decoder runs none "
                         "(drop --provider or use --decoder cnn)")
    if depth_range_m is not None:
        check_depth_range(depth_range_m)  # before any work
    frame, quality, timings = _read_checked(frame_or_path, allow_test_pattern)
    camera, calibration = camera_for(frame, calibration_path, calibration_id)
    t0 = time.perf_counter()
    decoder = classical_decoder or build_decoder(camera, classical_config or ClassicalConfig())
    result = decode_frame(decoder, frame, camera, progress=progress)
    timings["decode_s"] = time.perf_counter() - t0
    head = {"decoder": "classical", "camera": camera.to_dict() | {"sha256": camera.sha256()},
            "calibration_id": camera.calibration_id, "calibration_note": None, "calibration_file": calibration}
    return result, _write_and_report(out_dir, result, frame, quality, timings, head, ply_step_px, depth_range_m,
                                     camera)


def _learned_into(frame_or_path, out_dir, *, model: Model | None = None, model_path=None, calibration_path=None,
                  calibration_id: str | None = None, tile_px: int = 512, threads: int | None = None,
                  overlap_px: int | None = None, ply_step_px: int = 1, progress: bool = False,
                  allow_test_pattern: bool = False, providers=None,
                  depth_range_m: tuple[float, float] | None = None, learned_decoder=None) -> tuple:
    """The learned refinement's job, written into ``out_dir`` (``run_job``'s staging folder).

    The classical stage reads the camera's own kernels (``calibration_path``: the calibrated camera,
    after ``calibration_for``'s checks) with the knobs of the model's manifest; the network is the
    packaged ``learned.onnx`` unless ``model``/``model_path`` is given. ``learned_decoder`` reuses a built
    classical stage (its memoised kernels) across frames of one camera.
    """
    from .learned import decode_learned
    from .learned import learned_decoder as build_decoder

    if depth_range_m is not None:
        check_depth_range(depth_range_m)  # before any work
    frame, quality, timings = _read_checked(frame_or_path, allow_test_pattern)
    camera, calibration = camera_for(frame, calibration_path, calibration_id)
    if model is None:
        if model_path is None:
            try:
                model_path, _ = select_model(None, lens=camera.lens_name, decoder="learned")
            except ModelError as exc:
                raise ModelError(f"{exc}; decode this frame with --decoder cnn or --decoder classical") from None
        model = Model(model_path, tile_px=tile_px, threads=threads, providers=providers)
        timings["load_model_s"] = model.load_s
        timings["warmup_s"] = model.warmup_s
    t0 = time.perf_counter()
    decoder = learned_decoder or build_decoder(model, camera, threads)
    result = decode_learned(model, decoder, frame, camera, overlap_px=overlap_px, progress=progress)
    timings["decode_s"] = time.perf_counter() - t0
    head = {"decoder": "learned", "model": model.describe(), "camera": camera.to_dict() | {"sha256": camera.sha256()},
            "calibration_id": camera.calibration_id, "calibration_note": None, "calibration_file": calibration}
    return result, _write_and_report(out_dir, result, frame, quality, timings, head, ply_step_px, depth_range_m,
                                     camera)
