"""A robot's own ROS 2 topics over Zenoh, as rmw_zenoh carries them: subscriber, and a publisher for tests.

The daemon connects as a Zenoh *client* to the robot's local router (``rmw_zenohd``, default
``tcp/localhost:7447``) and subscribes to the camera, its CameraInfo, ``/tf`` and ``/tf_static``
in rmw_zenoh's key expressions and attachment (:mod:`protocol.rmw_format`, which names the
release followed). Payloads are CDR, decoded with ``rosbags``; what reaches ``on_message`` is the
deserialised message (numpy arrays inside) with its attachment, never torch: the agent turns it
into keyframes (:mod:`agent.data.stream`).

A message is delivered once per (publisher gid, sequence number): a publisher that stops and comes
back (a new process: a new gid) is heard again from its first message, and nothing already
received is lost or repeated. ``/tf_static`` is transient-local in ROS 2: rmw_zenoh publishes it
with a cache and subscribes with history, so does this module, and a late subscriber still gets it.

:class:`RosTopicPublisher` writes the same keys from CDR bytes (a bag's, :func:`replay_bag`): the
tests' stand-in for a robot's camera driver, since no ROS runtime is installable here.
"""

from __future__ import annotations

import hashlib
import json
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from itertools import islice
from typing import Callable, Iterable

import zenoh
import zenoh.ext

from protocol.pacing import paced
from protocol.rmw_format import (HASH_NOT_SUPPORTED, Attachment, AttachmentError, parse_topic_key, topic_key,
                                 topic_key_pattern)

__all__ = ["RosMessage", "RosTopicSubscriber", "RosTopicPublisher", "replay_bag", "open_router", "type_hash", "TRANSIENT_TOPICS"]

TRANSIENT_TOPICS = ("/tf_static",)  # published transient-local by ROS 2 (tf2_ros.StaticTransformBroadcaster)


def _typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


_STORE = None


def _store():
    global _STORE
    if _STORE is None:
        _STORE = _typestore()
    return _STORE


def type_hash(ros_type: str) -> str:
    """The RIHS01 hash rmw_zenoh puts in the key (Jazzy's definitions; rosbags computes it)."""
    try:
        return _store().hash_rihs01(ros_type)
    except (KeyError, ValueError):
        return HASH_NOT_SUPPORTED


@dataclass
class RosMessage:
    topic: str
    ros_type: str
    message: object  # the deserialised message (rosbags' dataclasses; arrays as numpy)
    attachment: Attachment
    received_ns: int  # time.time_ns() when it arrived


def _client_config(connect: Iterable[str], mode: str = "client", listen: Iterable[str] = (),
                   connect_timeout_s: float = 10.0) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    conf.insert_json5("scouting/multicast/enabled", "false")
    # rmw_zenoh's own session config turns timestamping on; transient-local caches need it
    conf.insert_json5("timestamping/enabled", json.dumps({"router": True, "peer": True, "client": True}))
    # the router must answer within the timeout (else one error, not a hang); once connected, a
    # client reconnects by itself when the router restarts
    ms = int(connect_timeout_s * 1000)
    conf.insert_json5("connect/timeout_ms", json.dumps({"client": ms, "peer": ms, "router": ms}))
    conf.insert_json5("connect/exit_on_failure", json.dumps({"client": True, "peer": False, "router": False}))
    return conf


@dataclass
class _Seen:
    """Sequence numbers delivered per publisher gid (a window: old ones are forgotten)."""

    window: int = 4096
    by_gid: dict[bytes, set[int]] = field(default_factory=dict)

    def first_time(self, gid: bytes, seq: int) -> bool:
        seen = self.by_gid.setdefault(gid, set())
        if seq in seen:
            return False
        seen.add(seq)
        if len(seen) > 2 * self.window:
            newest = max(seen)
            self.by_gid[gid] = {s for s in seen if s > newest - self.window}
        return True


class RosTopicSubscriber:
    """Subscribes to ROS 2 topics (``(topic, ros type)`` pairs) as a Zenoh client of ``connect``."""

    def __init__(self, connect: list[str], topics: Iterable[tuple[str, str]], on_message: Callable[[RosMessage], None],
                 domain_id: int = 0, on_refused: Callable[[str, str], None] | None = None,
                 connect_timeout_s: float = 10.0) -> None:
        if not connect:
            raise ValueError("no endpoint to connect to (the robot's Zenoh router, e.g. tcp/localhost:7447)")
        self.connect, self.topics, self.domain_id = list(connect), set(topics), domain_id
        self.connect_timeout_s = connect_timeout_s
        self.patterns = {(t, ty): topic_key_pattern(domain_id, t, ty) for t, ty in self.topics}
        self.on_message, self.on_refused = on_message, on_refused or (lambda reason, detail: None)
        self.expected_hash = {ty: type_hash(ty) for _, ty in self.topics}
        self.refused: dict[str, int] = {}
        self.received = 0
        self.duplicates = 0
        self._seen = _Seen()
        self._lock = threading.Lock()
        self._session: zenoh.Session | None = None
        self._subs: list = []

    def open(self) -> "RosTopicSubscriber":
        try:
            self._session = zenoh.open(_client_config(self.connect, connect_timeout_s=self.connect_timeout_s))
        except zenoh.ZError as e:
            raise ConnectionError(f"no Zenoh router answered at {', '.join(self.connect)} within "
                                  f"{self.connect_timeout_s:g} s (is the robot's rmw_zenohd running?): "
                                  f"{str(e).split(' at /')[0][:160]}") from None
        for (topic, _), pattern in self.patterns.items():
            if topic in TRANSIENT_TOPICS:
                sub = zenoh.ext.declare_advanced_subscriber(
                    self._session, pattern, self._on_sample,
                    history=zenoh.ext.HistoryConfig(detect_late_publishers=True))
            else:
                sub = self._session.declare_subscriber(pattern, self._on_sample)
            self._subs.append(sub)
        return self

    def close(self) -> None:
        for sub in self._subs:
            try:
                sub.undeclare()
            except zenoh.ZError:
                pass
        self._subs = []
        if self._session is not None:
            self._session.close()
            self._session = None

    def _refuse(self, reason: str, detail: str) -> None:
        with self._lock:
            self.refused[reason] = self.refused.get(reason, 0) + 1
        self.on_refused(reason, detail)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        now = time.time_ns()
        key = str(sample.key_expr)
        try:
            _, topic, ros_type, hash_ = parse_topic_key(key)
        except ValueError as e:
            return self._refuse("bad_key", str(e))
        if (topic, ros_type) not in self.topics:
            return self._refuse("bad_key", f"{key}: not a subscribed topic and type")
        if hash_ not in (self.expected_hash[ros_type], HASH_NOT_SUPPORTED):
            return self._refuse("type_hash", f"{topic}: type hash {hash_} is not {ros_type}'s as this robot knows "
                                             f"it ({self.expected_hash[ros_type]}): another message definition")
        try:
            att = Attachment.decode(sample.attachment.to_bytes() if sample.attachment is not None else None)
        except AttachmentError as e:
            return self._refuse("bad_attachment", f"{topic}: {e}")
        with self._lock:
            fresh = self._seen.first_time(att.gid, att.sequence_number)
            self.duplicates += not fresh
        if not fresh:
            return None
        try:
            msg = _store().deserialize_cdr(sample.payload.to_bytes(), ros_type)
        except Exception as e:  # rosbags raises whatever a truncated buffer gives: all are bad input
            return self._refuse("bad_cdr", f"{topic}: the payload is not a {ros_type} in CDR ({type(e).__name__})")
        with self._lock:
            self.received += 1
        self.on_message(RosMessage(topic, ros_type, msg, att, now))
        return None


def open_router(listen: list[str]):
    """A Zenoh router on ``listen``: what ``rmw_zenohd`` is to a robot's nodes (tests, benchmarks).
    Returns the session; closing it stops the router."""
    return zenoh.open(_client_config([], "router", listen))


class RosTopicPublisher:
    """Publishes CDR bytes on rmw_zenoh's keys with its attachment (tests, benchmarks, tools)."""

    def __init__(self, connect: list[str] = (), listen: list[str] = (), domain_id: int = 0,
                 mode: str = "peer", match_timeout_s: float = 0.0) -> None:
        """match_timeout_s: wait this long at a topic's first message for a subscriber to match it
        (a camera driver does not wait; a test that counts every message does)."""
        self.domain_id, self.match_timeout_s = domain_id, match_timeout_s
        self._session = zenoh.open(_client_config(connect, mode, listen))
        zid = str(self._session.info.zid())
        self._pubs: dict[str, tuple[object, bytes, list[int]]] = {}  # topic -> (publisher, gid, [seq])
        self._zid = zid

    def publish(self, topic: str, ros_type: str, cdr: bytes, stamp_ns: int | None = None) -> Attachment:
        entry = self._pubs.get(topic)
        if entry is None:
            key = topic_key(self.domain_id, topic, ros_type, type_hash(ros_type))
            if topic in TRANSIENT_TOPICS:
                pub = zenoh.ext.declare_advanced_publisher(self._session, key, cache=zenoh.ext.CacheConfig(max_samples=16),
                                                           publisher_detection=True)
            else:
                pub = self._session.declare_publisher(key, reliability=zenoh.Reliability.RELIABLE,
                                                      congestion_control=zenoh.CongestionControl.BLOCK)
                deadline = time.monotonic() + self.match_timeout_s
                while not pub.matching_status.matching and time.monotonic() < deadline:
                    time.sleep(0.01)
            gid = hashlib.blake2b(f"{self._zid}/{key}".encode(), digest_size=16).digest()
            entry = self._pubs[topic] = (pub, gid, [0])
        pub, gid, seq = entry
        seq[0] += 1
        att = Attachment(seq[0], time.time_ns() if stamp_ns is None else stamp_ns, gid)
        pub.put(cdr, attachment=att.encode())
        return att

    def close(self) -> None:
        for pub, _, _ in self._pubs.values():
            try:
                pub.undeclare()
            except zenoh.ZError:
                pass
        self._pubs = {}
        self._session.close()


def replay_bag(path: str | Path, publisher: RosTopicPublisher, rate: float = 1.0, *, skip: int = 0,
               count: int | None = None, stop: threading.Event | None = None,
               topics: Iterable[str] | None = None) -> int:
    """Publish a rosbag2's messages in their recorded order and pace (``rate`` x; 0: as fast as
    possible), from the ``skip``-th message on, ``count`` of them; returns how many were published."""
    from rosbags.highlevel import AnyReader

    wanted = None if topics is None else set(topics)
    published = 0
    with AnyReader([Path(path)], default_typestore=_store()) as reader:
        conns = [c for c in reader.connections if wanted is None or c.topic in wanted]
        stamped = ((t, (conn, raw)) for conn, t, raw in reader.messages(connections=conns))
        for conn, raw in paced(islice(stamped, skip, None if count is None else skip + count), rate, stop):
            publisher.publish(conn.topic, conn.msgtype, bytes(raw))
            published += 1
    return published
