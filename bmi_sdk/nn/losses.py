"""Training losses of the paper (§3.4): multi-scale content L1, multi-scale FFT, SILog; weights 1.0 / 0.1 / 0.1.

Every loss takes a pixel mask (N×1×H×W, 1 = valid: inside the image circle and
with a finite ground-truth range), because tiles at the sensor corners hold
pixels beyond θ = 60° that carry no signal.

Multi-scale targets are 2×2 / 4×4 average pools of the full-resolution target
(the same operator that makes the network's coarse inputs, see ``model``);
a coarse pixel is valid only where its whole footprint is (min-pool of the mask).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

WEIGHTS = {"content": 1.0, "fft": 0.1, "silog": 0.1}
"""γ_cont, γ_MSFR, γ_SILog of the paper."""

SILOG_LAMBDA = 0.85
"""Variance weight of the SILog loss; 1.0 is the paper's printed, fully scale-invariant form (see ``silog_loss``)."""


def pyramid(x: torch.Tensor, levels: int = 3) -> list[torch.Tensor]:
    """[¼, ½, full] average-pool pyramid (coarse first, matching the network's AiF outputs)."""
    out = [x]
    for _ in range(levels - 1):
        out.insert(0, F.avg_pool2d(out[0], 2))
    return out


def mask_pyramid(mask: torch.Tensor, levels: int = 3) -> list[torch.Tensor]:
    """[¼, ½, full] validity masks: a coarse pixel is valid when all the pixels it pools are."""
    out = [mask]
    for _ in range(levels - 1):
        out.insert(0, -F.max_pool2d(-out[0], 2))
    return out


def content_loss(preds: list[torch.Tensor], target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """L_cont = Σ_k (1/t_k) ‖Ŝ_k − S_k‖₁ over the valid pixels of scale k.

    t_k is the number of valid values (pixels × channels) at scale k, so each
    scale contributes a mean absolute error and the sum is over the K = 3 scales.
    """
    total = target.new_zeros(())
    for pred, tgt, m in zip(preds, pyramid(target, len(preds)), mask_pyramid(mask, len(preds))):
        m = m.expand_as(tgt)
        total = total + ((pred - tgt).abs() * m).sum() / m.sum().clamp_min(1.0)
    return total


def fft_loss(preds: list[torch.Tensor], target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """L_MSFR = Σ_k (1/t_k) ‖F(Ŝ_k) − F(S_k)‖₁ (Cho et al. 2021, Eq. 6), pinned down as:

    * F is the unnormalised 2-D DFT over H×W of each image and channel
      (``torch.fft.fft2``, norm="backward": F(x)[0, 0] = Σ x);
    * ‖·‖₁ of a complex array is Σ (|Re| + |Im|), the L1 norm of the real and
      imaginary parts stacked (as in MIMO-UNet's code);
    * t_k = 2 · N · C · H_k · W_k, the number of real values compared, so each
      scale's term is a mean; the sum runs over the K = 3 scales.

    Invalid pixels are zeroed in both images before the transform (a DFT has
    no per-pixel mask): the loss then compares the images restricted to the
    valid set.
    """
    total = target.new_zeros(())
    for pred, tgt, m in zip(preds, pyramid(target, len(preds)), mask_pyramid(mask, len(preds))):
        diff = torch.fft.fft2((pred - tgt) * m, dim=(-2, -1))
        total = total + (diff.real.abs() + diff.imag.abs()).sum() / (2 * diff.numel())
    return total


def silog_loss(pred_m: torch.Tensor, target_m: torch.Tensor, mask: torch.Tensor,
               lam: float = SILOG_LAMBDA) -> torch.Tensor:
    """SILog (Eigen et al. 2014), per image, averaged over the batch.

    With g_i = log d̂_i − log d_i over the n valid pixels of an image:
    L = (1/n) Σ g_i² − λ ((1/n) Σ g_i)².

    λ = 1 is the form printed in the paper: it equals the variance of g, so a
    prediction off by any constant factor (d̂ = s·d) has zero loss and the
    loss cannot teach metric scale. λ < 1 keeps a (1 − λ)·mean(g)² term that
    penalises a global scale error while still weighting structure mostly
    scale-invariantly; 0.85 is the value of Lee et al. (BTS, 2019). No square
    root and no ×10 factor (those variants change only the effective weight).
    """
    if not 0.0 <= lam <= 1.0:
        raise ValueError(f"SILog λ must lie in [0, 1], got {lam}")
    m = mask.to(pred_m.dtype)
    g = (torch.log(pred_m.clamp_min(1e-6)) - torch.log(target_m.clamp_min(1e-6))) * m
    n = m.sum(dim=(1, 2, 3))
    has = n > 0
    mean_g2 = g.square().sum(dim=(1, 2, 3)) / n.clamp_min(1.0)
    mean_g = g.sum(dim=(1, 2, 3)) / n.clamp_min(1.0)
    per_image = mean_g2 - lam * mean_g.square()
    return per_image[has].mean() if has.any() else pred_m.new_zeros(())


def total_loss(aif_preds: list[torch.Tensor], depth_pred_m: torch.Tensor, aif_target: torch.Tensor,
               depth_target_m: torch.Tensor, mask: torch.Tensor, lam: float = SILOG_LAMBDA) -> tuple[torch.Tensor, dict]:
    """γ_cont L_cont + γ_MSFR L_MSFR + γ_SILog L_SILog, and the three terms (floats) for logging."""
    terms = {"content": content_loss(aif_preds, aif_target, mask),
             "fft": fft_loss(aif_preds, aif_target, mask),
             "silog": silog_loss(depth_pred_m, depth_target_m, mask, lam)}
    total = sum(WEIGHTS[k] * v for k, v in terms.items())
    return total, {k: float(v.detach()) for k, v in terms.items()}


SIGMA_WEIGHT = 0.1
"""Weight of the σ head's likelihood (``sigma_nll_loss``) in the learned refinement's loss."""


def sigma_nll_loss(depth_pred_m: torch.Tensor, sigma_pred_m: torch.Tensor, target_m: torch.Tensor,
                   mask: torch.Tensor) -> torch.Tensor:
    """Gaussian negative log-likelihood of the depth error in metres under the predicted 1σ.

    With g = (d̂ − d) / d̂ (the depth held fixed: ``detach``, so the σ head learns how wrong the depth
    is without pulling the depth towards easy pixels) and s = σ̂ / d̂: L = mean over valid pixels of
    ½ (g / s)² + log s, i.e. of ½ ((d̂ − d) / σ̂)² + log σ̂ up to a term the σ head does not change. Its
    minimum over s is s = |g| per pixel, so on average σ̂² matches the squared error in metres, the error
    the runtime's ``depth_sigma`` is read against: (d̂ − d) / σ̂ has unit spread. The log-depth error would
    understate it for a far object read near (d̂ = d/2: log 2 = 0.69 d̂ against d − d̂ = d̂) and leave σ too
    small in metres.
    """
    m = mask.to(depth_pred_m.dtype)
    d_hat = depth_pred_m.detach().clamp_min(1e-6)
    g = (d_hat - target_m) / d_hat
    s = (sigma_pred_m / depth_pred_m.clamp_min(1e-6)).clamp_min(1e-4)  # exp of the σ output: no depth gradient
    per_px = 0.5 * (g / s).square() + torch.log(s)
    return (per_px * m).sum() / m.sum().clamp_min(1.0)
