"""Tile layout and blending weights for streaming inference over a raw frame.

One fixed tile shape (``tile_px`` × ``tile_px``) covers the frame after a
virtual reflect padding of ``pad_px`` on every side (the network sees a
plausible continuation at the frame borders instead of zeros). Neighbouring
tiles overlap by ``overlap_px``, split into

* ``context_px`` per side, whose outputs are discarded (weight 0): the part of
  a tile where the network's receptive field reaches past the tile edge, and
* a Hann cross-fade of ``ramp_px`` in the middle, where the two tiles'
  weights sum to one.

So ``overlap_px = 2 × context_px + ramp_px``. With ``context_px`` ≥ half the
receptive field every kept output pixel sees its whole receptive field inside
its tile, and the tiled result equals the untiled one up to float rounding:
the default overlap is that context alone (no ramp), since both tiles already
agree wherever a ramp would blend them. A ramp is left only when an explicit
overlap exceeds twice the context (benchmarks).
Sides that face the (padded) frame edge keep weight 1: there is no neighbour
to blend with. Every origin and size is a multiple of ``step_px`` (the
network's size multiple, itself even), so the Bayer phase and the network's
downsampling grid are the same in every tile.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def round_up(value: float, multiple: int) -> int:
    return int(math.ceil(value / multiple) * multiple)


@dataclass(frozen=True)
class TilePlan:
    """How a ``height_px`` × ``width_px`` frame is cut into tiles (coordinates relative to the frame)."""

    height_px: int
    width_px: int
    tile_px: int
    overlap_px: int
    context_px: int
    pad_px: int
    step_px: int = 4

    def __post_init__(self):
        if self.height_px <= 0 or self.width_px <= 0:
            raise ValueError(f"frame size must be positive, got {self.height_px}×{self.width_px}")
        for name in ("tile_px", "overlap_px", "pad_px"):
            if getattr(self, name) % self.step_px:
                raise ValueError(f"{name}={getattr(self, name)} must be a multiple of {self.step_px}")
        if not 0 <= self.overlap_px < self.tile_px:
            raise ValueError(f"overlap_px={self.overlap_px} must lie in [0, tile_px={self.tile_px})")
        if not 0 <= 2 * self.context_px <= self.overlap_px:
            raise ValueError(f"2 × context_px={self.context_px} must not exceed overlap_px={self.overlap_px}")

    @classmethod
    def for_model(cls, height_px: int, width_px: int, tile_px: int, receptive_field_px: int,
                  step_px: int = 4, overlap_px: int | None = None) -> "TilePlan":
        """The plan for a network with the given receptive field (full width, input px).

        Default overlap: the receptive field (context = half of it per side,
        rounded up to ``step_px``; no ramp: module doc). An explicit
        ``overlap_px`` (benchmarks) keeps the context at half the receptive
        field as long as the overlap allows, and gives the rest to the ramp.
        The border pad is half the receptive field whatever the overlap, so
        that only seams change with it.
        """
        half_rf = round_up(receptive_field_px / 2, step_px)
        if overlap_px is None:
            overlap_px = 2 * half_rf
        if overlap_px < 0:  # checked as given: rounding first would report -10 as -8
            raise ValueError(f"overlap_px must be >= 0, got {overlap_px}")
        given_px, overlap_px = overlap_px, round_up(overlap_px, step_px)
        context = min(half_rf, overlap_px // 2)
        if overlap_px >= tile_px:
            raise ValueError(f"tile_px={tile_px} is too small for an overlap of {given_px} px "
                             f"(receptive field {receptive_field_px} px)")
        return cls(height_px, width_px, tile_px, overlap_px, context, half_rf, step_px)

    @property
    def ramp_px(self) -> int:
        return self.overlap_px - 2 * self.context_px

    def _origins(self, length: int) -> list[int]:
        """Tile origins along one axis (frame coordinates, may be negative: the pad)."""
        padded = length + 2 * self.pad_px
        stride = self.tile_px - self.overlap_px
        last = max(0, round_up(padded - self.tile_px, self.step_px))
        origins = list(range(0, last, stride)) + [last]
        return [o - self.pad_px for o in origins]

    @property
    def row_origins(self) -> list[int]:
        return self._origins(self.height_px)

    @property
    def col_origins(self) -> list[int]:
        return self._origins(self.width_px)

    def weights_1d(self, origins: list[int], index: int) -> np.ndarray:
        """Blend weight along one axis for tile ``index``: 0 on the context, Hann ramp, 1 inside."""
        w = np.ones(self.tile_px, np.float32)
        ramp = self.ramp_px
        t = (np.arange(ramp, dtype=np.float32) + 0.5) / max(ramp, 1)
        rise = np.sin(0.5 * np.pi * t) ** 2  # Hann half-window: rise + mirrored fall of the neighbour = 1
        if index > 0:
            w[:self.context_px] = 0
            w[self.context_px:self.context_px + ramp] = rise
        if index < len(origins) - 1:
            # blend against the next tile where its context ends, whatever its (clamped) position
            end = origins[index + 1] + self.context_px - origins[index]   # next tile's first kept pixel
            w[end + ramp:] = 0
            w[end:end + ramp] = np.minimum(w[end:end + ramp], rise[::-1])
        return w

    def tiles(self):
        """Yield (row0, col0, weight) for every tile in row-major order (frame coordinates)."""
        rows, cols = self.row_origins, self.col_origins
        col_w = [self.weights_1d(cols, j) for j in range(len(cols))]
        for i, r0 in enumerate(rows):
            rw = self.weights_1d(rows, i)
            for j, c0 in enumerate(cols):
                yield r0, c0, rw[:, None] * col_w[j][None, :]

    @property
    def n_tiles(self) -> int:
        return len(self.row_origins) * len(self.col_origins)

    def to_dict(self) -> dict:
        return {"tile_px": self.tile_px, "overlap_px": self.overlap_px, "context_px": self.context_px,
                "ramp_px": self.ramp_px, "pad_px": self.pad_px, "step_px": self.step_px,
                "grid": [len(self.row_origins), len(self.col_origins)]}
