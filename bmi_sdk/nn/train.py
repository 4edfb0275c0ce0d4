"""The training loop behind ``bmi train``: seeded, resumable, on a GPU when there is one.

Optimiser as in the paper (§4.1): Adam, β = (0.9, 0.99), initial learning rate
5e-4, batch 8; the learning rate follows a cosine from 5e-4 to 1e-6 over the
run's ``steps`` (the paper does not state its schedule). Losses: ``losses``.

The learned refinement (``refine`` set: ``bmi train --decoder learned``) trains the same network with the
classical decoder's channels appended to its input (``refine_data``) and a σ head (``losses.sigma_nll_loss``),
starting from the weights of a trained end-to-end model (``init_from``, the shipped ``default.onnx``): the
new input channels and the σ output start at zero, so step 0 reproduces that model and training only adds
what the evidence brings.

Reproducibility: weights are initialised from ``torch.manual_seed(seed)`` (then ``init_from``) and
the batch of step t is a pure function of (seed, t) (``PairCache.batch``), so a
run resumed from its checkpoint takes exactly the steps the uninterrupted run
would have. Checkpoints hold only tensors, numbers and strings and are read
with ``torch.load(weights_only=True)`` (no pickle of code); they are written
atomically every ``save_every`` steps, at the end, and on Ctrl-C.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from bmi_sdk.io_atomic import atomic_path, write_json
from bmi_sdk.model_io import INPUT_CHANNELS
from bmi_sdk.nn.data import STANDARD_SIGMA, CacheSpec, PairCache, build_cache, check_noise_range
from bmi_sdk.nn.losses import SIGMA_WEIGHT, SILOG_LAMBDA, sigma_nll_loss, total_loss
from bmi_sdk.nn.model import DualHeadMimoUNet, ModelConfig, preset_config
from bmi_sdk.nn.refine_data import RefinePairs, RefineSpec, build_refine_cache

CHECKPOINT = "checkpoint.pt"
LR_FINAL = 1e-6
TRAIN_BYTES_PER_PX = {"tiny": 2300, "small": 4700, "paper": 18000}
"""Peak memory of one training step per pixel of the batch (``--batch`` × ``--crop``²) by preset: the growth of peak
RSS from batch 1 (2 for tiny) to 5 (32) at crop 128, rounded up (2256, 4649 and 17802 bytes measured;
docs/benchmarks.md, "Training memory per batch pixel")."""


@dataclass(frozen=True)
class TrainConfig:
    preset: str = "tiny"
    steps: int = 6000
    batch_size: int = 8
    lr: float = 5e-4
    betas: tuple = (0.9, 0.99)
    sigma: float = STANDARD_SIGMA
    sigma_max: float | None = None  # set: each pair's σ is log-uniform over [sigma, sigma_max]
    silog_lambda: float = SILOG_LAMBDA
    seed: int = 0
    cache: CacheSpec = field(default_factory=CacheSpec)
    refine: RefineSpec | None = None  # set: the learned refinement (classical channels in, σ out)
    init_from: str | None = None      # an ONNX model whose weights start the run (``init_from_onnx``)
    warmup_steps: int = 0             # linear learning-rate warm-up (a warm-started refinement needs one)
    sigma_head_only: bool = False     # train the σ head alone on pairs its trunk never saw (``Trainer``)

    def __post_init__(self):
        check_noise_range(self.sigma, self.sigma_max)
        if self.sigma_head_only and (self.refine is None or self.init_from is None):
            raise ValueError("sigma_head_only recalibrates a trained refinement's 1σ: it needs refine and init_from")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["betas"] = list(self.betas)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        d = dict(d)
        d["betas"] = tuple(d["betas"])
        d["cache"] = CacheSpec(**d["cache"])
        if d.get("refine") is not None:
            d["refine"] = RefineSpec(**d["refine"])
        return cls(**d)


def default_device() -> torch.device:
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def learning_rate(config: TrainConfig, step: int) -> float:
    """Cosine decay from ``config.lr`` at step 0 to ``LR_FINAL`` at the last step, scaled up linearly over the
    first ``warmup_steps`` (Adam's first steps move every weight by ~lr whatever its gradient: on a warm-started
    network that undoes what it had learnt)."""
    t = step / max(config.steps - 1, 1)
    lr = LR_FINAL + 0.5 * (config.lr - LR_FINAL) * (1 + math.cos(math.pi * min(t, 1.0)))
    return lr * min(1.0, (step + 1) / config.warmup_steps) if config.warmup_steps else lr


def network_config(config: TrainConfig, extra_channels: int = 0) -> ModelConfig:
    """The network a run trains: its preset, plus ``extra_channels`` inputs and a σ head for a refinement."""
    base = preset_config(config.preset)
    if config.refine is None:
        return base
    return ModelConfig(**{**base.to_dict(), "extra_channels": extra_channels, "sigma_head": True})


def init_from_onnx(net: DualHeadMimoUNet, onnx_path: str | Path, input_stats: bool = False) -> int:
    """Copy the weights of an exported model (initializers ``net.<parameter>``) into ``net``; returns how many
    tensors were copied. Where ``net`` is wider, the extra input channels of the head start at zero and a σ head
    the exported model lacks outputs log 0.2, so ``net`` computes what the exported model does; a σ head the
    exported model has (a refinement warm-started from a refinement) keeps its trained weights. ``input_stats``:
    also copy the standardisation of the extra input channels (otherwise set from the run's own data)."""
    import onnx
    from onnx import numpy_helper

    weights = {t.name.removeprefix("net."): numpy_helper.to_array(t) for t in onnx.load(str(onnx_path)).graph.initializer}
    state = net.state_dict()
    # the exported graph keeps only the full-resolution AiF output: the coarse outputs' convolutions are
    # not in it and keep their seeded initialisation (they feed only the multi-scale training loss)
    # the refinement's input statistics are set from its own training data (``Trainer``), unless ``input_stats``
    missing = [k for k in state if k not in weights
               and not k.startswith(("image_out.0.", "image_out.1.", "extra_mean", "extra_std", "sigma_out."))]
    if not input_stats:
        weights = {k: v for k, v in weights.items() if k not in ("extra_mean", "extra_std")}
    elif "extra_mean" in state and "extra_mean" not in weights:
        raise ValueError(f"{onnx_path} has no input standardisation to keep: not a learned refinement")
    if missing:
        raise ValueError(f"{onnx_path} lacks {len(missing)} of the network's tensors (e.g. {missing[0]}): "
                         "another architecture")
    copied = 0
    with torch.no_grad():
        for name, target in state.items():
            if name not in weights:
                continue
            copied += 1
            src = torch.from_numpy(np.array(weights[name]))
            if src.shape == target.shape:
                target.copy_(src)
            elif name == "head.0.weight" and src.shape[1] < target.shape[1] and src.shape[0] == target.shape[0]:
                target.zero_()
                target[:, :src.shape[1]] = src
            else:
                raise ValueError(f"{onnx_path}: tensor {name} has shape {tuple(src.shape)}, "
                                 f"the network {tuple(target.shape)}")
    if "sigma_out.1.0.weight" in state and "sigma_out.1.0.weight" not in weights:  # a trained σ head is kept
        with torch.no_grad():
            state["sigma_out.1.0.weight"].zero_()
            state["sigma_out.1.0.bias"].fill_(math.log(0.2))
    return copied


class Trainer:
    """One run: model, optimiser, data; ``step()`` advances by one batch, ``save``/``load`` checkpoint it."""

    def __init__(self, config: TrainConfig, cache_dir: str | Path, device: torch.device | None = None):
        self.config = config
        self.device = device or default_device()
        self.data = PairCache(cache_dir) if config.refine is None else RefinePairs(cache_dir, config.refine)
        if self.data.spec != config.cache:
            raise ValueError(f"cache {cache_dir} holds {self.data.spec}, the run asks for {config.cache}")
        torch.manual_seed(config.seed)
        extra = self.data.extra_channels if config.refine is not None else 0
        self.net = DualHeadMimoUNet(network_config(config, extra))
        if config.init_from is not None:
            init_from_onnx(self.net, config.init_from, input_stats=config.sigma_head_only)
        if extra and not config.sigma_head_only:
            mean, std = self.data.feature_stats()
            self.net.extra_mean.copy_(torch.from_numpy(mean).reshape(1, -1, 1, 1))
            self.net.extra_std.copy_(torch.from_numpy(std).reshape(1, -1, 1, 1))
        if config.sigma_head_only:
            # a σ head fitted to the residuals of the pairs its trunk was trained on learns the training error,
            # which is smaller than the error on new scenes: trained alone on other pairs, it learns the latter.
            # Everything else, the input standardisation included, stays as the source model has it.
            for name, parameter in self.net.named_parameters():
                parameter.requires_grad_(name.startswith("sigma_out."))
        self.net.to(self.device)
        self.opt = torch.optim.Adam([p for p in self.net.parameters() if p.requires_grad], lr=config.lr,
                                    betas=config.betas)
        self.step_index = 0
        self.history: list[dict] = []

    def step(self) -> dict:
        """One optimiser step on the batch of ``step_index``; returns the loss terms."""
        c = self.config
        arrays = self.data.batch(c.seed, self.step_index, c.batch_size, c.sigma, c.sigma_max)
        x, aif, depth_m, valid = (torch.from_numpy(a).to(self.device) for a in arrays)
        for group in self.opt.param_groups:
            group["lr"] = learning_rate(c, self.step_index)
        self.net.train()
        aif_preds, depth_pred, *sigma_pred = self.net(x)
        loss, terms = total_loss(aif_preds, depth_pred, aif, depth_m, valid, c.silog_lambda)
        if sigma_pred:
            sigma_term = sigma_nll_loss(depth_pred, sigma_pred[0], depth_m, valid)
            loss = loss + SIGMA_WEIGHT * sigma_term
            terms["sigma_nll"] = float(sigma_term.detach())
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        self.step_index += 1
        record = {"step": self.step_index, "loss": float(loss.detach()), **terms}
        self.history.append(record)
        return record

    def save(self, path: str | Path) -> None:
        state = {"model": self.net.state_dict(), "optimizer": self.opt.state_dict(),
                 "step": self.step_index, "config": json.dumps(self.config.to_dict()),
                 "history": json.dumps(self.history)}
        with atomic_path(path, suffix=".pt") as tmp:
            torch.save(state, tmp)

    def load(self, path: str | Path) -> None:
        state = torch.load(path, map_location=self.device, weights_only=True)
        _refuse_another_config(path, state, self.config)
        self.net.load_state_dict(state["model"])
        self.opt.load_state_dict(state["optimizer"])
        self.step_index = int(state["step"])
        self.history = json.loads(state["history"])


def _refuse_another_config(path: Path, state: dict, config: TrainConfig) -> None:
    saved = TrainConfig.from_dict(json.loads(state["config"]))
    if saved != config:
        raise ValueError(f"{path} was trained with {saved}, not {config}; use another --out")


def check_resumable(checkpoint: Path, config: TrainConfig) -> None:
    """Refuse a checkpoint already in the run folder that another config trained, before the render cache is
    built (hours for a large one): re-running a command resumes it, a changed command needs another --out."""
    if checkpoint.exists():
        _refuse_another_config(checkpoint, torch.load(checkpoint, map_location="cpu", weights_only=True), config)


def load_weights(checkpoint: str | Path) -> tuple[DualHeadMimoUNet, TrainConfig]:
    """The network (eval mode, CPU) and config of a checkpoint."""
    state = torch.load(checkpoint, map_location="cpu", weights_only=True)
    config = TrainConfig.from_dict(json.loads(state["config"]))
    head_in = state["model"]["head.0.weight"].shape[1]
    net = DualHeadMimoUNet(network_config(config, max(head_in - INPUT_CHANNELS, 0)))
    net.load_state_dict(state["model"])
    return net.eval(), config


def check_sigma_head_source(config: TrainConfig) -> None:
    """Refuse, before any pair is rendered, a ``sigma_head_only`` run whose ``init_from`` is not a learned
    refinement (its manifest, verified): there would be no σ head and no input standardisation to keep."""
    if not config.sigma_head_only:
        return
    from bmi_sdk.model_manifest import verify_model

    if verify_model(config.init_from).get("decoder") != "learned":
        raise ValueError(f"--init-from {config.init_from} is not a learned refinement: --sigma-head-only has no "
                         "σ head to retrain")


def train(config: TrainConfig, out_dir: str | Path, cache_dir: str | Path, save_every: int = 250,
          progress: bool = True, device: torch.device | None = None, scheduler: str | None = None,
          workers: int = 1) -> Path:
    """Build the render cache if needed (on Dask with ``scheduler``: ``local:N`` / ``tcp://HOST:PORT``), and
    for a refinement its classical decodes (``workers`` processes), then train (resuming from ``out_dir``'s
    checkpoint); returns the checkpoint."""
    check_sigma_head_source(config)
    out_dir = Path(out_dir)
    ckpt = out_dir / CHECKPOINT
    check_resumable(ckpt, config)
    out_dir.mkdir(parents=True, exist_ok=True)
    build_cache(cache_dir, config.cache, progress=progress, scheduler=scheduler)
    if config.refine is not None:
        build_refine_cache(cache_dir, config.refine, workers=workers, progress=progress)
    trainer = Trainer(config, cache_dir, device)
    if ckpt.exists():
        trainer.load(ckpt)
    write_json(out_dir / "train_config.json", {**config.to_dict(), "device": str(trainer.device),
                                                "torch": torch.__version__})
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=config.steps, initial=trainer.step_index, desc=f"train {config.preset}", unit="step")
    t0, s0 = time.perf_counter(), trainer.step_index
    try:
        while trainer.step_index < config.steps:
            rec = trainer.step()
            rate = (trainer.step_index - s0) * config.batch_size / (time.perf_counter() - t0)
            if bar is not None:
                bar.update()
                bar.set_postfix(loss=f"{rec['loss']:.4f}", silog=f"{rec['silog']:.4f}",
                                l1=f"{rec['content']:.4f}", pairs_per_s=f"{rate:.1f}")
            if trainer.step_index % save_every == 0:
                trainer.save(ckpt)
    finally:  # Ctrl-C or an error: keep what was learnt
        trainer.save(ckpt)
        if bar is not None:
            bar.close()
        _write_log(out_dir, trainer, time.perf_counter() - t0, s0)
    return ckpt


def _write_log(out_dir: Path, trainer: Trainer, seconds: float, first_step: int) -> None:
    """train_log.json: loss history (means per 50 steps) and the wall time of this session."""
    h = trainer.history
    chunks = [h[i:i + 50] for i in range(0, len(h), 50)]
    curve = [{"step": c[-1]["step"], **{k: float(np.mean([r[k] for r in c])) for k in ("loss", "content", "fft", "silog")}}
             for c in chunks]
    log_path = out_dir / "train_log.json"
    sessions = json.loads(log_path.read_text())["sessions"] if log_path.exists() else []
    sessions.append({"from_step": first_step, "to_step": trainer.step_index, "seconds": round(seconds, 1),
                     "device": str(trainer.device), "threads": torch.get_num_threads()})
    write_json(log_path, {"sessions": sessions, "curve": curve})
