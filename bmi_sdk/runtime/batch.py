"""Many raw frames → one output folder each (``OUT/<frame stem>/``), in this process or on Dask workers.

Each frame goes through the runtime's own per-frame job (``job.run_job``), so a frame decoded here is
decoded exactly as ``bmi infer FRAME`` decodes it. What a batch adds is that every process (this one, or
each Dask worker) loads a model once and keeps it for all its frames (``FrameDecoder``), one progress bar
for the whole batch, and a per-frame failure that is reported instead of ending the batch.

Frames are passed to workers by path, never as pixels: on a cluster the frames and ``OUT`` must be on a
filesystem every worker sees (docs/scale-out.md).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Sequence
from urllib.parse import urlsplit

FRAME_SUFFIX = ".dng"


def _dngs_in(folder: Path, what: str) -> list[Path]:
    if not folder.is_dir():
        raise FileNotFoundError(f"{what}: no folder {folder}")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() == FRAME_SUFFIX and p.is_file())
    if not files:
        raise FileNotFoundError(f"{what}: folder {folder} holds no {FRAME_SUFFIX} frames")
    return files


def frame_paths(sources: Sequence[str | os.PathLike]) -> list[Path]:
    """The frames named by ``sources``: DNG files, folders of DNGs, or ``replay://FOLDER`` (file-name order,
    as a replay camera plays them). Missing files, empty folders and endless replays are refused."""
    out: list[Path] = []
    for source in sources:
        text = str(source)
        if text.startswith("replay://"):
            parts = urlsplit(text)
            if parts.query:
                raise ValueError(f"{text}: a batch decodes each recorded frame once; drop ?{parts.query}")
            out += _dngs_in(Path(parts.netloc + parts.path), text)
        elif Path(text).is_dir():
            out += _dngs_in(Path(text), text)
        elif Path(text).is_file():
            out.append(Path(text))
        else:
            raise FileNotFoundError(f"no raw frame {text}")
    return out


def is_batch(sources: Sequence[str | os.PathLike]) -> bool:
    """True when ``sources`` name several frames, a folder or a replay (outputs go to ``OUT/<stem>/``);
    one file keeps ``bmi infer``'s single-frame layout (outputs directly in ``OUT``)."""
    return len(sources) != 1 or str(sources[0]).startswith("replay://") or Path(sources[0]).is_dir()


def plan_outputs(sources: Sequence[str | os.PathLike], out_dir: str | os.PathLike) -> list[tuple[Path, Path]]:
    """(frame, its output folder) for every frame: ``out_dir/<stem>`` for a batch, ``out_dir`` for one file.
    Two frames with one stem would overwrite each other's outputs, so that is refused."""
    frames = frame_paths(sources)
    out_dir = Path(out_dir)
    if not is_batch(sources):
        return [(frames[0], out_dir)]
    seen: dict[str, Path] = {}
    for frame in frames:
        if frame.stem in seen:
            raise ValueError(f"{seen[frame.stem]} and {frame} would both write {out_dir / frame.stem}; "
                             "rename one or decode them in separate runs")
        seen[frame.stem] = frame
    return [(frame, out_dir / frame.stem) for frame in frames]


@dataclass(frozen=True)
class DecodeOptions:
    """The ``run_job`` options every frame of a batch shares (``bmi infer``'s flags)."""

    model_path: str | None = None
    calibration_id: str | None = None
    calibration_path: str | None = None
    tile_px: int = 512
    threads: int | None = None
    overlap_px: int | None = None
    ply_step_px: int = 1
    decoder: str = "cnn"
    classical_config: object = None        # decode.ClassicalConfig for decoder "classical"
    overwrite: bool = False
    allow_test_pattern: bool = False
    providers: str | tuple[str, ...] | None = None   # onnxruntime execution provider(s); None: the best available
    depth_range_m: tuple[float, float] | None = None  # fixed depth_preview.png colours (near, far), metres


@dataclass
class FrameDecoder:
    """What one process keeps between frames: the models it has loaded (usually one).

    A model is chosen per frame by ``job.load_model_for`` from the model path, the calibration in use
    (the calibration file's id, else ``calibration_id``, else the frame's own) and the frame's lens; the
    decoder loads each distinct choice once and hands it to ``run_job``.
    """

    options: DecodeOptions
    models: dict = field(default_factory=dict)
    classical: dict = field(default_factory=dict)   # camera SHA-256 → decode.ClassicalDecoder (its kernels)
    learned: dict = field(default_factory=dict)     # (model path, camera SHA-256) → (Model, its classical stage)
    _calibration_file_id: str | None = field(default=None, init=False)

    def _calibration_in_use(self, frame) -> str | None:
        o = self.options
        if o.calibration_path is not None:
            if self._calibration_file_id is None:
                from calibration.io import load_calibration

                self._calibration_file_id = load_calibration(o.calibration_path).id
            return self._calibration_file_id
        return o.calibration_id or getattr(frame, "calibration_id", None)

    def model_for(self, frame):
        """(Model, note) for ``frame``: loaded on first use, then reused."""
        from .job import load_model_for
        from .pipeline import frame_lens_name

        o = self.options
        calibration_id = self._calibration_in_use(frame)
        key = (o.model_path, calibration_id, frame_lens_name(frame))
        if key not in self.models:
            self.models[key] = load_model_for(frame, o.model_path, calibration_id, o.tile_px, o.threads,
                                              o.providers)
        return self.models[key]

    def decode(self, frame_path: str | os.PathLike, out_dir: str | os.PathLike) -> dict:
        """Decode one frame into ``out_dir``; returns a summary (a failure with its reason instead of raising,
        for the errors ``bmi`` reports as clear messages: bad frames, models, calibrations, files)."""
        from devices import load_raw

        from .job import run_job

        o = self.options
        t0 = time.perf_counter()
        summary = {"frame": str(frame_path), "out": str(out_dir), "pid": os.getpid()}
        try:
            frame = load_raw(frame_path)
            if o.decoder == "classical":
                result, report = run_job(frame, out_dir, decoder="classical", calibration_id=o.calibration_id,
                                         calibration_path=o.calibration_path, ply_step_px=o.ply_step_px,
                                         overwrite=o.overwrite, allow_test_pattern=o.allow_test_pattern,
                                         classical_decoder=self.classical_decoder_for(frame),
                                         input_path=frame_path, providers=o.providers,
                                         depth_range_m=o.depth_range_m)
                return {**summary, "ok": True, "calibration_note": None, "decoder": "classical",
                        "camera_sha256": report["camera"]["sha256"], "blocks_run": report["blocks_run"],
                        "seconds": time.perf_counter() - t0}
            if o.decoder == "learned":
                model, stage = self.learned_for(frame)
                result, report = run_job(frame, out_dir, decoder="learned", model=model, learned_decoder=stage,
                                         calibration_id=o.calibration_id, calibration_path=o.calibration_path,
                                         overlap_px=o.overlap_px, ply_step_px=o.ply_step_px, overwrite=o.overwrite,
                                         allow_test_pattern=o.allow_test_pattern, input_path=frame_path,
                                         depth_range_m=o.depth_range_m)
                return {**summary, "ok": True, "calibration_note": None, "decoder": "learned",
                        "model_sha256": report["model"]["sha256"], "camera_sha256": report["camera"]["sha256"],
                        "tiles_run": result.network.tiles_run, "seconds": time.perf_counter() - t0}
            model, note = self.model_for(frame)
            result, report = run_job(frame, out_dir, model=model, calibration_id=o.calibration_id,
                                     calibration_path=o.calibration_path, overlap_px=o.overlap_px,
                                     ply_step_px=o.ply_step_px, overwrite=o.overwrite,
                                     allow_test_pattern=o.allow_test_pattern, input_path=frame_path,
                                     depth_range_m=o.depth_range_m)
        except (ValueError, FileNotFoundError, OSError) as exc:
            return {**summary, "ok": False, "error": f"{type(exc).__name__}: {exc}",
                    "seconds": time.perf_counter() - t0}
        return {**summary, "ok": True, "calibration_note": note, "decoder": "cnn",
                "model_sha256": report["model"]["sha256"], "tiles_run": result.tiles_run,
                "seconds": time.perf_counter() - t0}

    def classical_decoder_for(self, frame):
        """The classical decoder of the camera that took ``frame``: built once per camera, then reused."""
        from ..decode import ClassicalConfig
        from .classical import classical_decoder
        from .job import camera_for

        o = self.options
        camera, _ = camera_for(frame, o.calibration_path, o.calibration_id)
        key = camera.sha256()
        if key not in self.classical:
            config = o.classical_config or ClassicalConfig()
            if o.threads is not None and config.threads is None:  # a Dask worker's own thread count
                config = replace(config, threads=o.threads)
            self.classical[key] = classical_decoder(camera, config)
        return self.classical[key]


    def learned_for(self, frame):
        """(Model, classical stage) of the learned refinement for the camera that took ``frame``: built once per
        (model, camera), then reused."""
        from .job import camera_for
        from .learned import learned_decoder
        from .model import Model, select_model

        o = self.options
        camera, _ = camera_for(frame, o.calibration_path, o.calibration_id)
        path = o.model_path or select_model(None, lens=camera.lens_name, decoder="learned")[0]
        key = (str(path), camera.sha256())
        if key not in self.learned:
            model = Model(path, tile_px=o.tile_px, threads=o.threads, providers=o.providers)
            self.learned[key] = (model, learned_decoder(model, camera, o.threads))
        return self.learned[key]


def _decode(decoder: FrameDecoder, job: tuple[Path, Path]) -> dict:
    return decoder.decode(*job)


@dataclass(frozen=True)
class _DecoderFactory:
    """Builds a process's ``FrameDecoder`` (picklable, so a Dask worker plugin can build one per worker).
    Without explicit ``threads`` a worker's onnxruntime session gets the worker's own thread count."""

    options: DecodeOptions

    def __call__(self) -> FrameDecoder:
        options = self.options
        if options.threads is None:
            try:
                from distributed import get_worker

                options = replace(options, threads=get_worker().state.nthreads)
            except (ImportError, ValueError):  # not on a Dask worker: the runtime's default (all cores)
                pass
        return FrameDecoder(options)


def run_batch(jobs: Sequence[tuple[Path, Path]], options: DecodeOptions = DecodeOptions(), *, client=None,
              progress: bool = True) -> list[dict]:
    """Decode every (frame, output folder) of ``jobs`` (``plan_outputs``) with one progress bar; returns the
    per-frame summaries in ``jobs`` order. ``client``: a Dask client (``scaleout.open_client``), or None to
    decode here, one frame after another, with one model load."""
    from ..scaleout import fan_out

    return fan_out(_decode, list(jobs), client=client, state=_DecoderFactory(options), desc="decoding frames",
                   unit="frame", progress=progress)
