"""The Zenoh peer session of one robot: the only module of dinerf that imports zenoh.

::

    cfg = TransportConfig(listen=["tcp/127.0.0.1:7501"], connect=["tcp/127.0.0.1:7500"])
    with ZenohTransport(cfg, Keys("lab"), robot_id=1) as net:
        net.declare_alive()
        net.watch_alive(lambda ids: membership.update(ids))      # full set on every change
        net.subscribe(keys.theta_for(0, 1), on_bytes)             # on_bytes(key: str, data: bytes)
        net.publish(keys.theta(1, 7, to=0), encode(snapshot))     # BLOCK + reliable
        net.set_latest(encoded, round=7)                          # served on latest/1
        data = net.query(keys.latest(0), timeout=5.0)             # bytes or None
        data = net.query(keys.latest_since(0, 8), timeout=5.0)    # None until robot 0 serves round 8

Why these choices:

- Snapshots are published with ``CongestionControl.BLOCK`` and reliable delivery: with the
  default DROP a 64 MB put is silently lost (zenoh#2258). BLOCK closes a link that stays
  blocked longer than ``block_wait_before_close_ms``, half the lease by default: while a put
  waits on a cut link the whole session stops sending, keep-alives included, so a wait as
  long as the lease (Zenoh's default is 5 s) lets the healthy links expire too. A slow but live
  link (10% loss, 100 ms each way) frees a queue slot well within it. Periodic messages (status)
  and replies to queries over a link that may be dying use DROP.
- The lease (``lease_ms``, ~2 s) bounds how long a hung robot or a cut link looks alive; a
  killed process is seen at once because its TCP link closes.
- ``transport/link/rx/max_message_size`` is set to ``max_message_bytes`` so Zenoh itself refuses
  to reassemble anything larger, before the codec's own caps.
- Callbacks run on Zenoh threads: they are wrapped so an exception never escapes into Zenoh
  (it is logged and counted in ``stats()["callback_errors"]``). Keep user callbacks short:
  hand the bytes to a queue or :class:`protocol.rounds.Mailbox` and decode elsewhere, and never
  call a blocking method of the transport (``query``, ``alive_now``, ``publish``) from a callback.
- ``close()`` is idempotent, never blocks on a second call and never raises, so it can be
  called from a signal handler path and from ``__exit__`` alike.

Byte counters count payload bytes (Zenoh framing excluded): out per destination kind (theta,
status, latest, keyframes ...), in per sender id parsed from the key.
"""

from __future__ import annotations

import json
import logging
import os
import threading
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any, Callable

import zenoh

from protocol.keys import ForeignKey, Keys
from protocol.network import Served

log = logging.getLogger("dinerf.transport")

MiB = 1024 * 1024


class TransportError(RuntimeError):
    """The Zenoh session could not be opened or used (bad endpoint, port in use, closed ...)."""


@dataclass
class TransportConfig:
    """How this robot joins the swarm network. Defaults work on loopback."""

    listen: list[str] = field(default_factory=lambda: ["tcp/127.0.0.1:0"])
    connect: list[str] = field(default_factory=list)
    multicast_scouting: bool = False
    lease_ms: int = 2000
    # BLOCK put's wait for queue room before Zenoh closes the link; None: half the lease (a blocked put stops all keep-alives)
    block_wait_before_close_ms: int | None = None
    # Zenoh's rx/tx runtime threads (its defaults 2, 1): closing a cut link's socket blocks one for 10 s (SO_LINGER)
    rx_threads: int = 8
    tx_threads: int = 4
    # Reconnect backoff for configured endpoints after a session is lost (a healed link is
    # used again within about reconnect_max_ms).
    reconnect_init_ms: int = 250
    reconnect_max_ms: int = 2_000
    query_timeout_s: float = 10.0
    max_message_bytes: int = 512 * MiB
    # TLS (endpoints then use tls/host:port). cert/key are used for both listening and connecting.
    tls_root_ca: str | None = None
    tls_cert: str | None = None
    tls_key: str | None = None
    #: None: on whenever TLS is used (both ends must present a certificate of the swarm CA)
    enable_mtls: bool | None = None
    tls_verify_name_on_connect: bool = True
    #: Zenoh access control (``protocol.acl``: who may say what, by certificate name); needs mTLS.
    #: Built from the swarm file's roster, not written by hand.
    access_control: dict[str, Any] | None = None
    #: Raw Zenoh config overrides: key path -> json5 value, applied last (e.g.
    #: {"transport/link/tx/queue/size/data": "4"}).
    extra: dict[str, str] = field(default_factory=dict)

    def validate(self) -> None:
        """Raise ValueError with a clear message for an unusable configuration."""
        for name in ("listen", "connect"):
            eps = getattr(self, name)
            if not isinstance(eps, list) or not all(isinstance(e, str) and "/" in e for e in eps):
                raise ValueError(f"{name} must be a list of endpoints like 'tcp/127.0.0.1:7447', got {eps!r}")
        if not self.listen and not self.connect and not self.multicast_scouting:
            raise ValueError("no listen or connect endpoints and multicast scouting off: this robot could never meet a peer")
        if type(self.lease_ms) is not int or self.lease_ms < 100:
            raise ValueError("lease_ms must be an integer >= 100")
        for name in ("rx_threads", "tx_threads"):
            n = getattr(self, name)
            if type(n) is not int or not 1 <= n <= 64:
                raise ValueError(f"{name} must be an integer in 1..64, got {n!r}")
        wait = self.block_wait_before_close_ms
        if wait is not None and (type(wait) is not int or not 0 < wait < self.lease_ms):
            raise ValueError(f"block_wait_before_close_ms must be a positive integer below lease_ms "
                             f"({self.lease_ms}), got {wait!r}: a put blocked for longer starves every link")
        if not (type(self.reconnect_init_ms) is int and type(self.reconnect_max_ms) is int
                and 0 < self.reconnect_init_ms <= self.reconnect_max_ms):
            raise ValueError("need integers 0 < reconnect_init_ms <= reconnect_max_ms")
        if not self.query_timeout_s > 0:
            raise ValueError("query_timeout_s must be positive")
        if type(self.max_message_bytes) is not int or self.max_message_bytes < 64 * 1024:
            raise ValueError("max_message_bytes must be an integer >= 65536")
        for name in ("tls_root_ca", "tls_cert", "tls_key"):
            path = getattr(self, name)
            if path is not None and not os.path.isfile(path):
                raise ValueError(f"{name}: no such file {path!r}")
        if (self.tls_cert is None) != (self.tls_key is None):
            raise ValueError("tls_cert and tls_key go together")
        if self.mtls() and not (self.tls_root_ca and self.tls_cert and self.tls_key):
            raise ValueError("mutual TLS (on whenever TLS is used) needs tls_root_ca, tls_cert and tls_key; "
                             "set enable_mtls = false explicitly to accept peers without a certificate")
        if self.uses_tls() and not self.tls_root_ca:
            raise ValueError("tls/ endpoints need tls_root_ca (and tls_cert/tls_key to listen)")
        if self.access_control is not None:
            if not isinstance(self.access_control, dict):
                raise ValueError("access_control must be a table (see protocol.acl)")
            if not (self.uses_tls() and self.mtls()):
                raise ValueError("access_control names peers by their certificates: it needs tls/ endpoints "
                                 "and mutual TLS")
        for k, v in self.extra.items():
            if not isinstance(k, str) or not isinstance(v, str):
                raise ValueError(f"extra must map config paths to json5 strings, got {k!r}: {v!r}")

    def uses_tls(self) -> bool:
        return any(e.startswith("tls/") for e in self.listen + self.connect)

    def mtls(self) -> bool:
        """Mutual TLS: as configured, else on whenever TLS is (endpoints or certificates)."""
        if self.enable_mtls is not None:
            return self.enable_mtls
        return self.uses_tls() or bool(self.tls_root_ca or self.tls_cert)

    def block_wait_ms(self) -> int:
        """The BLOCK wait Zenoh gets: the configured one, else half the lease."""
        return self.block_wait_before_close_ms if self.block_wait_before_close_ms is not None else self.lease_ms // 2

    def zenoh_settings(self) -> dict[str, str]:
        """The Zenoh config entries (path -> json5 value) this config stands for, in order."""
        self.validate()
        s: dict[str, str] = {
            "mode": json.dumps("peer"),
            "listen/endpoints": json.dumps(self.listen),
            "connect/endpoints": json.dumps(self.connect),
            "scouting/multicast/enabled": json.dumps(self.multicast_scouting),
            "transport/link/tx/lease": json.dumps(self.lease_ms),
            "transport/link/tx/threads": json.dumps(self.tx_threads),
            # Zenoh counts this one in microseconds
            "transport/link/tx/queue/congestion_control/block/wait_before_close": json.dumps(
                self.block_wait_ms() * 1000),
            "transport/link/rx/max_message_size": json.dumps(self.max_message_bytes),
            "connect/retry": json.dumps({"period_init_ms": self.reconnect_init_ms,
                                         "period_max_ms": self.reconnect_max_ms,
                                         "period_increase_factor": 2.0}),
        }
        if self.tls_root_ca:
            s["transport/link/tls/root_ca_certificate"] = json.dumps(self.tls_root_ca)
        if self.tls_cert and self.tls_key:
            s["transport/link/tls/listen_certificate"] = json.dumps(self.tls_cert)
            s["transport/link/tls/listen_private_key"] = json.dumps(self.tls_key)
            s["transport/link/tls/connect_certificate"] = json.dumps(self.tls_cert)
            s["transport/link/tls/connect_private_key"] = json.dumps(self.tls_key)
        if self.tls_root_ca or self.tls_cert:
            s["transport/link/tls/enable_mtls"] = json.dumps(self.mtls())
            s["transport/link/tls/verify_name_on_connect"] = json.dumps(self.tls_verify_name_on_connect)
        if self.access_control is not None:
            s["access_control"] = json.dumps(self.access_control)
        s.update(self.extra)
        return s

    def to_zenoh(self) -> zenoh.Config:
        conf = zenoh.Config()
        for path, value in self.zenoh_settings().items():
            try:
                conf.insert_json5(path, value)
            except Exception as exc:
                raise ValueError(f"Zenoh refuses config {path} = {value}: {exc}") from None
        return conf


class Subscription:
    """Handle of a subscription: call :meth:`undeclare` to stop receiving."""

    def __init__(self, transport: "ZenohTransport", zenoh_handle: Any, key_expr: str):
        self._transport = transport
        self._handle = zenoh_handle
        self.key_expr = key_expr

    def undeclare(self) -> None:
        handle, self._handle = self._handle, None
        if handle is not None:
            self._transport._forget(self)
            try:
                handle.undeclare()
            except Exception as exc:  # session already closed: nothing left to undeclare
                log.debug("undeclare %s: %s", self.key_expr, exc)


class ZenohTransport:
    """One robot's Zenoh peer session (see the module docstring)."""

    #: Declared publishers kept alive (keys change every round: theta/<id>/<round>/<to>).
    PUBLISHER_CACHE = 4

    def __init__(self, cfg: TransportConfig, keys: Keys, robot_id: int):
        cfg.validate()
        self.senders_authenticated = cfg.mtls() and cfg.access_control is not None
        keys.alive(robot_id)  # validates the id
        self.cfg = cfg
        self.keys = keys
        self.robot_id = robot_id
        self._session: zenoh.Session | None = None
        self._token: Any = None
        self._handles: list[Any] = []  # zenoh subscribers / queryables to undeclare on close
        self._subscriptions: list[Subscription] = []
        self._close_once = threading.Lock()
        self._closed = False
        self._lock = threading.Lock()  # counters and served data
        self._bytes_out: dict[str, int] = defaultdict(int)
        self._bytes_in: dict[int, int] = defaultdict(int)
        self._messages_in = 0
        self._messages_out = 0
        self._callback_errors = 0
        self._foreign_keys = 0
        self._served: dict[str, Served] = {}  # key -> what its queryable answers
        self._queryables: dict[str, Any] = {}
        self._publishers: dict[tuple[str, bool], Any] = {}
        self._publisher_users: dict[tuple[str, bool], int] = {}  # puts in flight: never undeclared under them
        self._publishers_lock = threading.Lock()

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> "ZenohTransport":
        if self._closed:
            raise TransportError("this transport was closed; make a new one")
        if self._session is not None:
            return self
        if os.environ.get("RUST_LOG"):
            zenoh.try_init_log_from_env()  # Zenoh's own log on stderr, for diagnosing links; off by default
        conf = self.cfg.to_zenoh()  # a bad config raises ValueError here, before anything changes
        # Read by Zenoh when its runtimes start, i.e. at the first link of this process.
        os.environ.setdefault("ZENOH_RUNTIME", f"(rx: (worker_threads: {self.cfg.rx_threads}))")
        try:
            self._session = zenoh.open(conf)
        except ValueError:
            raise
        except Exception as exc:
            raise TransportError(f"cannot open the Zenoh session (listen={self.cfg.listen}, "
                                 f"connect={self.cfg.connect}): {exc}") from None
        log.info("zenoh session %s open for robot %d in swarm %s", self._session.zid(), self.robot_id,
                 self.keys.swarm)
        return self

    def close(self) -> None:
        """Undeclare everything and close the session. Idempotent, non-blocking on repeat, never raises."""
        if not self._close_once.acquire(blocking=False):
            return
        self._closed = True
        session, self._session = self._session, None
        for sub in list(self._subscriptions):
            sub._handle = None
        publishers = list(self._publishers.values())
        self._publishers.clear()
        for handle in publishers + self._handles + ([self._token] if self._token is not None else []):
            try:
                handle.undeclare()
            except Exception as exc:
                log.debug("undeclare on close: %s", exc)
        self._handles.clear()
        self._token = None
        if session is not None:
            try:
                session.close()
            except Exception as exc:
                log.warning("closing the Zenoh session: %s", exc)

    def __enter__(self) -> "ZenohTransport":
        return self.open()

    def __exit__(self, *exc_info: Any) -> None:
        self.close()

    @property
    def session(self) -> zenoh.Session:
        if self._session is None:
            raise TransportError("transport is not open" if not self._closed else "transport is closed")
        return self._session

    def _forget(self, sub: Subscription) -> None:
        with self._lock:
            if sub in self._subscriptions:
                self._subscriptions.remove(sub)
            if sub._handle in self._handles:
                self._handles.remove(sub._handle)

    def _guard(self, what: str, fn: Callable[..., None]) -> Callable[..., None]:
        """Wrap a Zenoh callback so no exception ever escapes into Zenoh."""

        def guarded(*args: Any) -> None:
            try:
                fn(*args)
            except Exception:
                with self._lock:
                    self._callback_errors += 1
                log.exception("error in %s callback (dropped)", what)

        return guarded

    # ------------------------------------------------------------------ liveliness
    def declare_alive(self) -> None:
        """Declare this robot's liveliness token (gone when the process dies or the lease expires)."""
        if self._token is None:
            self._token = self.session.liveliness().declare_token(self.keys.alive(self.robot_id))

    def watch_alive(self, callback: Callable[[frozenset[int]], None], seed_timeout: float = 1.0) -> Subscription:
        """Call ``callback(ids)`` with the full set of live robot ids on every change.

        The subscriber asks for history, and the current tokens are also fetched with a
        liveliness get before this returns, so the robots already alive are reported at once
        (history alone arrives asynchronously). An id whose token is seen deleted meanwhile is
        not re-added by that get.
        """
        members: set[int] = set()
        deleted: set[int] = set()
        members_lock = threading.Lock()  # also serialises callbacks: each call sees the newest set
        keys = self.keys

        def change(robot_id: int, present: bool, seeding: bool = False) -> None:
            with members_lock:
                if seeding and (robot_id in deleted or robot_id in members):
                    return
                before = frozenset(members)
                if present:
                    members.add(robot_id)
                    deleted.discard(robot_id)
                else:
                    members.discard(robot_id)
                    deleted.add(robot_id)
                now = frozenset(members)
                if now != before:
                    callback(now)

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                parsed = keys.parse(str(sample.key_expr))
            except ForeignKey as exc:
                with self._lock:
                    self._foreign_keys += 1
                log.warning("ignoring liveliness token: %s", exc)
                return
            if parsed.kind == "alive":
                change(parsed.robot_id, sample.kind != zenoh.SampleKind.DELETE)

        handle = self.session.liveliness().declare_subscriber(
            keys.alive_all(), self._guard("liveliness", on_sample), history=True)
        sub = self._track(handle, keys.alive_all())
        try:
            current = self.alive_now(timeout=seed_timeout)
        except Exception as exc:
            log.warning("liveliness get failed, relying on subscriber history: %s", exc)
            current = set()
        guarded_change = self._guard("liveliness", change)
        for robot_id in sorted(current):
            guarded_change(robot_id, True, True)
        return sub

    def alive_now(self, timeout: float | None = None) -> set[int]:
        """Ask the network which robots hold a liveliness token right now."""
        ids: set[int] = set()
        replies = self.session.liveliness().get(self.keys.alive_all(), timeout=timeout or self.cfg.query_timeout_s)
        for reply in replies:
            if reply.ok is None:
                continue
            try:
                ids.add(self.keys.parse(str(reply.ok.key_expr)).robot_id)
            except ForeignKey:
                continue
        return ids

    # ------------------------------------------------------------------ pub/sub
    def _kind_of(self, key: str) -> str:
        try:
            return self.keys.parse(key).kind
        except ForeignKey:
            return "other"

    def _publisher(self, key: str, block: bool) -> Any:
        """A declared publisher for ``key`` (reliable; BLOCK or DROP), held for one put until
        :meth:`_release`; the few most recent idle ones are kept. A publisher is never undeclared
        while a put on it is in flight (snapshots to several neighbours go out at once: with more
        neighbours than the cache holds, a put failed with "Undeclared publisher" and the
        neighbour waited for its pull)."""
        with self._publishers_lock:  # not the counters lock: Zenoh callbacks never wait on this one
            pub = self._publishers.pop((key, block), None)
            if pub is None:
                # Periodic messages (block=False) get a queue of their own, ahead of the snapshots:
                # behind a snapshot crossing a slow link, a heartbeat would be dropped or late.
                congestion = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
                priority = zenoh.Priority.DATA if block else zenoh.Priority.DATA_HIGH
                pub = self.session.declare_publisher(
                    key, congestion_control=congestion, priority=priority, reliability=zenoh.Reliability.RELIABLE)
            self._publishers[(key, block)] = pub  # most recent last
            self._publisher_users[(key, block)] = self._publisher_users.get((key, block), 0) + 1
            evicted = self._evict_idle()
        self._undeclare(evicted)
        return pub

    def _evict_idle(self) -> list[Any]:
        """The least recently used idle publishers beyond the cache, removed (with the lock held)."""
        idle = [k for k in self._publishers if k not in self._publisher_users]  # least recent first
        return [self._publishers.pop(k) for k in idle[:max(len(self._publishers) - self.PUBLISHER_CACHE, 0)]]

    @staticmethod
    def _undeclare(publishers: list[Any]) -> None:
        for old in publishers:
            try:
                old.undeclare()
            except Exception as exc:
                log.debug("undeclare publisher: %s", exc)

    def _release(self, key: str, block: bool) -> None:
        """One put on ``key`` is done; publishers left idle beyond the cache go now (puts that
        overlapped kept more of them declared than the cache holds)."""
        with self._publishers_lock:
            users = self._publisher_users.pop((key, block), 1) - 1
            if users > 0:
                self._publisher_users[(key, block)] = users
            evicted = self._evict_idle()
        self._undeclare(evicted)

    def publish(self, key: str, data: bytes, block: bool = True) -> None:
        """Reliable put that blocks rather than drops when the link is congested (``block``).

        ``block=False`` is for periodic messages (status): a put that matches a subscriber
        behind a dead link would otherwise wait until Zenoh gives up on that link (seconds),
        and the next heartbeat makes up for a dropped one anyway.
        """
        try:
            pub = self._publisher(key, block)
        except TransportError:
            raise
        except Exception as exc:
            raise TransportError(f"put on {key} failed: {exc}") from None
        try:
            pub.put(data)
        except Exception as exc:
            raise TransportError(f"put on {key} failed: {exc}") from None
        finally:
            self._release(key, block)
        with self._lock:
            self._bytes_out[self._kind_of(key)] += len(data)
            self._messages_out += 1

    def subscribe(self, key_expr: str, callback: Callable[[str, bytes], None]) -> Subscription:
        """Deliver ``callback(key, data)`` for every put matching ``key_expr`` (deletes are ignored).

        ``key`` is passed as received: under a wildcard it may be foreign (``theta/abc/1``), so
        parse it with :meth:`Keys.parse` and count a ``ForeignKey`` as a rejection.
        """

        def on_sample(sample: zenoh.Sample) -> None:
            if sample.kind == zenoh.SampleKind.DELETE:
                return
            key = str(sample.key_expr)
            data = sample.payload.to_bytes()
            self._count_in(key, len(data))
            callback(key, data)

        handle = self.session.declare_subscriber(key_expr, self._guard(f"subscriber {key_expr}", on_sample))
        return self._track(handle, key_expr)

    def _count_in(self, key: str, n: int) -> None:
        try:
            sender = self.keys.parse(key).robot_id
        except ForeignKey:
            sender = -1
        with self._lock:
            self._bytes_in[sender] += n
            self._messages_in += 1
            if sender < 0:
                self._foreign_keys += 1

    def _track(self, handle: Any, key_expr: str) -> Subscription:
        sub = Subscription(self, handle, key_expr)
        with self._lock:
            self._handles.append(handle)
            self._subscriptions.append(sub)
        return sub

    # ------------------------------------------------------------------ queryables
    def _serve(self, key: str, served: Served) -> None:
        with self._lock:
            self._served[key] = served
            if key in self._queryables:
                return

        def on_query(query: zenoh.Query) -> None:
            with query:
                with self._lock:
                    now = self._served.get(key, Served(None))
                for payload in now.answer(dict(query.parameters)):  # none: the get ends without a reply
                    query.reply(key, payload)
                    with self._lock:
                        self._bytes_out[self._kind_of(key)] += len(payload)
                        self._messages_out += 1

        handle = self.session.declare_queryable(key, self._guard(f"queryable {key}", on_query))
        with self._lock:
            self._queryables[key] = handle
            self._handles.append(handle)

    def set_latest(self, data: bytes | None, round: int | None = None,
                   deltas: tuple[tuple[int, bytes], ...] = ()) -> None:
        """Serve ``data`` (our newest encoded snapshot, of ``round``) on ``latest/<robot_id>``;
        None serves nothing. A query for ``latest_since(id, k)`` gets it only if ``round >= k``;
        one that says which base it holds may get ``deltas`` instead (:meth:`Served.answer`)."""
        self._serve(self.keys.latest(self.robot_id), Served(data, round, deltas))

    def set_keyframes(self, data: bytes | None) -> None:
        """Serve our encoded keyframe summary on ``keyframes/<robot_id>``."""
        self._serve(self.keys.keyframes(self.robot_id), Served(data))

    def query(self, key: str, timeout: float | None = None, block: bool = True) -> bytes | None:
        """First reply to a get on ``key``, or None if nobody answered before the timeout.

        Replies follow the query's congestion control, and the replier sends them from a Zenoh
        runtime thread. ``block=True`` (a large snapshot is never dropped) is for a link known to
        be up, e.g. at start; ``block=False`` for a link that may be dying: a BLOCK reply queued
        towards a link that was just cut stalled the replier's runtime, and its healthy links
        missed their keep-alives and died too (measured on a ring with one link cut). DROP drops
        a reply only when that link's queue is full; the caller asks again.
        """
        for _, data in self._get(key, timeout, first_only=True, block=block):
            return data
        return None

    def query_all(self, key_expr: str, timeout: float | None = None, block: bool = True) -> list[tuple[str, bytes]]:
        """Every (key, data) reply to a get on ``key_expr`` (e.g. all robots' latest snapshots, or
        every answer on one robot's key: a forged queryable answers too)."""
        return list(self._get(key_expr, timeout, first_only=False, block=block))

    def _get(self, key_expr: str, timeout: float | None, first_only: bool, block: bool):
        congestion = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        try:
            # no consolidation: Zenoh would keep one reply per key, and a forged queryable's answer
            # could be the one kept; every answer is seen and judged by the caller
            replies = self.session.get(key_expr, timeout=timeout or self.cfg.query_timeout_s,
                                       target=zenoh.QueryTarget.ALL, congestion_control=congestion,
                                       consolidation=zenoh.ConsolidationMode.NONE)
        except Exception as exc:
            raise TransportError(f"get on {key_expr} failed: {exc}") from None
        for reply in replies:
            sample = reply.ok
            if sample is None:
                continue
            key = str(sample.key_expr)
            data = sample.payload.to_bytes()
            self._count_in(key, len(data))
            yield key, data
            if first_only:
                return

    # ------------------------------------------------------------------ counters
    def stats(self) -> dict[str, Any]:
        """Snapshot of the traffic counters."""
        with self._lock:
            return {
                "bytes_out": dict(self._bytes_out),
                "bytes_in": dict(self._bytes_in),
                "bytes_out_total": sum(self._bytes_out.values()),
                "bytes_in_total": sum(self._bytes_in.values()),
                "messages_out": self._messages_out,
                "messages_in": self._messages_in,
                "callback_errors": self._callback_errors,
                "foreign_keys": self._foreign_keys,
            }
