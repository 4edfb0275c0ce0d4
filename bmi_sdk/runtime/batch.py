"""Many raw frames → one output folder each (``OUT/<frame stem>/``), in this process or on Dask workers.

Each frame goes through the runtime's own per-frame job (``job.run_job``), so a frame decoded here is
decoded exactly as ``bmi infer FRAME`` decodes it. What a batch adds is that every process (this one, or
each Dask worker) reads the calibration once and opens one decoder per camera (its model and kernels) for all
its frames (``FrameDecoder``), one progress bar for the whole batch, and a per-frame failure that is reported
instead of ending the batch.

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
    calibration_path: str | None = None
    tile_px: int = 512
    threads: int | None = None
    overlap_px: int | None = None
    ply_step_px: int = 1
    decoder: str | None = None             # a kind of ``decoders.DECODERS``; None: the model's kind, else the default
    classical_config: object = None        # decode.ClassicalConfig, for a decoder that takes one
    overwrite: bool = False
    allow_test_pattern: bool = False
    providers: str | tuple[str, ...] | None = None   # onnxruntime execution provider(s); None: the best available
    depth_range_m: tuple[float, float] | None = None  # fixed depth_preview.png colours (near, far), metres
    texture_exponent: str = "prior"        # decode.classical.TEXTURE_EXPONENTS (the evidence and classical decoders)


@dataclass
class FrameDecoder:
    """What one process keeps between frames: the calibration, read once, and one opened decoder per camera.

    Each frame's camera is built from the frame (its lens and sensor) and the loaded calibration
    (``job.camera_for``); the decoder of that camera (its model loaded, its kernels made) is opened on first use
    (``decoders.open_decoder``) and handed to ``run_job`` for every later frame of the same camera.
    """

    options: DecodeOptions
    decoders: dict = field(default_factory=dict)   # camera SHA-256 → opened Decoder
    _calibration: object = field(default=None, init=False)

    def calibration(self):
        """The batch's ``calibration.io.Calibration`` (None without one), read and validated on first use."""
        if self._calibration is None and self.options.calibration_path is not None:
            from .job import load_calibration

            self._calibration = load_calibration(self.options.calibration_path)
        return self._calibration

    def decoder_for(self, frame):
        """The opened decoder of the camera that took ``frame``: opened on first use, then reused."""
        from .decoders import DecoderOptions, open_decoder
        from .job import camera_for

        o = self.options
        camera, _ = camera_for(frame, self.calibration())
        key = camera.sha256()
        if key not in self.decoders:
            self.decoders[key] = open_decoder(camera, o.decoder, o.model_path, o.classical_config,
                                              DecoderOptions(o.tile_px, o.threads, o.providers, o.overlap_px,
                                                             o.texture_exponent))
        return self.decoders[key]

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
            _, report = run_job(frame, out_dir, decoder=self.decoder_for(frame), calibration=self.calibration(),
                                ply_step_px=o.ply_step_px, overwrite=o.overwrite,
                                allow_test_pattern=o.allow_test_pattern, input_path=frame_path,
                                depth_range_m=o.depth_range_m)
        except (ValueError, FileNotFoundError, OSError) as exc:
            return {**summary, "ok": False, "error": f"{type(exc).__name__}: {exc}",
                    "seconds": time.perf_counter() - t0}
        return {**summary, "ok": True, "decoder": report["decoder"],
                "model_sha256": report["model"]["sha256"] if "model" in report else None,
                "camera_sha256": report["camera"]["sha256"] if "camera" in report else None,
                "tiles_run": report.get("tiles_run"), "blocks_run": report.get("blocks_run"),
                "seconds": time.perf_counter() - t0}


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
