"""Seeded fault injection on the device's frame output.

Each frame the device reads out draws at most one fault from a ``FaultPlan``
(probabilities per frame) with its own ``numpy`` generator, so a seed replays
the same faults. The injector keeps a ledger (fault → frame ids) that a test
compares with what the host reported.

* DROP: the frame is read out (the frame counter advances) but never sent.
* CORRUPT: one payload byte is flipped after the CRC was computed.
* INCOMPLETE: the FRAME message ends part-way through the payload (as when a
  readout is aborted); framing stays intact, the host sees fewer bytes.
* STALL: the frame is sent intact after a pause of ``stall_s`` (at most
  ``bmi_sdk.protocol.wire.MAX_STALL_S``); the device still answers commands
  meanwhile, and a STOP discards the held frame.
* DISCONNECT: part of the frame is sent, then the device drops the link.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np

from bmi_sdk.protocol.wire import MAX_STALL_S


class Fault(enum.Enum):
    NONE = "none"
    DROP = "drop"
    CORRUPT = "corrupt"
    INCOMPLETE = "incomplete"
    STALL = "stall"
    DISCONNECT = "disconnect"


_KINDS = (Fault.DROP, Fault.CORRUPT, Fault.INCOMPLETE, Fault.STALL, Fault.DISCONNECT)


@dataclass(frozen=True)
class FaultPlan:
    """Per-frame fault probabilities (each in [0, 1], sum <= 1) and the seed that replays them."""

    seed: int = 0
    drop: float = 0.0
    corrupt: float = 0.0
    incomplete: float = 0.0
    stall: float = 0.0
    disconnect: float = 0.0
    stall_s: float = 0.2

    def __post_init__(self):
        if not 0 <= self.seed < 2**32:
            raise ValueError(f"fault seed must be in [0, 2**32), got {self.seed}")
        probs = self.probabilities()
        for kind, p in zip(_KINDS, probs):
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"fault probability {kind.value}={p} is outside [0, 1]")
        if sum(probs) > 1.0 + 1e-12:
            raise ValueError(f"fault probabilities sum to {sum(probs)} > 1 (at most one fault per frame)")
        if not 0.0 <= self.stall_s <= MAX_STALL_S:
            raise ValueError(f"stall_s must be in [0, {MAX_STALL_S:g}] s, got {self.stall_s}")

    def probabilities(self) -> tuple[float, ...]:
        return (self.drop, self.corrupt, self.incomplete, self.stall, self.disconnect)

    @classmethod
    def parse(cls, spec: str) -> "FaultPlan":
        """``"seed=3,drop=0.05,corrupt=0.02,stall_s=0.1"`` → FaultPlan (for the CLI)."""
        kwargs = {}
        for item in filter(None, (s.strip() for s in spec.split(","))):
            key, sep, value = item.partition("=")
            if not sep or key not in cls.__dataclass_fields__:
                raise ValueError(f"bad fault spec item {item!r}; use KEY=VALUE with KEY in "
                                 f"{', '.join(cls.__dataclass_fields__)}")
            try:
                kwargs[key] = int(value) if key == "seed" else float(value)
            except ValueError:
                raise ValueError(f"bad fault spec item {item!r}: {key} takes "
                                 f"{'a whole number' if key == 'seed' else 'a number'}") from None
        return cls(**kwargs)


@dataclass
class FaultInjector:
    plan: FaultPlan
    ledger: dict[Fault, list[int]] = field(default_factory=lambda: {k: [] for k in _KINDS})

    def __post_init__(self):
        self.rng = np.random.default_rng(self.plan.seed)
        probs = np.array(self.plan.probabilities())
        self._edges = np.cumsum(probs)

    def draw(self, frame_id: int) -> Fault:
        u = self.rng.random()
        idx = int(np.searchsorted(self._edges, u, side="right"))
        if idx >= len(_KINDS):
            return Fault.NONE
        kind = _KINDS[idx]
        self.ledger[kind].append(frame_id)
        return kind

    def counts(self) -> dict[str, int]:
        return {k.value: len(v) for k, v in self.ledger.items()}

    def corrupt_offset(self, payload_len: int) -> int:
        return int(self.rng.integers(0, payload_len))

    def cut_fraction(self) -> float:
        """Share of the payload that still goes out for INCOMPLETE / DISCONNECT."""
        return float(self.rng.uniform(0.05, 0.95))
