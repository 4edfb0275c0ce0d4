"""The evidence decoder's network: a small 3-D hourglass over the classical cost volume.

Input, per window of the classical decoder's grid (``decode.volume.volume_inputs``):

* ``volume`` (N, 2, D, R, C): the pooled and the own ΔNLL curves over the D depth candidates, in nats;
* ``guide`` (N, 4, R, C): the windows' log mean colour less its grid mean, and a 1/0 valid channel.

Output: ``logits`` (N, D, R, C) over the candidates, ``−a · pooled ΔNLL + residual``. The residual comes
from a 3-D convolutional hourglass (GC-Net, Kendall et al. ICCV 2017; PSMNet, Chang & Chen CVPR 2018)
that aggregates the volume over neighbouring windows and candidates at the window grid's resolution and at
½ and ¼ of it, with the guide's features added at each level so that image edges can stop aggregation.
Its last convolution starts at zero and ``a`` at 1: an untrained network returns the pooled evidence's own
posterior, and training can only move it where the data says the evidence misleads (depth edges, weak
texture, model error of a built camera).

Depth is the posterior mean of 1/d about its mode (``MODE_REACH`` candidates either side: a far second mode
does not pull the read between two surfaces), the posterior continuous between candidates
(``decode.volume.posterior``), its 1σ ``reported_sigma``: the whole posterior's spread times a
scale, in quadrature with a floor (both fitted with the Gaussian likelihood): flat or two-peaked evidence gives a
wide σ.

The grid's rows and columns must be multiples of 4 (the runtime pads them; ``PAD_MULTIPLE``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import nn

from bmi_sdk.decode.volume import INTERVAL_POINTS, MODE_REACH, VOLUME_SCALE_NATS, continuous_read

PAD_MULTIPLE = 4
"""The grid's rows and columns are padded to a multiple of this (two ½ levels)."""
GUIDE_CHANNELS = 4


@dataclass(frozen=True)
class VolumeNetConfig:
    """Size of the network: ``width`` features per voxel at the grid level (×2, ×4 at ½, ¼)."""

    candidates: int
    width: int = 8

    def to_dict(self) -> dict:
        return asdict(self)


class _Res3d(nn.Module):
    def __init__(self, ch: int):
        super().__init__()
        self.a = nn.Conv3d(ch, ch, 3, padding=1)
        self.b = nn.Conv3d(ch, ch, 3, padding=1)

    def forward(self, x):
        return F.relu(x + self.b(F.relu(self.a(x))))


class _Guide(nn.Module):
    """2-D features of the guide at one level, broadcast along the candidate axis."""

    def __init__(self, ch: int):
        super().__init__()
        self.a = nn.Conv2d(GUIDE_CHANNELS, ch, 3, padding=1)
        self.b = nn.Conv2d(ch, ch, 3, padding=1)

    def forward(self, g):
        return self.b(F.relu(self.a(g))).unsqueeze(2)


def _pool2(x):
    """Average over 2 × 2 windows (the guide and the valid mask one level down)."""
    return F.avg_pool2d(x, 2)


def _up2(x):
    """Nearest-neighbour doubling of rows and columns of an (N, C, D, R, C) volume."""
    return F.interpolate(x, scale_factor=(1.0, 2.0, 2.0), mode="nearest")


class VolumeNet(nn.Module):
    def __init__(self, config: VolumeNetConfig):
        super().__init__()
        self.config = config
        w = config.width
        self.stem = nn.Conv3d(2, w, 3, padding=1)
        self.guide0, self.guide1, self.guide2 = _Guide(w), _Guide(2 * w), _Guide(4 * w)
        self.enc0 = _Res3d(w)
        self.down1 = nn.Conv3d(w, 2 * w, 3, stride=(1, 2, 2), padding=1)
        self.enc1 = _Res3d(2 * w)
        self.down2 = nn.Conv3d(2 * w, 4 * w, 3, stride=(1, 2, 2), padding=1)
        self.enc2 = _Res3d(4 * w)
        self.up1 = nn.Conv3d(4 * w, 2 * w, 3, padding=1)
        self.dec1 = _Res3d(2 * w)
        self.up0 = nn.Conv3d(2 * w, w, 3, padding=1)
        self.dec0 = _Res3d(w)
        self.head = nn.Conv3d(w, 1, 3, padding=1)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)
        self.log_anchor = nn.Parameter(torch.zeros(()))        # a = exp(log_anchor) scales −pooled ΔNLL
        self.log_sigma_scale = nn.Parameter(torch.zeros(()))   # posterior spread → reported 1σ of 1/d
        self.log_sigma_floor = nn.Parameter(torch.tensor(math.log(0.01)))  # m⁻¹: the kernels' and grid's own error

    def residual_is_zero(self) -> bool:
        """Whether the residual is exactly zero for any input: its last convolution's weights and bias all zero
        (an untrained network, or one whose scalars alone were fitted)."""
        return not (bool(self.head.weight.detach().any()) or bool(self.head.bias.detach().any()))

    def anchor(self, volume: torch.Tensor) -> torch.Tensor:
        """(N, D, R, C) logits without the residual: −a · pooled ΔNLL."""
        return -torch.exp(self.log_anchor) * volume[:, 0]

    def forward(self, volume: torch.Tensor, guide: torch.Tensor) -> torch.Tensor:
        """(N, D, R, C) logits over the candidates (module doc)."""
        x = volume / VOLUME_SCALE_NATS
        g1 = _pool2(guide)
        g2 = _pool2(g1)
        f0 = self.enc0(F.relu(self.stem(x) + self.guide0(guide)))
        f1 = self.enc1(F.relu(self.down1(f0) + self.guide1(g1)))
        f2 = self.enc2(F.relu(self.down2(f1) + self.guide2(g2)))
        u1 = self.dec1(F.relu(self.up1(_up2(f2)) + f1))
        u0 = self.dec0(F.relu(self.up0(_up2(u1)) + f0))
        return self.anchor(volume) + self.head(u0)[:, 0]


def posterior_torch(logits: torch.Tensor, inv_depth_per_m: torch.Tensor,
                    reach: int = MODE_REACH) -> tuple[torch.Tensor, torch.Tensor]:
    """(read, spread) of 1/d under (N, D, R, C) logits over dim 1, as ``decode.volume.posterior`` reads them: the
    mean 1/d of the continuous posterior (the logits' cubic Hermite interpolant in 1/d, a uniform prior on the
    candidate index) over the ``reach`` candidates either side of the most probable one, and the discrete
    posterior's std."""
    z = logits - logits.amax(dim=1, keepdim=True)
    p = torch.softmax(z, dim=1)
    x = inv_depth_per_m.view(1, -1, 1, 1)
    mean = (p * x).sum(dim=1)
    var = (p * (x - mean.unsqueeze(1)) ** 2).sum(dim=1)
    read = continuous_read(z.movedim(1, 0), inv_depth_per_m.view(-1, 1, 1, 1), reach, INTERVAL_POINTS, torch)
    return read, torch.sqrt(var + 1e-12)


def reported_sigma(net: VolumeNet, posterior_std: torch.Tensor) -> torch.Tensor:
    """The reported 1σ of 1/d: √((s · posterior std)² + floor²), s and floor the network's fitted scalars."""
    return torch.sqrt((posterior_std * torch.exp(net.log_sigma_scale)) ** 2 + torch.exp(2 * net.log_sigma_floor))


class VolumeDecoderGraph(nn.Module):
    """What the ONNX file holds: volume and guide in; 1/d, its reported 1σ and the logits out (N, R, C each;
    logits N, D, R, C), the candidates' 1/d a constant of the graph."""

    def __init__(self, net: VolumeNet, inv_depth_per_m):
        super().__init__()
        self.net = net
        self.register_buffer("inv_depth_per_m", torch.as_tensor(inv_depth_per_m, dtype=torch.float32))
        # a residual that is exactly zero is left out: the graph holds the anchor alone (the same logits without
        # the hourglass's 3-D convolutions) and reads no guide
        self.anchor_only = net.residual_is_zero()

    def forward(self, volume, guide):
        logits = self.net.anchor(volume) if self.anchor_only else self.net(volume, guide)
        mean, std = posterior_torch(logits, self.inv_depth_per_m)
        return mean, reported_sigma(self.net, std), logits
