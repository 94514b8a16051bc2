"""Zenoh key expressions, built and parsed in this one place.

Layout (``<swarm>`` is validated, robot ids and rounds are non-negative decimal integers)::

    dinerf/<swarm>/alive/<id>           liveliness token of a running robot
    dinerf/<swarm>/theta/<id>/<round>/<to>  parameter snapshot of robot <id> after <round>, for <to>
    dinerf/<swarm>/latest/<id>          queryable: the newest snapshot of <id> (late join, restart)
    dinerf/<swarm>/latest/<id>?min_round=<k>   ... only if that snapshot is of round k or later
    dinerf/<swarm>/latest/<id>?min_round=<k>;held=<b>   ... as the deltas from round b if cheaper
    dinerf/<swarm>/status/<id>          telemetry
    dinerf/<swarm>/keyframes/<id>       queryable: compact keyframe summary for coarse alignment

Usage::

    keys = Keys("lab")
    keys.theta(3, 12, to=5)      # 'dinerf/lab/theta/3/12/5'
    keys.parse('dinerf/lab/theta/3/12/5') # ParsedKey(kind='theta', robot_id=3, round=12, receiver=5)

Snapshots are addressed to one neighbour each (``<to>``): Zenoh routes a put only to the
sessions with a matching subscriber, so a dead or congested link delays that neighbour's copy
only. With one key for all neighbours, a put with congestion control BLOCK waited on the worst
link for every neighbour (measured: 20 s stalls of the whole ring after one cut link).

:meth:`Keys.parse` raises :class:`ForeignKey` for anything that is not one of *our* keys (other
swarm, unknown kind, non-canonical numbers), so a sender id is only ever taken from a key that
this module would have built itself. Pure Python: no zenoh, no torch.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

ROOT = "dinerf"
#: Largest robot id / round a key may carry (signed 32-bit, like the message header).
MAX_ID = 2**31 - 1

KIND_ALIVE = "alive"
KIND_THETA = "theta"
KIND_LATEST = "latest"
KIND_STATUS = "status"
KIND_KEYFRAMES = "keyframes"
#: Key kinds and the number of segments after the robot id (theta: round and receiver).
KEY_KINDS: dict[str, int] = {
    KIND_ALIVE: 0,
    KIND_THETA: 2,
    KIND_LATEST: 0,
    KIND_STATUS: 0,
    KIND_KEYFRAMES: 0,
}

#: Query parameters of :meth:`Keys.latest_since` (read back with :func:`min_round_of`).
MIN_ROUND_PARAM = "min_round"
HELD_PARAM = "held"  # the round of the asker's base of that robot: the answer may be deltas from it

_SWARM_RE = re.compile(r"[A-Za-z0-9_-]{1,64}")
_CANONICAL_INT_RE = re.compile(r"0|[1-9][0-9]{0,9}")


class ForeignKey(ValueError):
    """A key expression that is not one of this swarm's keys."""


def min_round_of(value: str | None) -> int | None:
    """The round of a ``min_round`` query parameter; None when absent or not a canonical number
    (a malformed parameter is treated as absent: the query is answered as a plain one)."""
    return None if value is None else _parse_number(value)


@dataclass(frozen=True)
class ParsedKey:
    kind: str
    robot_id: int
    round: int | None = None
    receiver: int | None = None


def validate_swarm(swarm: str) -> str:
    """Return ``swarm`` if it is a usable swarm name, else raise ValueError saying why."""
    if not isinstance(swarm, str) or not _SWARM_RE.fullmatch(swarm):
        raise ValueError(
            f"invalid swarm name {swarm!r}: use 1-64 characters from A-Z a-z 0-9 _ - "
            "(no '/', '*', '$', '?', '#', spaces)"
        )
    return swarm


def _check_number(value: int, what: str) -> str:
    if type(value) is not int or not 0 <= value <= MAX_ID:
        raise ValueError(f"{what} must be an integer in [0, {MAX_ID}], got {value!r}")
    return str(value)


def _parse_number(text: str) -> int | None:
    if not _CANONICAL_INT_RE.fullmatch(text):
        return None
    value = int(text)
    return value if value <= MAX_ID else None


class Keys:
    """Key expressions of one swarm."""

    def __init__(self, swarm: str):
        self.swarm = validate_swarm(swarm)
        self.prefix = f"{ROOT}/{self.swarm}"

    def __repr__(self) -> str:
        return f"Keys({self.swarm!r})"

    def _robot(self, kind: str, robot_id: int) -> str:
        return f"{self.prefix}/{kind}/{_check_number(robot_id, 'robot id')}"

    # -- concrete keys
    def alive(self, robot_id: int) -> str:
        return self._robot(KIND_ALIVE, robot_id)

    def theta(self, robot_id: int, round: int, to: int) -> str:
        """Robot ``robot_id``'s snapshot after ``round``, addressed to neighbour ``to``."""
        return (f"{self._robot(KIND_THETA, robot_id)}/{_check_number(round, 'round')}/"
                f"{_check_number(to, 'receiver id')}")

    def latest(self, robot_id: int) -> str:
        return self._robot(KIND_LATEST, robot_id)

    def latest_since(self, robot_id: int, min_round: int, held: int | None = None) -> str:
        """Selector for ``robot_id``'s newest snapshot, answered only if its round is >= ``min_round``:
        a neighbour that has not got that far replies nothing, so asking costs no snapshot. With
        ``held`` (the round of our base of it) the answer may be the deltas since that round."""
        selector = f"{self.latest(robot_id)}?{MIN_ROUND_PARAM}={_check_number(min_round, 'round')}"
        return selector if held is None else f"{selector};{HELD_PARAM}={_check_number(held, 'round')}"

    def status(self, robot_id: int) -> str:
        return self._robot(KIND_STATUS, robot_id)

    def keyframes(self, robot_id: int) -> str:
        return self._robot(KIND_KEYFRAMES, robot_id)

    # -- wildcards (for subscribers and queries)
    def alive_all(self) -> str:
        return f"{self.prefix}/{KIND_ALIVE}/*"

    def theta_for(self, robot_id: int, receiver: int) -> str:
        """Every round of ``robot_id``'s snapshots addressed to ``receiver`` (what a robot subscribes to)."""
        return f"{self._robot(KIND_THETA, robot_id)}/*/{_check_number(receiver, 'receiver id')}"

    def theta_of(self, robot_id: int) -> str:
        """Every snapshot of one robot, to anyone."""
        return f"{self._robot(KIND_THETA, robot_id)}/*/*"

    def theta_all(self) -> str:
        return f"{self.prefix}/{KIND_THETA}/*/*/*"

    def latest_all(self) -> str:
        return f"{self.prefix}/{KIND_LATEST}/*"

    def status_all(self) -> str:
        return f"{self.prefix}/{KIND_STATUS}/*"

    def keyframes_all(self) -> str:
        return f"{self.prefix}/{KIND_KEYFRAMES}/*"

    # -- parsing
    def parse(self, key: str) -> ParsedKey:
        """Parse one of this swarm's concrete keys; raise :class:`ForeignKey` otherwise."""
        if not isinstance(key, str):
            raise ForeignKey(f"key must be a string, got {type(key).__name__}")
        parts = key.split("/")
        if len(parts) < 4 or parts[0] != ROOT:
            raise ForeignKey(f"not a dinerf key: {key[:200]!r}")
        if parts[1] != self.swarm:
            raise ForeignKey(f"key of swarm {parts[1][:64]!r}, not {self.swarm!r}: {key[:200]!r}")
        kind = parts[2]
        if kind not in KEY_KINDS:
            raise ForeignKey(f"unknown key kind {kind[:64]!r} in {key[:200]!r}")
        extra = KEY_KINDS[kind]
        if len(parts) != 4 + extra:
            raise ForeignKey(f"wrong number of segments for a {kind} key: {key[:200]!r}")
        robot_id = _parse_number(parts[3])
        if robot_id is None:
            raise ForeignKey(f"bad robot id {parts[3][:32]!r} in {key[:200]!r}")
        round_ = receiver = None
        if extra:
            round_ = _parse_number(parts[4])
            if round_ is None:
                raise ForeignKey(f"bad round {parts[4][:32]!r} in {key[:200]!r}")
            receiver = _parse_number(parts[5])
            if receiver is None:
                raise ForeignKey(f"bad receiver id {parts[5][:32]!r} in {key[:200]!r}")
        return ParsedKey(kind, robot_id, round_, receiver)
