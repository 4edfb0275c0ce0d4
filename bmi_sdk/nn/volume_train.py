"""Training and export of the evidence decoder's network (``volume_net``) on ``volume_data`` pairs.

Loss per valid window (a scene depth in its cell, ``decode.volume.grid_targets``):

* cross-entropy of softmax(logits) against the target spread over its two neighbouring candidates in 1/d
  (linear weights): the posterior learns where the evidence misleads;
* L1 of log depth between the posterior mean and the target: the read itself;
* the Gaussian negative log-likelihood of the target under (posterior mean, reported σ), with the posterior
  spread detached, so it fits only the σ scale (``VolumeNet.log_sigma_scale``) and leaves the logits to the
  two terms above.

Export: ``VolumeDecoderGraph`` to ONNX (legacy exporter, dynamic batch, rows and columns), checked against
torch on a held-out pair, with a manifest naming the decoder kind ``evidence``, the candidates, the lens and
the classical knobs the volume was made with.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from bmi_sdk.lenses import DEFAULT_LENS
from bmi_sdk.nn.volume_data import VolumePairs
from bmi_sdk.nn.volume_net import VolumeDecoderGraph, VolumeNet, VolumeNetConfig, posterior_torch, reported_sigma

CE_WEIGHT, L1_WEIGHT, NLL_WEIGHT = 1.0, 4.0, 0.1


def two_hot(target_inv: torch.Tensor, inv_depth_per_m: torch.Tensor) -> torch.Tensor:
    """(N, D, R, C) weights of the target 1/d (N, R, C) on its two neighbouring candidates (linear in 1/d);
    targets beyond the candidates go to the end one."""
    x = inv_depth_per_m
    order = torch.argsort(x)
    xs = x[order]
    t = target_inv.clamp(float(xs[0]), float(xs[-1]))
    hi = torch.searchsorted(xs, t.contiguous()).clamp(1, len(xs) - 1)
    lo = hi - 1
    w_hi = ((t - xs[lo]) / (xs[hi] - xs[lo])).clamp(0, 1)
    out = torch.zeros(target_inv.shape[0], len(xs), *target_inv.shape[1:], device=target_inv.device)
    out.scatter_(1, order[lo].unsqueeze(1), (1 - w_hi).unsqueeze(1))
    out.scatter_add_(1, order[hi].unsqueeze(1), w_hi.unsqueeze(1))
    return out


def losses(net: VolumeNet, batch: dict, inv_depth_per_m: torch.Tensor) -> dict:
    """The three loss terms (module doc) over a batch's valid windows, and their weighted sum."""
    logits = net(batch["volume"], batch["guide"])
    target = batch["target"]
    ok = torch.isfinite(target) & (batch["guide"][:, 3] > 0.5)
    t = torch.where(ok, target, torch.ones_like(target))
    ce = -(two_hot(t, inv_depth_per_m) * F.log_softmax(logits, dim=1)).sum(dim=1)
    mean, std = posterior_torch(logits, inv_depth_per_m)
    l1 = (torch.log(mean.clamp_min(1e-4)) - torch.log(t)).abs()
    sigma = reported_sigma(net, std.detach())
    nll = 0.5 * ((mean.detach() - t) / sigma) ** 2 + torch.log(sigma)
    n = ok.sum().clamp_min(1)
    terms = {"ce": (ce * ok).sum() / n, "l1_log": (l1 * ok).sum() / n, "nll": (nll * ok).sum() / n}
    terms["total"] = CE_WEIGHT * terms["ce"] + L1_WEIGHT * terms["l1_log"] + NLL_WEIGHT * terms["nll"]
    return terms


def evaluate(net: VolumeNet, pairs: VolumePairs, device: str) -> dict:
    """AbsRel of 1/d at the windows, the network's and the untrained anchor's (the pooled evidence), and the
    std of z = error / σ over every valid window of ``pairs`` (whole grids, cropped to a multiple of 4)."""
    inv = torch.as_tensor(pairs.inv_depth_per_m, device=device)
    rows, cols = pairs.arrays["target"].shape[1:]
    r4, c4 = rows // 4 * 4, cols // 4 * 4
    errs, anchor_errs, zs = [], [], []
    net.eval()
    with torch.no_grad():
        for start in range(0, len(pairs), 32):
            sl = slice(start, start + 32)
            vol = torch.as_tensor(pairs.arrays["volume"][sl, ..., :r4, :c4].astype(np.float32), device=device)
            guide = torch.as_tensor(pairs.arrays["guide"][sl, :, :r4, :c4].astype(np.float32), device=device)
            target = torch.as_tensor(pairs.arrays["target"][sl, :r4, :c4], device=device)
            ok = torch.isfinite(target) & (guide[:, 3] > 0.5)
            logits = net(vol, guide)
            mean, std = posterior_torch(logits, inv)
            anchor, _ = posterior_torch(-vol[:, 0], inv)
            sigma = reported_sigma(net, std)
            depth, true = 1 / mean[ok], 1 / target[ok]
            errs.append(((depth - true).abs() / true).cpu())
            anchor_errs.append(((1 / anchor[ok] - true).abs() / true).cpu())
            zs.append(((mean[ok] - target[ok]) / sigma[ok]).cpu())
    net.train()
    z = torch.cat(zs)
    return {"absrel": float(torch.cat(errs).mean()), "anchor_absrel": float(torch.cat(anchor_errs).mean()),
            "z_std": float(z.std()), "windows": int(z.numel())}


SCALARS = ("log_anchor", "log_sigma_scale", "log_sigma_floor")
"""The network's three scalars: the anchor's temperature and the σ scale and floor."""


def train(train_dirs, val_dirs, steps: int, batch_size: int = 16, crop: int = 16, lr: float = 2e-3,
          width: int = 8, seed: int = 0, device: str = "cpu", log_every: int = 100, init: str | None = None,
          scalars_only: bool = False) -> tuple[VolumeNet, dict]:
    """Train a ``VolumeNet`` (optionally from ``init``'s state dict), then fit its σ's scale on the held-out pairs
    (``calibrate_sigma``); returns it and its held-out metrics.
    ``scalars_only``: fit only ``SCALARS`` (the residual stays zero): the pooled evidence's own read, with its
    posterior's temperature and σ fitted, which few pairs determine well."""
    torch.manual_seed(seed)
    pairs = VolumePairs(train_dirs)
    val = VolumePairs(val_dirs)
    inv = torch.as_tensor(pairs.inv_depth_per_m, device=device)
    net = VolumeNet(VolumeNetConfig(candidates=len(pairs.inv_depth_per_m), width=width)).to(device)
    if init:
        net.load_state_dict(torch.load(init, map_location=device))
    params = [p for name, p in net.named_parameters() if not scalars_only or name in SCALARS]
    opt = torch.optim.AdamW(params, lr=lr, weight_decay=0.0 if scalars_only else 1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=steps, pct_start=0.1)
    rng = np.random.default_rng(seed)
    log = {"before": evaluate(net, val, device), "steps": []}
    t0 = time.time()
    for step in range(steps):
        b = {k: torch.as_tensor(v, device=device) for k, v in pairs.batch(rng, batch_size, crop).items()}
        terms = losses(net, b, inv)
        opt.zero_grad()
        terms["total"].backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        opt.step()
        sched.step()
        if (step + 1) % log_every == 0 or step + 1 == steps:
            row = {"step": step + 1, "s": round(time.time() - t0, 1), **{k: float(v.detach()) for k, v in terms.items()}}
            log["steps"].append(row)
            print(json.dumps(row), flush=True)
    log["after_training"] = evaluate(net, val, device)
    log["sigma_factor"] = calibrate_sigma(net, val, device)
    log["after"] = evaluate(net, val, device)
    return net, log


def export(net: VolumeNet, inv_depth_per_m, path: str | Path, sample: dict | None = None) -> Path:
    """Write the network as ONNX (``VolumeDecoderGraph``; dynamic N, R, C), checked against torch on ``sample``
    (volume, guide arrays) or a random grid when none is given; returns the path."""
    import onnxruntime as ort

    graph = VolumeDecoderGraph(net.cpu().eval(), inv_depth_per_m)
    d = len(inv_depth_per_m)
    if sample is None:
        gen = np.random.default_rng(0)
        sample = {"volume": gen.uniform(0, 20, (1, 2, d, 8, 12)).astype(np.float32),
                  "guide": np.concatenate([gen.normal(0, 0.3, (1, 3, 8, 12)), np.ones((1, 1, 8, 12))],
                                          axis=1).astype(np.float32)}
    vol, guide = torch.as_tensor(sample["volume"]), torch.as_tensor(sample["guide"])
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp.onnx")
    dyn = {0: "n", 3: "rows", 4: "cols"}
    torch.onnx.export(graph, (vol, guide), str(tmp), input_names=["volume", "guide"],
                      output_names=["inv_depth", "sigma_inv", "logits"], opset_version=17, dynamo=False,
                      dynamic_axes={"volume": dyn, "guide": {0: "n", 2: "rows", 3: "cols"},
                                    "inv_depth": {0: "n", 1: "rows", 2: "cols"},
                                    "sigma_inv": {0: "n", 1: "rows", 2: "cols"},
                                    "logits": {0: "n", 2: "rows", 3: "cols"}})
    session = ort.InferenceSession(str(tmp), providers=["CPUExecutionProvider"])
    inputs = {i.name for i in session.get_inputs()}  # a zero residual's graph reads no guide (``VolumeNet``)
    got = session.run(None, {k: v for k, v in sample.items() if k in inputs})
    with torch.no_grad():
        want = [t.numpy() for t in graph(vol, guide)]
    worst = max(float(np.max(np.abs(g - w) / (np.abs(w) + 1e-3))) for g, w in zip(got[:2], want[:2]))
    if not worst < 1e-3:
        tmp.unlink()
        raise RuntimeError(f"the exported evidence network differs from torch by {worst:.2e} (relative)")
    tmp.replace(path)
    return path



UPSAMPLE_COLOUR_SIGMA = 0.3
"""Colour scale (log colour) of the guided upsampling an evidence network's manifest names (``bmi bench
evidence`` measures it)."""


def write_evidence_manifest(onnx_path: str | Path, inv_depth_per_m, training: dict, metrics: dict,
                            lens: str = DEFAULT_LENS, sigma_source: str = "network") -> Path:
    """The manifest of an exported evidence network: the evidence contract (``model_manifest``), the classical
    knobs its volume is made with (the defaults the training pairs used), its candidates, its training and where
    its reported 1σ comes from (``model_manifest.EVIDENCE_SIGMA_SOURCES``), and the support read's knobs
    (``decode.support``, the defaults)."""
    from bmi_sdk.decode import ClassicalConfig
    from bmi_sdk.decode.support import SupportConfig
    from bmi_sdk.lenses import lens_tensor
    from bmi_sdk.model_manifest import EVIDENCE_INPUT_NAME, EVIDENCE_OUTPUT_NAMES, write_manifest

    tensor = lens_tensor(lens)
    config = {k: v for k, v in ClassicalConfig().to_dict().items() if k != "threads"}
    return write_manifest(onnx_path, preset=f"evidence-w{training.get('width', 8)}", decoder="evidence",
                          receptive_field_px=16 * (2 * 28 + 1) + 64, lens=lens,
                          psf_tensor_key=tensor.spec.cache_key(tensor.lens), training=training, metrics=metrics,
                          input_name=EVIDENCE_INPUT_NAME, output_names=EVIDENCE_OUTPUT_NAMES, input_channels=2,
                          size_multiple=4, candidates_inv_depth_per_m=[float(x) for x in inv_depth_per_m],
                          classical_config=config, upsample_colour_sigma=UPSAMPLE_COLOUR_SIGMA,
                          sigma_source=sigma_source, support=SupportConfig().to_dict())


def calibrate_sigma(net: VolumeNet, pairs: VolumePairs, device: str = "cpu") -> float:
    """Scale the network's reported σ (its σ scale and floor alike) so that error / σ has unit standard deviation
    over ``pairs``' valid windows (held-out pairs: one scale fitted on data the weights never saw); returns the
    factor applied."""
    factor = evaluate(net, pairs, device)["z_std"]
    if not (factor > 0 and np.isfinite(factor)):
        raise ValueError(f"cannot calibrate σ: error/σ has standard deviation {factor} on the held-out pairs")
    with torch.no_grad():
        net.log_sigma_scale += float(np.log(factor))
        net.log_sigma_floor += float(np.log(factor))
    return float(factor)


def steps_for(seconds: float, train_dirs, batch_size: int, crop: int, width: int, device: str) -> int:
    """How many steps of ``train`` fit in ``seconds`` here: 10 timed steps of a throwaway network."""
    pairs = VolumePairs(train_dirs)
    inv = torch.as_tensor(pairs.inv_depth_per_m, device=device)
    net = VolumeNet(VolumeNetConfig(candidates=len(inv), width=width)).to(device)
    opt = torch.optim.AdamW(net.parameters(), lr=1e-4)
    rng = np.random.default_rng(1)
    for k in range(13):
        if k == 3:
            if device.startswith("cuda"):
                torch.cuda.synchronize()
            t0 = time.time()
        b = {key: torch.as_tensor(v, device=device) for key, v in pairs.batch(rng, batch_size, crop).items()}
        opt.zero_grad()
        losses(net, b, inv)["total"].backward()
        opt.step()
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    return max(50, int(seconds / ((time.time() - t0) / 10)))


def main(argv=None) -> None:
    """``python -m bmi_sdk.nn.volume_train --train DIR [DIR …] --val DIR --out NET.onnx (--steps N | --seconds S)``"""
    import argparse

    from bmi_sdk.model_manifest import EVIDENCE_SIGMA_SOURCES

    ap = argparse.ArgumentParser(description="train and export the evidence decoder's network")
    ap.add_argument("--train", nargs="+", required=True)
    ap.add_argument("--val", nargs="+", required=True)
    ap.add_argument("--out", required=True, help="the ONNX file; its state dict and log are written beside it")
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--seconds", type=float, default=None)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--crop", type=int, default=16)
    ap.add_argument("--width", type=int, default=8)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--init", default=None)
    ap.add_argument("--scalars-only", action="store_true", help="fit only the temperature and σ scale and floor")
    ap.add_argument("--sigma-source", choices=EVIDENCE_SIGMA_SOURCES, default="network",
                    help="the 1σ the runtime reports: the network's, or the classical stage's σ model "
                         "(model_manifest.EVIDENCE_SIGMA_SOURCES)")
    a = ap.parse_args(argv)
    if (a.steps is None) == (a.seconds is None):
        ap.error("give one of --steps and --seconds")
    steps = a.steps or steps_for(a.seconds, a.train, a.batch, a.crop, a.width, a.device)
    net, log = train(a.train, a.val, steps, a.batch, a.crop, a.lr, a.width, device=a.device, init=a.init,
                     log_every=max(1, steps // 20), scalars_only=a.scalars_only)
    out = Path(a.out)
    pairs = VolumePairs(a.val)
    torch.save(net.state_dict(), out.with_suffix(".pt"))
    export(net, pairs.inv_depth_per_m, out)
    log.update({"steps_run": steps, "scalars_only": a.scalars_only, "batch": a.batch, "crop": a.crop, "width": a.width, "lr": a.lr,
                "train": [str(p) for p in a.train], "val": [str(p) for p in a.val],
                "log_sigma_scale": float(net.log_sigma_scale.detach()),
                "log_sigma_floor": float(net.log_sigma_floor.detach()),
                "log_anchor": float(net.log_anchor.detach())})
    out.with_suffix(".log.json").write_text(json.dumps(log, indent=1))
    write_evidence_manifest(out, pairs.inv_depth_per_m, {k: v for k, v in log.items() if k not in ("before", "after")},
                            {"val_before": log["before"], "val_after": log["after"]}, sigma_source=a.sigma_source)
    print(json.dumps({"before": log["before"], "after": log["after"]}))


if __name__ == "__main__":
    main()
