"""Dual-head MIMO-UNet: one coded frame → multi-scale AiF RGB + metric depth (paper §3.4).

MIMO-UNet (Cho et al., ICCV 2021, "Rethinking coarse-to-fine approach in
single image deblurring") adapted as in the paper: the input B1 is pooled to
B2 (½) and B3 (¼); all three scales feed one shared encoder (B2, B3 through
shallow convolution modules SCM and feature attention modules FAM), and the
encoder's three stages are fused across scales by the asymmetric feature
fusion modules AFF. Two decoders share encoder and AFFs:

* the image decoder is MIMO-UNet's: AiF outputs at ¼, ½ and full resolution,
  each a residual on the (pooled) RGB input;
* the depth decoder is a copy of its structure with its own weights and a
  single full-resolution, non-residual output: log range around a reference
  range (``depth_m = d_ref · exp(out)``), positive by construction.

Departures from MIMO-UNet, each for a reason:

* the input has 6 channels (model_io: RGB + θ/60°, cos φ, sin φ) so a tile
  knows where it sits on the sensor; ``field_input=False`` (the ablation)
  drops channels 3–5 inside the network and keeps the same I/O contract;
* B2, B3 (and the multi-scale targets, see ``losses``) are 2×2 / 4×4 average
  pools instead of nearest-neighbour decimation: noisy coded pixels alias
  otherwise, and pooling exports to ONNX as one plain operator;
* ``multi_scale_input=False`` (the paper's input-scale ablation) removes the
  two coarse input branches (SCM + FAM); the decoders are unchanged.

The learned refinement (``--decoder learned``, docs/decoder.md) is this network
with ``extra_channels`` > 0: the classical decoder's per-pixel channels
(``decode.features``) are appended to the input, standardised by fixed per-channel
statistics of the training data (buffers ``extra_mean``, ``extra_std``, exported
with the weights: the evidence channels sit around 5–8 and would otherwise swamp
the head's pretrained inputs), and read by the full-resolution head only (the
coarse SCM branches keep the 6 contract channels), and with
``sigma_head``: a small head on the depth decoder's features returns log(σ_d / d),
trained with a Gaussian likelihood (``losses.sigma_nll_loss``). It reads those
features detached: the likelihood's gradient is large while σ is wrong and would
otherwise reshape the features the depth output is made from.

With width 32 and 8 residual blocks per stage (``PRESETS["paper"]``) the
network has 10.08 M parameters, the paper's count.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import nn

from bmi_sdk.model_io import INPUT_CHANNELS

RGB_CHANNELS = 3
DEPTH_REF_M = math.sqrt(0.7 * 10.0)
"""Reference range of the depth head (geometric mean of the paper's 0.7–10 m): a zero output means 2.65 m."""
LOG_SIGMA_MIN, LOG_SIGMA_MAX = -7.0, 3.0
"""Bounds of the σ head's log(σ_d / d): 0.1 % to 20× the depth."""


@dataclass(frozen=True)
class ModelConfig:
    """Shape of the network: channel width of stage 1 (stages 2, 3 have 2×, 4×), residual blocks per stage."""

    width: int = 32
    res_blocks: int = 8
    field_input: bool = True
    multi_scale_input: bool = True
    extra_channels: int = 0   # appended input channels read by the head (the learned refinement's features)
    sigma_head: bool = False  # a second depth output: log(σ_d / d)

    def __post_init__(self):
        if self.width < 4 or self.width % 4:
            raise ValueError(f"width must be a multiple of 4 and ≥ 4 (SCM splits it in quarters), got {self.width}")
        if self.res_blocks < 1:
            raise ValueError(f"res_blocks must be ≥ 1, got {self.res_blocks}")
        if self.extra_channels < 0:
            raise ValueError(f"extra_channels must be ≥ 0, got {self.extra_channels}")

    def to_dict(self) -> dict:
        return asdict(self)


PRESETS = {
    "paper": ModelConfig(width=32, res_blocks=8),
    "small": ModelConfig(width=16, res_blocks=2),
    "tiny": ModelConfig(width=8, res_blocks=1),
}
"""``paper`` is the published size; ``small`` and ``tiny`` train and run on a 2-core CPU."""

ABLATIONS = {
    "no_field": {"field_input": False},
    "single_scale": {"multi_scale_input": False},
}
"""Ablation variants of a preset, named ``<preset>-<ablation>`` (e.g. ``tiny-no_field``)."""


def preset_config(name: str) -> ModelConfig:
    """A preset by name, optionally with an ablation suffix: ``tiny``, ``tiny-no_field``, ``small-single_scale``."""
    base, _, ablation = name.partition("-")
    if base not in PRESETS:
        raise ValueError(f"unknown preset {base!r}; one of {sorted(PRESETS)}")
    cfg = PRESETS[base]
    if ablation:
        if ablation not in ABLATIONS:
            raise ValueError(f"unknown ablation {ablation!r}; one of {sorted(ABLATIONS)}")
        cfg = ModelConfig(**{**cfg.to_dict(), **ABLATIONS[ablation]})
    return cfg


class BasicConv(nn.Sequential):
    """Conv (or 4×4 stride-2 transposed conv) + optional ReLU, 'same' padding."""

    def __init__(self, c_in: int, c_out: int, kernel: int, stride: int = 1, relu: bool = True,
                 transpose: bool = False):
        if transpose:
            layers = [nn.ConvTranspose2d(c_in, c_out, kernel, stride=stride, padding=kernel // 2 - 1)]
        else:
            layers = [nn.Conv2d(c_in, c_out, kernel, stride=stride, padding=kernel // 2)]
        super().__init__(*layers, *([nn.ReLU(inplace=True)] if relu else []))


class ResBlock(nn.Module):
    def __init__(self, c: int):
        super().__init__()
        self.body = nn.Sequential(BasicConv(c, c, 3), BasicConv(c, c, 3, relu=False))

    def forward(self, x):
        return x + self.body(x)


def _res_stack(c: int, n: int) -> nn.Sequential:
    return nn.Sequential(*[ResBlock(c) for _ in range(n)])


class SCM(nn.Module):
    """Shallow convolution module: features of a coarse input, concatenated with the input itself."""

    def __init__(self, c_in: int, c_out: int):
        super().__init__()
        self.main = nn.Sequential(BasicConv(c_in, c_out // 4, 3), BasicConv(c_out // 4, c_out // 2, 1),
                                  BasicConv(c_out // 2, c_out // 2, 3), BasicConv(c_out // 2, c_out - c_in, 1, relu=False))
        self.fuse = BasicConv(c_out, c_out, 1, relu=False)

    def forward(self, x):
        return self.fuse(torch.cat([x, self.main(x)], dim=1))


class FAM(nn.Module):
    """Feature attention module: x + conv(x ⊙ scm)."""

    def __init__(self, c: int):
        super().__init__()
        self.merge = BasicConv(c, c, 3, relu=False)

    def forward(self, x, scm):
        return x + self.merge(x * scm)


class AFF(nn.Module):
    """Asymmetric feature fusion: the three encoder stages (resized to one scale) → one stage's features."""

    def __init__(self, c_in: int, c_out: int):
        super().__init__()
        self.conv = nn.Sequential(BasicConv(c_in, c_out, 1), BasicConv(c_out, c_out, 3, relu=False))

    def forward(self, *xs):
        return self.conv(torch.cat(xs, dim=1))


class Decoder(nn.Module):
    """MIMO-UNet decoder path: ¼ → ½ → full; returns features at each scale (coarse first)."""

    def __init__(self, w: int, n: int):
        super().__init__()
        self.blocks = nn.ModuleList([_res_stack(4 * w, n), _res_stack(2 * w, n), _res_stack(w, n)])
        self.up = nn.ModuleList([BasicConv(4 * w, 2 * w, 4, stride=2, transpose=True),
                                 BasicConv(2 * w, w, 4, stride=2, transpose=True)])
        self.squeeze = nn.ModuleList([BasicConv(4 * w, 2 * w, 1), BasicConv(2 * w, w, 1)])

    def forward(self, z, skip2, skip1):
        f4 = self.blocks[0](z)
        z = self.squeeze[0](torch.cat([self.up[0](f4), skip2], dim=1))
        f2 = self.blocks[1](z)
        z = self.squeeze[1](torch.cat([self.up[1](f2), skip1], dim=1))
        return f4, f2, self.blocks[2](z)


def _half(x):
    return F.avg_pool2d(x, 2)


def _up(x, factor: int):
    return F.interpolate(x, scale_factor=float(factor), mode="nearest")


class DualHeadMimoUNet(nn.Module):
    """N × (6 + extra) × H × W (H, W multiples of 4) → (AiF list [¼, ½, full] each N×3, depth_m N×1×H×W),
    plus depth_sigma_m N×1×H×W with ``sigma_head``."""

    def __init__(self, config: ModelConfig = PRESETS["paper"]):
        super().__init__()
        self.config = config
        w, n = config.width, config.res_blocks
        c_in = INPUT_CHANNELS if config.field_input else RGB_CHANNELS
        self.head = BasicConv(c_in + config.extra_channels, w, 3)
        if config.extra_channels:
            self.register_buffer("extra_mean", torch.zeros(1, config.extra_channels, 1, 1))
            self.register_buffer("extra_std", torch.ones(1, config.extra_channels, 1, 1))
        self.down = nn.ModuleList([BasicConv(w, 2 * w, 3, stride=2), BasicConv(2 * w, 4 * w, 3, stride=2)])
        self.encoder = nn.ModuleList([_res_stack(w, n), _res_stack(2 * w, n), _res_stack(4 * w, n)])
        if config.multi_scale_input:
            self.scm = nn.ModuleList([SCM(c_in, 2 * w), SCM(c_in, 4 * w)])
            self.fam = nn.ModuleList([FAM(2 * w), FAM(4 * w)])
        self.aff = nn.ModuleList([AFF(7 * w, w), AFF(7 * w, 2 * w)])
        self.image_decoder = Decoder(w, n)
        self.image_out = nn.ModuleList([BasicConv(4 * w, RGB_CHANNELS, 3, relu=False),
                                        BasicConv(2 * w, RGB_CHANNELS, 3, relu=False),
                                        BasicConv(w, RGB_CHANNELS, 3, relu=False)])
        self.depth_decoder = Decoder(w, n)
        self.depth_out = BasicConv(w, 1, 3, relu=False)
        if config.sigma_head:
            self.sigma_out = nn.Sequential(BasicConv(w, w, 3), BasicConv(w, 1, 3, relu=False))

    def forward(self, coded: torch.Tensor):
        x = coded[:, :INPUT_CHANNELS] if self.config.field_input else coded[:, :RGB_CHANNELS]
        x2 = _half(x)
        x4 = _half(x2)
        if self.config.extra_channels:
            head_in = torch.cat([x, (coded[:, INPUT_CHANNELS:] - self.extra_mean) / self.extra_std], dim=1)
        else:
            head_in = x
        e1 = self.encoder[0](self.head(head_in))
        z = self.down[0](e1)
        if self.config.multi_scale_input:
            z = self.fam[0](z, self.scm[0](x2))
        e2 = self.encoder[1](z)
        z = self.down[1](e2)
        if self.config.multi_scale_input:
            z = self.fam[1](z, self.scm[1](x4))
        e3 = self.encoder[2](z)
        skip1 = self.aff[0](e1, _up(e2, 2), _up(e3, 4))
        skip2 = self.aff[1](_half(e1), e2, _up(e3, 2))

        f4, f2, f1 = self.image_decoder(e3, skip2, skip1)
        aif = [self.image_out[0](f4) + x4[:, :RGB_CHANNELS], self.image_out[1](f2) + x2[:, :RGB_CHANNELS],
               self.image_out[2](f1) + x[:, :RGB_CHANNELS]]
        _, _, g1 = self.depth_decoder(e3, skip2, skip1)
        depth_m = DEPTH_REF_M * torch.exp(self.depth_out(g1))
        if self.config.sigma_head:
            log_rel_sigma = self.sigma_out(g1.detach()).clamp(LOG_SIGMA_MIN, LOG_SIGMA_MAX)
            return aif, depth_m, depth_m * torch.exp(log_rel_sigma)
        return aif, depth_m


class InferenceWrapper(nn.Module):
    """The exported graph: ``coded`` → (``aif`` full resolution, ``depth_m``[, ``depth_sigma_m``]), model_io."""

    def __init__(self, net: DualHeadMimoUNet):
        super().__init__()
        self.net = net

    def forward(self, coded):
        aif, *depth = self.net(coded)
        return (aif[-1], *depth)


def parameter_count(net: nn.Module) -> int:
    return sum(p.numel() for p in net.parameters())


def gflops(config: ModelConfig, height: int = 480, width: int = 640) -> float:
    """Forward GFLOPs (1 multiply-add = 2 FLOPs, torch's flop counter) of one height×width frame."""
    from torch.utils.flop_counter import FlopCounterMode

    net = DualHeadMimoUNet(config).eval()
    with torch.no_grad(), FlopCounterMode(display=False) as counter:
        net(torch.zeros(1, INPUT_CHANNELS, height, width))
    return counter.get_total_flops() / 1e9
