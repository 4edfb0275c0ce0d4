"""One decoder interface: a camera's raw frames in, one ``DecodedFrame`` each out.

    camera = BuiltCamera.for_frame(frame, calibration)   # the camera (lens, fitted errors, sensor, kernels)
    decoder = open_decoder(camera)                        # DEFAULT_DECODER; its model and kernels are built once
    decoded = decoder.decode(frame)                       # DecodedFrame: aif, depth_m, depth_sigma_m, valid, report

``bmi infer`` (``job.run_job``), batches and Dask workers (``batch.FrameDecoder``), ``bmi psf warm`` and the
benchmarks open their decoders here. The decoder's kind (``--decoder``) is read in one place,
``decoder_kind``/``open_decoder``; everything else holds a ``Decoder``.

Decoders (``DECODERS``, the registry):

* ``evidence`` (``DEFAULT_DECODER``): the classical stage's cost volume over every candidate read by a small
  network anchored to the pooled evidence, guided to every pixel by colour (``runtime.evidence``);
* ``learned``: the classical evidence of the camera's own kernels refined by a network that also reads the
  image, and fused with it (``runtime.learned``);
* ``classical``: that evidence alone, no network (``runtime.classical``);
* ``cnn``: the end-to-end network (``pipeline.infer_frame``).

Adding a decoder
----------------
Write one class and register it; nothing else changes (the CLI's ``--decoder`` choices, batches, Dask
workers and the report read the registry):

1. ``kind = "name"`` (what ``--decoder`` takes), ``title`` (how ``bmi infer`` names it), ``model_kind`` (the manifest ``decoder`` of the ONNX model it
   runs, or None for a decoder without a network) and ``takes_config`` (whether it reads a
   ``decode.ClassicalConfig``; a decoder that does not refuses one);
2. ``__init__(self, camera, model, config, options)``: build, once, what every frame reuses (a ``Model`` from
   ``load_model``, kernels from ``camera.psf_map``). ``model``: None, a path or a loaded ``Model``; ``options``:
   ``DecoderOptions``;
3. ``decode(self, frame, progress=False) -> DecodedFrame``: refuse a frame it cannot read (``check_decodable``),
   then decode it; ``DecodedFrame.report`` holds what ``report.json`` records of this decode;
4. ``head(self) -> dict``: the report's first entries (``{"decoder": kind, ...}``: model, camera, calibration id);
5. decorate the class with ``@register``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from ..built_camera import BuiltCamera
from ..model_manifest import ModelError


@dataclass
class DecodedFrame:
    """One decoded frame, whichever decoder read it: what the outputs are written from, and its report."""

    aif: np.ndarray                              # H × W × 3 float32 linear RGB, 0 outside the image circle
    depth_m: np.ndarray                          # H × W float32 range along each pixel's chief ray, NaN where invalid
    valid: np.ndarray                            # H × W bool
    depth_sigma_m: np.ndarray | None = None      # H × W float32 1σ of depth_m (None: the decoder reports none)
    report: dict = field(default_factory=dict)   # this decode's report.json entries (tiles, blocks, stats, timings)
    parts: dict = field(default_factory=dict)    # the decoder's intermediate reads, not written (e.g. "network")

    def summary(self) -> dict:
        return dict(self.report)


@dataclass(frozen=True)
class DecoderOptions:
    """How a decoder with a network runs it: tile size, threads, onnxruntime provider(s), tile overlap."""

    tile_px: int = 512
    threads: int | None = None                        # None: all cores
    providers: str | tuple[str, ...] | None = None   # None: the best available (``model.choose_providers``)
    overlap_px: int | None = None                     # None: the model's receptive field
    texture_exponent: str = "prior"                   # decode.classical.TEXTURE_EXPONENTS: the evidence and classical
    #                                                   decoders' texture model; the others take only "prior"


class Decoder(Protocol):
    """What every decoder is: built once for a camera, then fed that camera's frames."""

    kind: str
    camera: BuiltCamera

    def decode(self, frame, progress: bool = False) -> DecodedFrame: ...

    def head(self) -> dict: ...


class DecoderClass(Protocol):
    """A decoder class as the registry holds it: its class attributes and its constructor."""

    kind: str
    title: str
    model_kind: str | None
    takes_config: bool
    takes_texture_exponent: bool  # reads ``DecoderOptions.texture_exponent``; else refuses any but "prior"

    def __call__(self, camera: BuiltCamera, model, config, options: DecoderOptions) -> Decoder: ...


DECODERS: dict[str, DecoderClass] = {}
"""kind → decoder class (``register``), in the order ``--decoder`` lists them."""

DEFAULT_DECODER = "evidence"
"""The evidence network: it reads the camera's own evidence, so a calibration carries through without
retraining; on ``bmi eval`` it reads better than the classical decoder on every design-camera row and
within 10 % of it on a built camera, where the learned refinement, which also reads the image, reads σ 0.02
frames up to 1.5× as badly as the classical one (docs/results.md, "Evidence decoder")."""


def register(cls: Any) -> Any:
    """Add a decoder class to ``DECODERS`` under its ``kind`` (a class decorator)."""
    if cls.kind in DECODERS:
        raise ValueError(f"decoder {cls.kind!r} is registered twice")
    DECODERS[cls.kind] = cls
    return cls


def decoder_kind(kind: str | None = None, model=None) -> str:
    """The kind a decoder is opened as: ``kind`` if named; else the kind of ``model`` (a loaded ``Model`` or an
    ONNX path: its manifest's ``decoder``, the decoder that runs such a model); else ``DEFAULT_DECODER``."""
    if kind is not None:
        if kind not in DECODERS:
            raise ValueError(f"unknown decoder {kind!r}; one of {', '.join(DECODERS)}")
        return kind
    if model is None:
        return DEFAULT_DECODER
    from ..model_manifest import model_decoder, read_manifest
    from .model import Model

    if isinstance(model, Model):
        made_for = model.decoder
    else:
        if not os.path.isfile(model):
            raise ModelError(f"no model file at {model}")
        made_for = model_decoder(read_manifest(model))
    runs = [k for k, cls in DECODERS.items() if cls.model_kind == made_for]
    if not runs:
        raise ModelError(f"model {os.fspath(getattr(model, 'path', model))}: no decoder runs a {made_for!r} model")
    return runs[0]


def open_decoder(camera: BuiltCamera, kind: str | None = None, model=None, config=None,
                 options: DecoderOptions = DecoderOptions()) -> Decoder:
    """The decoder of ``kind`` (default: ``decoder_kind``) for ``camera``, built once: its model loaded (``model``:
    a path, a loaded ``Model``, or None for the packaged model of the camera's lens) and its kernels made.
    ``config``: a ``decode.ClassicalConfig`` for a decoder that takes one (refused by the others)."""
    cls = DECODERS[decoder_kind(kind, model)]
    if model is not None and cls.model_kind is None:
        raise ValueError(f"--model names a network; the {cls.kind} decoder uses none (drop --model or choose "
                         f"another --decoder)")
    if options.providers is not None and cls.model_kind is None:
        raise ValueError(f"--provider picks the network's onnxruntime provider; the {cls.kind} decoder runs none "
                         f"(drop --provider or choose another --decoder)")
    if config is not None and not cls.takes_config:
        raise ValueError(f"the {cls.kind} decoder takes no classical decoder options (a learned refinement decodes "
                         "with the knobs of its manifest)")
    return cls(camera, model, config, options)


def load_model(model, camera: BuiltCamera, kind: str, options: DecoderOptions):
    """``model`` as a loaded ``Model`` for the ``kind`` decoder (a decoder with a network runs models whose manifest
    names its own kind): itself, the file it names, or (None) the packaged model of that kind for the camera's lens
    (``packaged_model``)."""
    from .model import Model

    if model is None:
        model = packaged_model(camera, kind)
    if not isinstance(model, Model):
        providers = list(options.providers) if isinstance(options.providers, tuple) else options.providers
        model = Model(model, tile_px=options.tile_px, threads=options.threads, providers=providers)
    if model.decoder != kind:
        raise ValueError(f"model {model.path.name} is a {model.decoder} model; the {kind} decoder runs a "
                         f"{kind} model")
    return model


def packaged_model(camera: BuiltCamera, kind: str):
    """The packaged model of the ``kind`` decoder for the camera's lens (``model.select_model``), or a
    ``ModelError`` that names the other decoders when none ships."""
    from .model import select_model

    try:
        return select_model(lens=camera.lens_name, decoder=kind)
    except ModelError as exc:
        others = ", ".join(f"--decoder {k}" for k in DECODERS if k != kind and _reads_lens(k, camera.lens_name))
        raise ModelError(f"{exc}; decode this frame with {others}") from None


def _reads_lens(kind: str, lens_name: str) -> bool:
    """Whether the ``kind`` decoder can read a frame of ``lens_name`` as shipped: it needs no model, or one ships."""
    from .model import select_model

    model_kind = DECODERS[kind].model_kind
    if model_kind is None:
        return True
    try:
        select_model(lens=lens_name, decoder=model_kind)
    except ModelError:
        return False
    return True


def camera_head(camera: BuiltCamera) -> dict:
    """The report's account of a camera: lens, errors, geometry, calibration id and its SHA-256."""
    return camera.to_dict() | {"sha256": camera.sha256()}


def texture_exponent_refusal(kind: str, texture_exponent: str) -> str | None:
    """Why the ``kind`` decoder cannot read with ``texture_exponent`` (a texture model other than the prior's for a
    decoder whose network holds its own, ``takes_texture_exponent`` False), or None when it can."""
    if texture_exponent == "prior" or DECODERS[kind].takes_texture_exponent:
        return None
    takers = ", ".join(k for k, cls in DECODERS.items() if cls.takes_texture_exponent)
    return f"the {kind} decoder reads with its model's own texture model (only 'prior'); the {takers} decoders take it"


def refuse_texture_exponent(kind: str, texture_exponent: str) -> None:
    """Raise ``ValueError`` with ``texture_exponent_refusal``'s reason, if it has one."""
    reason = texture_exponent_refusal(kind, texture_exponent)
    if reason is not None:
        raise ValueError(f"texture exponent {texture_exponent!r}: {reason}")


@register
class LearnedDecoder:
    """The classical stage over the camera's kernels with its model's knobs, then the refinement network, fused."""

    kind = "learned"
    title = "learned refinement"
    model_kind: str | None = "learned"
    takes_config = False
    takes_texture_exponent = False

    def __init__(self, camera: BuiltCamera, model, config, options: DecoderOptions):
        from .learned import learned_decoder

        refuse_texture_exponent(self.kind, options.texture_exponent)
        self.camera, self.options = camera, options
        self.model = load_model(model, camera, self.kind, options)
        self.stage = learned_decoder(self.model, camera, options.threads)

    def decode(self, frame, progress: bool = False) -> DecodedFrame:
        from .learned import decode_learned

        return decode_learned(self.model, self.stage, frame, self.camera, overlap_px=self.options.overlap_px,
                              progress=progress)

    def head(self) -> dict:
        return {"decoder": self.kind, "model": self.model.describe(), "camera": camera_head(self.camera),
                "calibration_id": self.camera.calibration_id}


@register
class NetworkDecoder:
    """The end-to-end network, tile by tile (``pipeline.infer_frame``); no depth 1σ."""

    kind = "cnn"
    title = "end-to-end network"
    model_kind: str | None = "cnn"
    takes_config = False
    takes_texture_exponent = False

    def __init__(self, camera: BuiltCamera, model, config, options: DecoderOptions):
        refuse_texture_exponent(self.kind, options.texture_exponent)
        self.camera, self.options = camera, options
        self.model = load_model(model, camera, self.kind, options)

    def decode(self, frame, progress: bool = False) -> DecodedFrame:
        from .pipeline import infer_frame

        result = infer_frame(self.model, frame, overlap_px=self.options.overlap_px, progress=progress)
        return DecodedFrame(result.aif, result.depth_m, result.valid, None, result.summary(), {"network": result})

    def head(self) -> dict:
        return {"decoder": self.kind, "model": self.model.describe(),
                "calibration_id": self.model.manifest["calibration_id"]}


@register
class ClassicalDecoderKind:
    """The evidence of the camera's own kernels, no network (``runtime.classical``); with a depth 1σ."""

    kind = "classical"
    title = "classical decoder"
    model_kind: str | None = None
    takes_config = True
    takes_texture_exponent = True

    def __init__(self, camera: BuiltCamera, model, config, options: DecoderOptions):
        from dataclasses import replace

        from ..decode import ClassicalConfig
        from ..decode.classical import with_texture_exponent
        from .classical import classical_decoder

        config = with_texture_exponent(config or ClassicalConfig(), options.texture_exponent)
        if options.threads is not None and config.threads is None:  # e.g. a Dask worker's own thread count
            config = replace(config, threads=options.threads)
        self.camera, self.options = camera, options
        self.model = None
        self.stage = classical_decoder(camera, config)

    def decode(self, frame, progress: bool = False) -> DecodedFrame:
        from .classical import decode_frame

        return decode_frame(self.stage, frame, self.camera, progress=progress)

    def head(self) -> dict:
        return {"decoder": self.kind, "camera": camera_head(self.camera), "calibration_id": self.camera.calibration_id}


@register
class EvidenceDecoder:
    """The camera's own evidence volume read by a small network, guided to every pixel (``runtime.evidence``);
    with a depth 1σ from the network's posterior."""

    kind = "evidence"
    title = "evidence network"
    model_kind: str | None = "evidence"
    takes_config = False
    takes_texture_exponent = True

    def __init__(self, camera: BuiltCamera, model, config, options: DecoderOptions):
        from .evidence import EvidenceNetwork, evidence_stage

        self.camera, self.options = camera, options
        if model is None:
            model = packaged_model(camera, self.kind)
        self.model = EvidenceNetwork(getattr(model, "path", model), threads=options.threads,
                                     providers=options.providers)
        self.stage = evidence_stage(self.model, camera, options.threads, options.texture_exponent)

    def decode(self, frame, progress: bool = False) -> DecodedFrame:
        from .evidence import decode_evidence

        return decode_evidence(self.model, self.stage, frame, self.camera, progress=progress)

    def head(self) -> dict:
        return {"decoder": self.kind, "model": self.model.describe(), "camera": camera_head(self.camera),
                "calibration_id": self.camera.calibration_id}
