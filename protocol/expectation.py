"""What a receiver accepts: its swarm, its model, its peers, and hard size caps.

Its own module so that every step of decoding (:mod:`protocol.header`,
:mod:`protocol.array_table`, :mod:`protocol.payload`) reads the same caps without importing
:mod:`protocol.codec`, which re-exports :class:`Expectation`. Pure Python.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from protocol.keys import validate_swarm
from protocol.messages import KIND_KEYFRAMES, KIND_STATUS, ModelSpec

MiB = 1024 * 1024


@dataclass(frozen=True)
class Expectation:
    """What a receiver accepts: its swarm, model, peers, and hard size caps.

    ``allowed_senders=None`` accepts any id (e.g. ``dinerf-agent status``); a robot passes the
    ids of its swarm. ``spec=None`` refuses every snapshot (``bad_signature``).

    The decompressed size a frame may declare depends on its kind (:meth:`max_raw_bytes`): a
    snapshot's is fixed by the model spec, but a status or keyframe summary has its own small
    cap, so a frame of a few KB can never make the receiver allocate hundreds of MB. The
    keyframe cap is 16x the summary budget of :class:`agent.align.config.AlignConfig` (256 kB).
    """

    swarm: str
    spec: ModelSpec | None = None
    allowed_senders: frozenset[int] | None = None
    max_wire_bytes: int = 512 * MiB
    max_decompressed_bytes: int = 512 * MiB
    max_tensors: int = 4096
    max_header_bytes: int = 1 * MiB
    max_keyframe_points: int = 200_000
    max_keyframes: int = 4096
    max_descriptor_dim: int = 1024
    max_keyframe_bytes: int = 4 * MiB
    max_status_bytes: int = 64 * 1024
    signature: str = field(init=False, default="")

    def __post_init__(self) -> None:
        validate_swarm(self.swarm)
        if self.allowed_senders is not None:
            object.__setattr__(self, "allowed_senders", frozenset(self.allowed_senders))
        if self.spec is not None:
            object.__setattr__(self, "signature", self.spec.signature())
            if len(self.spec.params) > self.max_tensors:
                raise ValueError("model spec has more tensors than max_tensors")
        for name in ("max_wire_bytes", "max_decompressed_bytes", "max_tensors", "max_header_bytes",
                     "max_keyframe_bytes", "max_status_bytes"):
            if getattr(self, name) <= 0:
                raise ValueError(f"Expectation.{name} must be positive")

    def max_raw_bytes(self, kind: str) -> int:
        """The largest decompressed payload a frame of this kind may declare."""
        if kind == KIND_STATUS:
            return min(self.max_status_bytes, self.max_decompressed_bytes)
        if kind == KIND_KEYFRAMES:
            return min(self.max_keyframe_bytes, self.max_decompressed_bytes)
        return self.max_decompressed_bytes
