"""Loading a verified ONNX model into one onnxruntime session with one fixed tile shape.

The model's bytes are checked against its manifest (``bmi_sdk.model_manifest``)
before onnxruntime sees them. Session options are explicit: intra-op threads
(default: the machine's cores), one inter-op thread, sequential execution,
full graph optimisation, memory pattern and arena on (or the caller's own
``SessionOptions``). The execution provider is the one asked for, else the best
available (``choose_providers``: TensorRT, CUDA, CPU). The session is only ever
fed ``1 × C × tile × tile`` (C = 6 for the end-to-end network, more for the
learned refinement, as its manifest says; onnxruntime grows its arena for every
new input shape), and a warm-up run at load time pays the first-run allocation
and kernel selection outside the timed frame.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from ..memory_budget import check_allocation
from ..model_io import INPUT_NAME
from ..model_manifest import ModelError, model_decoder, verify_model

MODELS_DIR = Path(__file__).resolve().parents[1] / "models"
DEFAULT_MODEL = MODELS_DIR / "default.onnx"
LEARNED_MODEL = MODELS_DIR / "learned.onnx"
TILE_BYTES_PER_PX = 700  # onnxruntime's peak per tile pixel, packaged model: 754 B/px at 512, 670 at 1024 measured


PREFERRED_PROVIDERS = ("TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider")
"""Best first: the default is the first of these onnxruntime says it has."""


def _provider_name(name: str, available: list[str]) -> str:
    """onnxruntime's name for ``name``: exact (``CUDAExecutionProvider``) or short, any case (``cuda``)."""
    for full in available:
        if name.lower() in (full.lower(), full.lower().removesuffix("executionprovider")):
            return full
    raise ValueError(f"execution provider {name!r} is not available here; available: {', '.join(available)}")


def choose_providers(requested: str | list[str] | tuple[str, ...] | None = None) -> list[str]:
    """The providers for a session, best first, each checked against ``onnxruntime.get_available_providers()``.

    ``requested``: a name or a list of names (full or short: ``CUDAExecutionProvider`` or ``cuda``);
    None picks the best available in ``PREFERRED_PROVIDERS`` order. CPU is appended as the fallback
    for operators another provider lacks. An unavailable name is a ``ValueError`` naming the available ones.
    """
    import onnxruntime as ort

    available = list(ort.get_available_providers())
    if requested is None:
        chosen = [next(p for p in PREFERRED_PROVIDERS if p in available)]
    else:
        names = [requested] if isinstance(requested, str) else list(requested)
        if not names:
            raise ValueError(f"no execution provider named; available: {', '.join(available)}")
        chosen = [_provider_name(n, available) for n in names]
    if "CPUExecutionProvider" not in chosen:
        chosen.append("CPUExecutionProvider")
    return chosen


def session_options(threads: int | None = None, optimization: str = "all"):
    """onnxruntime SessionOptions with every knob that matters here set explicitly."""
    import onnxruntime as ort

    levels = {"none": ort.GraphOptimizationLevel.ORT_DISABLE_ALL, "basic": ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
              "extended": ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED,
              "all": ort.GraphOptimizationLevel.ORT_ENABLE_ALL}
    if optimization not in levels:
        raise ValueError(f"graph optimisation must be one of {sorted(levels)}, got {optimization!r}")
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = int(threads or os.cpu_count() or 1)
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = levels[optimization]
    opts.enable_mem_pattern = True
    opts.enable_cpu_mem_arena = True
    opts.log_severity_level = 3
    # idle intra-op threads sleep instead of spinning: a frame's next tile inputs are made on another thread while
    # the network runs (``pipeline.infer_raw``), and spinning workers took its core (0.1 CPU-s per 512² tile)
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return opts


class Model:
    """A verified model, its manifest and one onnxruntime session for ``tile_px`` × ``tile_px`` tiles.

    ``Model(path)`` raises ``ModelError`` for a missing, unknown (no manifest),
    corrupted (SHA-256 mismatch) or unreadable model, or one whose graph does
    not have the contract's input/outputs. A model exported with a fixed input
    size fixes ``tile_px`` to that size; asking for another one is an error.

    ``providers``: execution provider name(s) for ``choose_providers`` (default: the best available);
    ``provider`` is the one the session actually runs on. ``sess_options``: an
    ``onnxruntime.SessionOptions`` used as given instead of ``session_options(threads, optimization)``.
    ``read_fusion_weights=False`` leaves a learned refinement's fusion weights unread (``fusion_weights`` None).
    """

    def __init__(self, path: str | os.PathLike = DEFAULT_MODEL, *, tile_px: int | None = 512,
                 threads: int | None = None, optimization: str = "all", warmup: bool = True,
                 providers: str | list[str] | None = None, sess_options=None,
                 read_fusion_weights: bool = True):
        import onnxruntime as ort

        self.path = Path(path)
        if not self.path.is_file() and self.path == DEFAULT_MODEL:
            raise ModelError(f"no shipped model at {DEFAULT_MODEL} yet; pass --model PATH.onnx "
                             "(with its .manifest.json) or export one with bmi_sdk.nn")
        t0 = time.perf_counter()
        self.manifest = verify_model(self.path)
        chosen = choose_providers(providers)
        if sess_options is None:
            sess_options = session_options(threads, optimization)
        else:
            threads = sess_options.intra_op_num_threads or None
            optimization = "caller's SessionOptions"
        try:
            self.session = ort.InferenceSession(str(self.path), sess_options=sess_options, providers=chosen)
        except Exception as exc:  # onnxruntime raises its own exception types for unreadable graphs
            raise ModelError(f"onnxruntime cannot load {self.path}: {exc}") from exc
        inputs, outputs = self.session.get_inputs(), self.session.get_outputs()
        names_in, names_out = [i.name for i in inputs], [o.name for o in outputs]
        self.output_names = tuple(self.manifest["output_names"])
        self.input_channels = int(self.manifest["input_channels"])
        self.decoder = model_decoder(self.manifest)
        # a refit (bmi fit-fusion) reads the model without its weights, so that it can replace unreadable ones
        self.fusion_weights = model_fusion_weights(self.manifest, self.path.name) if read_fusion_weights else None
        if names_in != [INPUT_NAME] or sorted(names_out) != sorted(self.output_names):
            raise ModelError(f"{self.path.name}: graph has inputs {names_in} and outputs {names_out}; "
                             f"its manifest says {INPUT_NAME!r} → {list(self.output_names)}")
        shape = inputs[0].shape
        if len(shape) != 4 or shape[1] != self.input_channels:
            raise ModelError(f"{self.path.name}: input {INPUT_NAME!r} has shape {shape}, "
                             f"expected N×{self.input_channels}×H×W")
        fixed = [s for s in shape[2:] if isinstance(s, int)]
        multiple = int(self.manifest["size_multiple"])
        if fixed:
            if len(fixed) != 2 or fixed[0] != fixed[1]:
                raise ModelError(f"{self.path.name}: fixed input size {shape[2:]}; the runtime needs square tiles")
            if tile_px is not None and tile_px != fixed[0]:
                raise ModelError(f"{self.path.name} was exported for {fixed[0]}×{fixed[0]} tiles, not {tile_px}")
            tile_px = fixed[0]
        if tile_px is None or tile_px <= 0 or tile_px % multiple:
            raise ValueError(f"tile_px must be a positive multiple of {multiple}, got {tile_px}")
        check_allocation("--tile-px", tile_px, TILE_BYTES_PER_PX * tile_px * tile_px, "lower it (default 512)")
        self.tile_px = int(tile_px)
        self.threads = int(threads or os.cpu_count() or 1)
        self.optimization = optimization
        self.provider = self.session.get_providers()[0]
        self._batch_fixed = isinstance(shape[0], int)
        self.load_s = time.perf_counter() - t0
        self.warmup_s = 0.0
        if warmup:
            t1 = time.perf_counter()
            self.run(np.zeros((1, self.input_channels, self.tile_px, self.tile_px), np.float32))
            self.warmup_s = time.perf_counter() - t1

    @property
    def sha256(self) -> str:
        return self.manifest["sha256"]

    @property
    def receptive_field_px(self) -> int:
        return int(self.manifest["receptive_field_px"])

    @property
    def size_multiple(self) -> int:
        return int(self.manifest["size_multiple"])

    def run(self, x: np.ndarray) -> tuple[np.ndarray, ...]:
        """``1 × C × tile × tile`` float32 → (aif ``1 × 3 × tile × tile``, depth_m ``1 × 1 × tile × tile``
        [, depth_sigma_m ``1 × 1 × tile × tile`` for the learned refinement]), in the manifest's order."""
        expected = (1, self.input_channels, self.tile_px, self.tile_px)
        if x.shape != expected or x.dtype != np.float32:
            raise ValueError(f"the session runs one tile shape {expected} float32, got {x.shape} {x.dtype}")
        return tuple(self.session.run(list(self.output_names), {INPUT_NAME: x}))

    def describe(self) -> dict:
        return {"path": str(self.path), "sha256": self.sha256, "decoder": self.decoder, "preset": self.manifest["preset"],
                "lens": self.manifest["lens"], "psf_tensor_key": self.manifest["psf_tensor_key"],
                "calibration_id": self.manifest["calibration_id"], "receptive_field_px": self.receptive_field_px,
                "tile_px": self.tile_px, "threads": self.threads, "execution_provider": self.provider, "graph_optimization": self.optimization,
                "load_s": self.load_s, "warmup_s": self.warmup_s}


def model_fusion_weights(manifest: dict, name: str):
    """The ``decode.fusion.FusionWeights`` a learned refinement's depth is fused with its classical stage's by:
    its manifest's fitted ``fusion.weights`` (``bmi fit-fusion``), else the inverse-variance ones; None for an
    end-to-end model, which has no classical stage."""
    if model_decoder(manifest) != "learned":
        return None
    from ..decode.fusion import INVERSE_VARIANCE, FusionWeights

    fusion = manifest.get("fusion")
    if fusion is None:
        return INVERSE_VARIANCE
    try:
        return FusionWeights.from_dict(fusion["weights"] if isinstance(fusion, dict) else fusion)
    except (KeyError, ValueError) as exc:
        raise ModelError(f"model {name}: its manifest's fusion weights are unreadable ({exc})") from exc


def select_model(lens: str, decoder: str, models_dir: str | os.PathLike = MODELS_DIR,
                 preset: str | None = None) -> Path:
    """The packaged model file of ``decoder``'s kind (a manifest's ``decoder``: ``cnn``, the end-to-end network;
    ``learned``, the refinement of the classical decoder) trained for ``lens`` (a fisheye-baseline model must never
    decode a BMI frame) in ``models_dir``: ``default.onnx`` or ``learned.onnx`` when it is one of them, else the
    first by name. ``preset`` narrows the choice. Manifests are read, not hash-checked: ``Model`` checks the one
    chosen."""
    from ..model_manifest import read_manifest

    models_dir = Path(models_dir)
    candidates = []
    for onnx in sorted(models_dir.glob("*.onnx")):
        try:
            m = read_manifest(onnx)
        except ModelError:
            continue
        if m["lens"] == lens and model_decoder(m) == decoder and (preset is None or m["preset"] == preset):
            candidates.append(onnx)
    if not candidates:
        raise ModelError(f"no {decoder} model with a manifest in {models_dir} for lens {lens!r}"
                         + (f" and preset {preset!r}" if preset else ""))
    packaged = [onnx for onnx in candidates if onnx.name in (DEFAULT_MODEL.name, LEARNED_MODEL.name)]
    return (packaged or candidates)[0]


def count_macs(onnx_path: str | os.PathLike, tile_px: int) -> int:
    """Multiply-accumulates of one ``tile_px`` × ``tile_px`` tile in the graph's Conv, ConvTranspose, MatMul and Gemm nodes.

    Shapes come from ONNX shape inference with the input fixed to the tile;
    elementwise operators are not counted (they are memory-bound, not FLOPs
    the machine's peak refers to). Used to state achieved GFLOP/s.
    """
    import onnx
    from onnx import shape_inference

    m = onnx.load(str(onnx_path))
    dims = m.graph.input[0].type.tensor_type.shape.dim
    channels = dims[1].dim_value  # the graph's own input channels (6, or more for the learned refinement)
    for d, v in zip(dims, (1, channels, tile_px, tile_px)):
        d.Clear()
        d.dim_value = v
    m = shape_inference.infer_shapes(m)
    shapes = {vi.name: [d.dim_value for d in vi.type.tensor_type.shape.dim]
              for vi in list(m.graph.value_info) + list(m.graph.output) + list(m.graph.input)}
    shapes.update({t.name: list(t.dims) for t in m.graph.initializer})
    macs = 0
    for node in m.graph.node:
        if node.op_type in ("Conv", "ConvTranspose"):
            w = shapes.get(node.input[1])
            src = shapes.get(node.input[0]) if node.op_type == "ConvTranspose" else shapes.get(node.output[0])
            if not w or not src or 0 in src:
                continue
            # Conv: output elements × (C_in/groups · kh · kw); ConvTranspose (weight C_in × C_out/groups × kh × kw):
            # input elements × (C_out/groups · kh · kw). Both are prod(src) × prod(w[1:]).
            macs += int(np.prod(src)) * int(np.prod(w[1:]))
        elif node.op_type in ("MatMul", "Gemm"):
            a, out = shapes.get(node.input[0]), shapes.get(node.output[0])
            if a and out and 0 not in out:
                macs += int(np.prod(out)) * a[-1]
    return macs
