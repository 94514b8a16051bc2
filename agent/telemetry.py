"""What a robot records about each round, in one typed record, and the files it goes to.

:class:`RoundRecord` is written by the daemon (one JSON line per completed round in
``telemetry.jsonl``), returned by the in-process simulation (:class:`agent.swarm.Simulation`),
and read back by every reader (scenario runner, report, compare) through
:func:`read_telemetry`, so that a field is named and typed in one place. ``events.jsonl`` holds
the rarer happenings (joined, aligned, silent neighbour ...) as free-form :class:`EventLog` lines.
"""

from __future__ import annotations

import dataclasses
import json
import math
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, TextIO

__all__ = ["RoundRecord", "EventLog", "JsonLines", "Reporter", "StatusBoard", "read_telemetry", "read_events"]


@dataclass
class RoundRecord:
    """One robot after one round. ``round`` counts completed rounds: theta^round exists."""

    robot: int
    round: int
    time: float = 0.0  # wall clock (time.time()) when the round ended
    monotonic: float = 0.0  # time.monotonic() of the robot's process, the clock of its events
    loss: float | None = None  # mean training loss of the round's steps
    rgb_loss: float | None = None
    depth_loss: float | None = None
    batch_psnr: float | None = None  # PSNR of the mean RGB loss on the training rays
    psnr: float | None = None  # on the robot's own held-out views (when evaluated this round)
    samples_per_ray: float | None = None
    pose: list[list[float]] | None = None  # [4, 4] T_shared_from_local, the robot's estimate
    pose_rotation_deg: float | None = None
    pose_translation: list[float] | None = None  # [3]
    pose_scale: float | None = None
    reference: int | None = None
    elected: bool = False  # this robot was the reference (its pose frozen)
    epoch: int = 0
    live_neighbours: list[int] = field(default_factory=list)
    reachable: list[int] = field(default_factory=list)  # live neighbours whose tokens it saw itself
    heard: list[int] = field(default_factory=list)  # neighbours whose snapshot this round used
    bytes_in: dict[int, int] = field(default_factory=dict)  # per sender, received since the last record (by time)
    bytes_out: int = 0
    bytes_out_links: dict[int, int] = field(default_factory=dict)  # per neighbour: snapshot bytes pushed this round
    wire_ratio: float | None = None  # mean of bytes_out_links over the raw float32 snapshot: 1.0 = uncompressed
    seconds_compute: float = 0.0
    seconds_wait: float = 0.0  # at the barrier, waiting for neighbours
    cpu_seconds: float | None = None  # the process's CPU time (all threads) since the last record
    cpu_seconds_compute: float | None = None  # ... of which during the training steps
    seconds_last_put: dict[int, float] = field(default_factory=dict)  # per neighbour: the last put's duration
    steps: int = 0
    seconds_per_step: float | None = None
    rejected: dict[str, int] = field(default_factory=dict)  # refused messages so far, by reason
    alignment: str | None = None  # protocol.messages.Alignment value
    alignment_detail: str = ""
    disagreement: float | None = None  # ||theta_i - mean|| / ||mean|| (the simulation knows it)
    clipped: dict[int, float] = field(default_factory=dict)  # per neighbour clipped this round: its smallest factor
    suspects: dict[int, str] = field(default_factory=dict)  # neighbours not trusted, and why (messages.SUSPICIONS)
    # Views that arrive while training (agent.data.stream; None: all given at start)
    keyframes: int | None = None  # training keyframes so far
    keyframes_admitted: int | None = None  # ... admitted this round
    keyframes_held_out: int | None = None  # held out this round
    keyframes_dropped: int | None = None  # frames that became no keyframe this round (no pose, over capacity)
    keyframe_age_s: float | None = None  # since the newest keyframe reached the robot
    coverage: list[float] | None = None  # extent of the camera centres so far per axis (local units)

    def to_json(self) -> str:
        doc = dataclasses.asdict(self)
        doc["bytes_in"] = {str(j): b for j, b in self.bytes_in.items()}
        doc["seconds_last_put"] = {str(j): s for j, s in self.seconds_last_put.items()}
        doc["bytes_out_links"] = {str(j): b for j, b in self.bytes_out_links.items()}
        doc["clipped"] = {str(j): f for j, f in self.clipped.items()}
        doc["suspects"] = {str(j): why for j, why in self.suspects.items()}
        return json.dumps(doc)

    @classmethod
    def from_dict(cls, doc: dict[str, Any]) -> "RoundRecord":
        """From a decoded JSON line; unknown keys (a newer writer) are ignored, missing ones default."""
        names = {f.name for f in dataclasses.fields(cls)}
        kwargs = {k: v for k, v in doc.items() if k in names}
        kwargs["bytes_in"] = {int(j): int(b) for j, b in (doc.get("bytes_in") or {}).items()}
        kwargs["seconds_last_put"] = {int(j): float(s) for j, s in (doc.get("seconds_last_put") or {}).items()}
        kwargs["bytes_out_links"] = {int(j): int(b) for j, b in (doc.get("bytes_out_links") or {}).items()}
        kwargs["clipped"] = {int(j): float(f) for j, f in (doc.get("clipped") or {}).items()}
        kwargs["suspects"] = {int(j): str(why) for j, why in (doc.get("suspects") or {}).items()}
        return cls(**kwargs)

    @property
    def translation_norm(self) -> float:
        return math.sqrt(sum(x * x for x in self.pose_translation or ()))

    def log_line(self, rounds: int) -> str:
        """The operator's line for this round (the daemon prints one per round, after ``[robot i]``)."""
        psnr = f"{self.psnr:5.2f} dB" if self.psnr is not None else "   n/a  "
        state = "reference" if self.elected else (self.alignment or "?")
        if state == "unaligned":
            state = "UNALIGNED: alone, out of consensus"
        return (
            f"round {self.round:3d}/{rounds} | loss {self.loss:.5f} | psnr {psnr} | "
            f"pose est {self.pose_rotation_deg:6.2f} deg, |t| {self.translation_norm:.3f}, s {self.pose_scale:.3f}"
            f" ({state}) | heard {self.heard}/{self.reachable} | "
            f"in {sum(self.bytes_in.values()) / 1e6:.1f} MB out {self.bytes_out / 1e6:.1f} MB"
            f"{f' ({self.wire_ratio:.3f} of float32)' if self.wire_ratio is not None and self.wire_ratio < 0.9 else ''} | "
            f"compute {self.seconds_compute:.1f} s wait {self.seconds_wait:.1f} s{self._views_text()}"
        )

    def _views_text(self) -> str:
        """The stream's part of the log line: keyframes so far (+ this round), the newest's age, the area."""
        if self.keyframes is None:
            return ""
        age = "-" if self.keyframe_age_s is None else f"{self.keyframe_age_s:.1f} s"
        area = coverage_text(self.coverage, digits=2)
        return (f" | keyframes {self.keyframes} (+{self.keyframes_admitted}, held out +{self.keyframes_held_out}, "
                f"dropped +{self.keyframes_dropped}) newest {age} ago, area {area}")


def coverage_text(extent: list[float] | None, digits: int = 1) -> str:
    """The area a stream's cameras cover (extent per axis), for log lines and ``status``."""
    return "-" if not extent else " x ".join(f"{x:.{digits}f}" for x in extent)


@dataclass(frozen=True)
class PlateauRule:
    """A loss that stops moving while still high, or without having fallen from where it started,
    means a field that cannot model what the cameras see (a bounded box around an RGB capture's
    room, a wrong frame), not convergence."""

    window: int = 4  # rounds
    rel_change: float = 0.03  # max spread of those rounds' losses, relative to their mean
    above_loss: float = 0.02  # photometric MSE; 0.02 is ~17 dB on the robot's own rays
    stalled_fraction: float = 0.7  # ... or still above this fraction of the first round's loss

    def is_flat(self, losses: list[float]) -> bool:
        last = losses[-self.window:]
        if len(last) < self.window or len(losses) < 2:
            return False
        mean = sum(last) / len(last)
        if max(last) - min(last) > self.rel_change * mean:
            return False
        return min(last) > self.above_loss or mean > self.stalled_fraction * losses[0]


class JsonLines:
    """An append-only JSON-lines file written from several threads, flushed line by line.

    A line written after :meth:`close` is dropped: a network callback (a neighbour's token gone
    while this robot shuts down) may still report after the robot closed its files, and it
    used to end in "I/O operation on closed file" in the log."""

    def __init__(self, path: Path) -> None:
        self._file: TextIO = open(path, "a")
        self._lock = threading.Lock()

    def write_line(self, line: str) -> None:
        with self._lock:
            if self._file.closed:
                return
            self._file.write(line + "\n")
            self._file.flush()

    def close(self) -> None:
        with self._lock:
            self._file.close()


class EventLog(JsonLines):
    """``events.jsonl``: one line per happening, with the robot's clocks and its current round."""

    def __init__(self, path: Path, robot_id: int) -> None:
        super().__init__(path)
        self.robot_id = robot_id

    def write(self, kind: str, round_index: int, **fields: Any) -> None:
        self.write_line(json.dumps({"event": kind, "robot": self.robot_id, "monotonic": time.monotonic(),
                                    "time": time.time(), "round": round_index, **fields}))


class Reporter:
    """A robot's voice: its log lines, its events and its count of refused messages, thread-safe."""

    def __init__(self, robot_id: int, log: Callable[[str], None], events: EventLog,
                 round_of: Callable[[], int], warn: Callable[[str], None] | None = None) -> None:
        self.robot_id = robot_id
        self._log, self._events, self._round_of = log, events, round_of
        self._warn = warn or log
        self._lock = threading.Lock()
        self.rejected: Counter[str] = Counter()

    def say(self, text: str) -> None:
        self._log(f"[robot {self.robot_id}] {text}")

    def warn(self, text: str) -> None:
        """Something an operator should act on or know (refused messages, a robot out of consensus)."""
        self._warn(f"[robot {self.robot_id}] {text}")

    def event(self, kind: str, **fields: Any) -> None:
        self._events.write(kind, self._round_of(), **fields)

    def reject(self, reason: str, detail: str) -> None:
        """Count a refused message by reason; log the first few of each and then every 100th."""
        with self._lock:
            self.rejected[reason] += 1
            count = self.rejected[reason]
        if count <= 3 or count % 100 == 0:
            self.warn(f"rejected a message ({reason}, #{count}): {detail[:200]}")

    def rejected_counts(self) -> dict[str, int]:
        with self._lock:
            return dict(self.rejected)

    def close(self) -> None:
        self._events.close()


class StatusBoard:
    """What this robot says about itself in its next Status, and the newest Status of each neighbour."""

    def __init__(self, **initial: Any) -> None:
        self._lock = threading.Lock()
        self._own: dict[str, Any] = dict(initial)
        self._peers: dict[int, Any] = {}

    def set(self, **fields: Any) -> None:
        with self._lock:
            self._own.update(fields)

    def own(self) -> dict[str, Any]:
        with self._lock:
            return dict(self._own)

    def heard_from(self, sender: int, status: Any) -> None:
        with self._lock:
            self._peers[sender] = status

    def peers(self) -> dict[int, Any]:
        with self._lock:
            return dict(self._peers)


def _read_lines(path: Path) -> list[dict]:
    if not path.is_file():
        return []
    out = []
    for line in path.read_text().splitlines():
        try:
            doc = json.loads(line)
        except json.JSONDecodeError:
            continue  # a line cut by SIGKILL
        if isinstance(doc, dict):
            out.append(doc)
    return out


def read_telemetry(path: Path) -> list[RoundRecord]:
    """The records of a robot's ``telemetry.jsonl`` (none if it is absent), in file order."""
    return [RoundRecord.from_dict(d) for d in _read_lines(Path(path)) if "robot" in d and "round" in d]


def read_events(path: Path) -> list[dict]:
    """The lines of a robot's ``events.jsonl`` (none if it is absent)."""
    return _read_lines(Path(path))
