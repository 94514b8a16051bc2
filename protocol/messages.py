"""Typed messages that cross the network, and the reasons a received message is refused.

Every message has the same header (see :class:`Header`): schema version, kind, swarm, sender,
round, reference epoch, model signature, encoding, payload lengths and checksum. The header is
built by :mod:`protocol.codec` on encode and attached to the message on decode; callers build
messages without it.

Kinds (``Header.kind``):

- ``theta``     :class:`ThetaSnapshot`, a robot's model parameters after a round;
- ``status``    :class:`Status`, telemetry for ``dinerf-agent status`` and reports;
- ``keyframes`` :class:`KeyframeSummary`, compact features for a coarse initial alignment.

:class:`ModelSpec` describes the parameters a snapshot must carry (ordered names, shapes,
dtypes, plus architecture settings); its :meth:`ModelSpec.signature` goes into every snapshot so
that robots with different models never mix parameters.

:class:`Rejected` is the one exception raised for anything received that does not validate; its
``reason`` is one of :data:`REJECT_REASONS` so the daemon can count refusals by cause.

Pure Python + numpy: importing this module never imports zenoh or torch.
"""

from __future__ import annotations

import enum
import hashlib
import json
import math
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

import numpy as np

from protocol.untrusted import describe

#: Bumped whenever the header or a body changes incompatibly; peers on another version are refused.
#: 2: Status.alignment is an :class:`Alignment` value, with its free text in alignment_detail.
#: 3: Status.suspects: the neighbours the sender does not trust, and why.
#: 4: Status.views: keyframes so far, held out, dropped, the newest's age, the area covered.
SCHEMA_VERSION = 4

#: Why a robot distrusts a neighbour (Status.suspects): its claimed round runs ahead of its pace,
#: its models are clipped, move erratically or are unrelated to the robot's own (robust consensus),
#: it is quarantined for that, or
#: its snapshots are refused.
SUSPICIONS = ("ahead_of_pace", "clipped", "erratic", "uncorrelated", "quarantined", "refused")

#: Largest round / epoch number accepted (fits a signed 32-bit int on every platform).
MAX_ROUND = 2**31 - 1

KIND_THETA = "theta"
KIND_STATUS = "status"
KIND_KEYFRAMES = "keyframes"
KEYFRAME_ARRAYS = ("descriptors", "points", "keyframe_index", "keypoints", "keyframe_cameras")  # wire order
KEYFRAME_CAMERA_DIM = 16  # per keyframe: camera-to-world rows 0-2 (OpenGL, 12) + fx, fy, cx, cy
KINDS = (KIND_THETA, KIND_STATUS, KIND_KEYFRAMES)

WIRE_DTYPES = ("float32", "float16")
COMPRESSIONS = ("zstd", "none")

#: Every reason a received message can be refused for, with what it means.
REJECT_REASONS: dict[str, str] = {
    "garbage": "not a dinerf message at all, or its header cannot be parsed",
    "bad_magic": "does not start with the dinerf magic bytes",
    "bad_schema": "schema version differs from ours",
    "bad_kind": "unknown message kind, or not the kind expected on this key",
    "bad_header": "a header field is missing, unexpected or of the wrong type",
    "wrong_swarm": "belongs to another swarm",
    "unknown_sender": "sender id is not one we accept",
    "sender_mismatch": "sender id in the header differs from the id in the key",
    "bad_round": "round or epoch is not an integer in [0, MAX_ROUND], or differs from the key",
    "bad_signature": "model signature differs from ours",
    "bad_encoding": "unknown wire dtype or compression",
    "bad_length": "a length does not match (truncated, padded, or inconsistent sizes)",
    "bad_checksum": "payload checksum does not match",
    "too_large": "declared or actual size is above our caps",
    "decompression_bomb": "compressed frame would expand beyond what the header declares",
    "bad_shape": "tensor names, dtypes or shapes differ from the model spec",
    "bad_field": "a body field has the wrong type or is out of range",
    "non_finite": "NaN or infinity among the values",
    "stale_round": "round is older than the current one",
    "too_far_ahead": "round is past the swarm's last round",
    "ahead_of_sender": "round is more than one past what its sender's heartbeat says it has completed",
    "unknown_base": "a compressed snapshot names a base we do not hold, where a full one was due",
}


class Rejected(Exception):
    """A received message was refused. ``reason`` is a key of :data:`REJECT_REASONS`."""

    def __init__(self, reason: str, detail: str = ""):
        if reason not in REJECT_REASONS:
            raise ValueError(f"unknown reject reason {reason!r}")
        self.reason = reason
        self.detail = detail
        super().__init__(f"{reason}: {detail}" if detail else reason)


@dataclass(frozen=True)
class Header:
    """What every message says about itself, as read from (or written to) the wire."""

    schema: int
    kind: str
    swarm: str
    sender: int
    round: int
    epoch: int
    signature: str
    wire_dtype: str
    compression: str
    raw_length: int  # payload bytes after decompression
    payload_length: int  # payload bytes on the wire
    checksum: str  # blake2b-64 (hex) of the header (checksum zeroed) + wire payload


# --------------------------------------------------------------------------- model spec


@dataclass(frozen=True)
class ParamSpec:
    """One named parameter tensor: its shape and in-memory dtype."""

    name: str
    shape: tuple[int, ...]
    dtype: str = "float32"

    @property
    def size(self) -> int:
        return math.prod(self.shape)


@dataclass(frozen=True)
class ModelSpec:
    """The parameters a snapshot must carry, in order, plus architecture settings.

    Two robots can exchange snapshots only when their :meth:`signature` is equal, which covers
    both the tensor layout and the ``arch`` settings (hash-grid levels, MLP width ...), since the
    same shapes with a different architecture would still mean different functions.
    """

    params: tuple[ParamSpec, ...]
    arch: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        names = [p.name for p in self.params]
        if len(set(names)) != len(names):
            raise ValueError("ModelSpec has duplicate parameter names")
        for p in self.params:
            if not p.name or not isinstance(p.name, str):
                raise ValueError(f"bad parameter name {p.name!r}")
            if p.dtype != "float32":
                raise ValueError(f"parameter {p.name}: only float32 parameters are supported")
            if any(type(d) is not int or d < 0 for d in p.shape):
                raise ValueError(f"parameter {p.name}: bad shape {p.shape!r}")
        try:
            json.dumps(dict(self.arch), sort_keys=True)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"ModelSpec.arch must be JSON-serialisable: {exc}") from None

    @classmethod
    def from_tensors(cls, tensors: Mapping[str, np.ndarray], arch: Mapping[str, Any] | None = None) -> "ModelSpec":
        """Spec of a dict of arrays (order kept)."""
        params = tuple(ParamSpec(name, tuple(int(d) for d in np.shape(a)), "float32") for name, a in tensors.items())
        return cls(params, dict(arch or {}))

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.params)

    @property
    def num_values(self) -> int:
        return sum(p.size for p in self.params)

    @property
    def float32_bytes(self) -> int:
        """The raw size of one snapshot at float32: what compression ratios are quoted against."""
        return 4 * self.num_values

    def canonical_json(self) -> str:
        doc = {
            "params": [[p.name, list(p.shape), p.dtype] for p in self.params],
            "arch": dict(self.arch),
        }
        return json.dumps(doc, sort_keys=True, separators=(",", ":"))

    def signature(self) -> str:
        """Short stable hash (16 hex chars of sha256) of the layout and the architecture."""
        return hashlib.sha256(self.canonical_json().encode()).hexdigest()[:16]

    def check(self, tensors: Mapping[str, np.ndarray]) -> None:
        """Raise ValueError if ``tensors`` does not have exactly this layout (for our own sends)."""
        if list(tensors.keys()) != list(self.names):
            raise ValueError(f"tensor names/order {list(tensors)} differ from the spec {list(self.names)}")
        for p in self.params:
            a = tensors[p.name]
            if tuple(np.shape(a)) != p.shape:
                raise ValueError(f"tensor {p.name}: shape {np.shape(a)} != spec {p.shape}")


# --------------------------------------------------------------------------- messages


class Alignment(str, enum.Enum):
    """Where a robot stands with its relative pose (``Status.alignment``)."""

    PENDING = "pending"  # still looking for it (coarse alignment running)
    REFERENCE = "reference"  # it defines the shared frame
    IDENTITY = "identity"  # it starts from the identity, as configured (the paper's start)
    COARSE = "coarse"  # found by matching keyframe summaries with an aligned neighbour
    UNALIGNED = "unaligned"  # the coarse step found nothing; it started from the identity

    @property
    def knows_pose(self) -> bool:
        """Others may align through this robot: its frame is placed in the shared one."""
        return self in (Alignment.REFERENCE, Alignment.COARSE)

    @property
    def settled(self) -> bool:
        """The robot has decided where it starts (it will not look any further)."""
        return self is not Alignment.PENDING


@dataclass
class CodedTheta:
    """A compressed snapshot's content (:mod:`protocol.compression`): its mode, the base it is a
    delta against (round, digest; -1 and "" without one), the digest of the model it decodes to,
    and its arrays by wire name (``<tensor>/q``, ``<tensor>/scale``, ``<tensor>/gaps``)."""

    mode: str
    chunk: int
    base_round: int
    base_digest: str
    digest: str
    arrays: dict[str, np.ndarray]


@dataclass
class ThetaSnapshot:
    """A robot's model parameters at the end of ``round`` (float32 in memory, ordered).

    A compressed one has ``coded`` set and no ``tensors`` until
    :meth:`protocol.compression.BaseBook.resolve` rebuilds them from its base.
    """

    swarm: str
    sender: int
    round: int
    epoch: int
    signature: str
    tensors: dict[str, np.ndarray]
    header: Header | None = None  # set by decode
    coded: CodedTheta | None = None

    kind = KIND_THETA


@dataclass
class Status:
    """Telemetry a robot publishes once per round (shown by ``dinerf-agent status``).

    ``pose`` is the robot's estimate of its frame in the shared frame: log scale, axis-angle
    phi (3), translation t (3). ``rejected`` counts refused messages by reason.
    """

    swarm: str
    sender: int
    round: int
    epoch: int
    reference: int
    phase: str
    loss: float | None
    psnr: float | None
    pose: list[float]
    neighbours_heard: list[int]
    bytes_in: int
    bytes_out: int
    rejected: dict[str, int]
    alignment: Alignment
    alignment_detail: str  # free text for people: via whom, how many inliers, why it failed
    wall_time: float
    seconds_compute: float
    seconds_wait: float
    #: Liveness gossip: {robot id: seconds since the sender last had evidence it was alive}.
    #: Zenoh peers do not relay, so this is how robots learn about non-neighbours.
    alive_ages: dict[int, float] = field(default_factory=dict)
    #: Neighbours the sender does not trust: {robot id: one of :data:`SUSPICIONS`}.
    suspects: dict[int, str] = field(default_factory=dict)
    #: A robot whose views arrive while it trains (None: all given at start): :data:`VIEWS_FIELDS`.
    views: dict | None = None
    header: Header | None = None

    kind = KIND_STATUS

    #: Body fields (everything but the header-level ones) and the checker for each.
    BODY_FIELDS = (
        "reference",
        "phase",
        "loss",
        "psnr",
        "pose",
        "neighbours_heard",
        "bytes_in",
        "bytes_out",
        "rejected",
        "alignment",
        "alignment_detail",
        "wall_time",
        "seconds_compute",
        "seconds_wait",
        "alive_ages",
        "suspects",
        "views",
    )


#: Status.views: training keyframes, held out and dropped so far, the newest's age (s, or None)
#: and the extent of the camera centres per axis ([3], or None).
VIEWS_FIELDS = ("keyframes", "held_out", "dropped", "newest_age_s", "coverage")


@dataclass
class KeyframeSummary:
    """Compact keyframe features for a coarse initial relative pose (never images).

    ``descriptors`` [P, D] uint8 (binary, e.g. ORB) or float32; ``points`` [P, 3] float32, the
    3-D points in the sender's frame; ``keyframe_index`` [P] int32, which keyframe each came
    from. ``image_bytes`` is informational (how much image data this summary stands for).
    Optional, together: ``keypoints`` [P, 2] float32, each feature's pixel position in its
    keyframe, and ``keyframe_cameras`` [K, 16] float32, each keyframe's camera-to-world rows 0-2
    and fx, fy, cx, cy; with them a receiver can measure matches in pixels.
    ``box_from_shared`` [4, 4] float64, optional: the field box the sender uses (a similarity
    from the shared frame onto [-1, 1]^3). Robots with images only cannot know it in advance: the
    reference derives it from its own SfM and it travels outward with the keyframes.
    """

    swarm: str
    sender: int
    round: int
    epoch: int
    descriptors: np.ndarray
    points: np.ndarray
    keyframe_index: np.ndarray
    image_bytes: int = 0
    keypoints: np.ndarray | None = None
    keyframe_cameras: np.ndarray | None = None
    box_from_shared: np.ndarray | None = None
    header: Header | None = None

    kind = KIND_KEYFRAMES


Message = ThetaSnapshot | Status | KeyframeSummary

MESSAGE_TYPES: dict[str, type] = {KIND_THETA: ThetaSnapshot, KIND_STATUS: Status, KIND_KEYFRAMES: KeyframeSummary}


# --------------------------------------------------------------------------- field checks


def similarity_problem(m: Any) -> str | None:
    """Why ``m`` is not a usable 4x4 similarity (``s R x + t``, s > 0), or None if it is.

    A field box from a peer goes straight into every ray's coordinates: a shear, a reflection or
    a degenerate scale would corrupt the model silently, so it is refused here.
    """
    try:
        a = np.asarray(m, dtype=np.float64)
    except (TypeError, ValueError):
        return "not a numeric matrix"
    if a.shape != (4, 4):
        return f"shape {list(a.shape)[:4]}, want [4, 4]"
    if not np.isfinite(a).all():
        return "non-finite entries"
    if not np.array_equal(a[3], [0.0, 0.0, 0.0, 1.0]):
        return "last row must be 0 0 0 1"
    sr = a[:3, :3]
    with np.errstate(all="ignore"):  # huge entries overflow to inf or NaN, refused below without a warning
        scale = float(np.cbrt(np.linalg.det(sr)))
        if not 1e-6 < scale < 1e6:
            return f"scale {scale:.3g} outside (1e-6, 1e6), or a reflection"
        error = np.abs(sr.T @ sr / scale**2 - np.eye(3)).max()
    if not error <= 1e-4:  # so that NaN is refused too
        return "not a scaled rotation"
    return None


def is_int(x: Any) -> bool:
    """True for a real int (bools are ints in Python but never valid here)."""
    return type(x) is int


def is_number(x: Any) -> bool:
    return type(x) in (int, float)


def _check_status_shape(body: Any) -> None:
    """A map of exactly the body fields, before any field is read."""
    if not isinstance(body, dict):
        raise Rejected("bad_field", "status body is not a map")
    keys = set(body)
    expected = set(Status.BODY_FIELDS)
    if keys != expected:
        missing, extra = sorted(expected - keys), sorted(describe(k) for k in keys - expected)[:4]
        raise Rejected("bad_field", f"status fields missing {missing} extra {extra}")


def check_status_body(body: Any) -> dict[str, Any]:
    """Validate a decoded Status body (a dict from msgpack); raise Rejected('bad_field'|...)."""
    _check_status_shape(body)

    def bad(name: str, what: str) -> Rejected:
        return Rejected("bad_field", f"status.{name}: {what}")

    def finite_number(name: str, allow_none: bool = False) -> float | None:
        v = body[name]
        if v is None and allow_none:
            return None
        if not is_number(v):
            raise bad(name, f"expected a number, got {type(v).__name__}")
        if not math.isfinite(v):
            raise Rejected("non_finite", f"status.{name} = {v}")
        return float(v)

    def count(name: str) -> int:
        v = body[name]
        if not is_int(v) or v < 0 or v > 2**63 - 1:
            raise bad(name, "expected a non-negative integer")
        return v

    def text(name: str, limit: int = 256) -> str:
        v = body[name]
        if not isinstance(v, str) or len(v) > limit:
            raise bad(name, f"expected a string of at most {limit} characters")
        return v

    out: dict[str, Any] = {}
    ref = body["reference"]
    if not is_int(ref) or not 0 <= ref <= MAX_ROUND:
        raise bad("reference", "expected a robot id")
    out["reference"] = ref
    out["phase"] = text("phase")
    state = body["alignment"]  # a str before the enum sees it: its error message reprs any value, however deep
    if not isinstance(state, str) or state not in {a.value for a in Alignment}:
        raise bad("alignment", f"expected one of {[a.value for a in Alignment]}")
    out["alignment"] = Alignment(state)
    out["alignment_detail"] = text("alignment_detail")
    out["loss"] = finite_number("loss", allow_none=True)
    out["psnr"] = finite_number("psnr", allow_none=True)
    pose = body["pose"]
    if not isinstance(pose, list) or len(pose) != 7 or not all(is_number(v) for v in pose):
        raise bad("pose", "expected a list of 7 numbers (log_scale, phi xyz, t xyz)")
    if not all(math.isfinite(v) for v in pose):
        raise Rejected("non_finite", "status.pose")
    out["pose"] = [float(v) for v in pose]
    heard = body["neighbours_heard"]
    if not isinstance(heard, list) or not all(is_int(v) and 0 <= v <= MAX_ROUND for v in heard):
        raise bad("neighbours_heard", "expected a list of robot ids")
    out["neighbours_heard"] = list(heard)
    out["bytes_in"] = count("bytes_in")
    out["bytes_out"] = count("bytes_out")
    rej = body["rejected"]
    if not isinstance(rej, dict) or not all(
        isinstance(k, str) and len(k) <= 64 and is_int(v) and v >= 0 for k, v in rej.items()
    ):
        raise bad("rejected", "expected a map reason -> non-negative count")
    out["rejected"] = dict(rej)
    for name in ("wall_time", "seconds_compute", "seconds_wait"):
        v = finite_number(name)
        if v is None or v < 0:
            raise bad(name, "expected a non-negative number")
        out[name] = v
    out["alive_ages"], out["suspects"] = _check_peers(body["alive_ages"], body["suspects"], bad)
    out["views"] = _check_views(body["views"], bad)
    return out


def _check_peers(ages: Any, suspects: Any, bad: Callable[[str, str], Rejected]) -> tuple[dict, dict]:
    """Status.alive_ages and Status.suspects: what a robot says about the others."""
    if not isinstance(ages, list) or not all(
        isinstance(p, list) and len(p) == 2 and is_int(p[0]) and 0 <= p[0] <= MAX_ROUND and is_number(p[1])
        and math.isfinite(p[1]) and p[1] >= 0
        for p in ages
    ):
        raise bad("alive_ages", "expected a list of [robot id, non-negative age in seconds]")
    if not isinstance(suspects, list) or len(suspects) > 1024 or not all(
        isinstance(p, list) and len(p) == 2 and is_int(p[0]) and 0 <= p[0] <= MAX_ROUND and p[1] in SUSPICIONS
        for p in suspects
    ):
        raise bad("suspects", f"expected a list of [robot id, one of {list(SUSPICIONS)}]")
    return {int(i): float(a) for i, a in ages}, {int(i): str(why) for i, why in suspects}


def _check_views(views: Any, bad: Callable[[str, str], Rejected]) -> dict | None:
    if views is None:
        return None
    if not isinstance(views, dict) or set(views) != set(VIEWS_FIELDS):
        raise bad("views", f"expected a map of exactly {list(VIEWS_FIELDS)}")
    for name in ("keyframes", "held_out", "dropped"):
        if not is_int(views[name]) or not 0 <= views[name] <= MAX_ROUND:
            raise bad("views", f"{name}: expected a non-negative count")
    age, cover = views["newest_age_s"], views["coverage"]
    if age is not None and not (is_number(age) and math.isfinite(age) and age >= 0):
        raise bad("views", "newest_age_s: expected a non-negative number or nil")
    if cover is not None and not (isinstance(cover, list) and len(cover) == 3 and all(
            is_number(v) and math.isfinite(v) and v >= 0 for v in cover)):
        raise bad("views", "coverage: expected 3 non-negative numbers or nil")
    return {k: views[k] if k != "coverage" or cover is None else [float(v) for v in cover] for k in VIEWS_FIELDS}


def status_body(msg: Status) -> dict[str, Any]:
    """The body fields of a Status, as plain Python values ready for msgpack."""
    return {
        "reference": int(msg.reference),
        "phase": str(msg.phase),
        "loss": None if msg.loss is None else float(msg.loss),
        "psnr": None if msg.psnr is None else float(msg.psnr),
        "pose": [float(v) for v in msg.pose],
        "neighbours_heard": [int(v) for v in msg.neighbours_heard],
        "bytes_in": int(msg.bytes_in),
        "bytes_out": int(msg.bytes_out),
        "rejected": {str(k): int(v) for k, v in msg.rejected.items()},
        "alignment": Alignment(msg.alignment).value,
        "alignment_detail": str(msg.alignment_detail),
        "wall_time": float(msg.wall_time),
        "seconds_compute": float(msg.seconds_compute),
        "seconds_wait": float(msg.seconds_wait),
        "alive_ages": [[int(i), float(a)] for i, a in sorted(msg.alive_ages.items())],
        "suspects": [[int(i), str(why)] for i, why in sorted(msg.suspects.items())],
        "views": None if msg.views is None else {
            "keyframes": int(msg.views["keyframes"]), "held_out": int(msg.views["held_out"]),
            "dropped": int(msg.views["dropped"]),
            "newest_age_s": None if msg.views["newest_age_s"] is None else float(msg.views["newest_age_s"]),
            "coverage": None if msg.views["coverage"] is None else [float(v) for v in msg.views["coverage"]]},
    }
