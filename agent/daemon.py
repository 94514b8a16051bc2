"""The long-running agent of one robot: rounds over the network, checkpoints, telemetry.

This module joins the trainer (``agent``) to the pure parts of the protocol (keys, messages,
codec, rounds, membership). It never imports Zenoh: the transport is injected (anything with the
methods of :class:`Network`; ``protocol.transport.ZenohTransport`` in production), which is how
rmw_zenoh and Swarm-SLAM keep transport, membership and application logic apart.

One round k, exactly as :class:`agent.swarm.Simulation` does it in memory::

    begin_round(k, theta_j^k heard)  ->  B training steps  ->  publish theta_i^{k+1}
    ->  barrier: theta_j^{k+1} from live neighbours until a deadline  ->  dual update
    ->  atomic checkpoint, telemetry line, status

Membership is decided by liveliness tokens plus gossip of ages carried in the status messages
(Zenoh peers do not relay, so a robot cannot see non-neighbours' tokens). The reference (lowest
live id) keeps its pose fixed; a newly elected reference freezes its *current* estimate, so the
shared frame, the field and every other robot's pose stay valid.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import threading
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Literal, Mapping, Protocol

import numpy as np
import torch
from torch import Tensor

from agent.data.views import Views
from agent.geometry import sim3_to_params
from agent.swarm import RobotSetup, SwarmTrainingConfig, build_robot
from protocol import codec
from protocol.keys import Keys
from protocol.membership import AliveView, LastHeard, Membership, Topology
from protocol.messages import ModelSpec, Rejected, Status, ThetaSnapshot
from protocol.rounds import Mailbox

CHECKPOINT = "checkpoint.pt"
SFM_CACHE = "sfm"  # in the run folder: an images-only robot's SfM, computed once, reused on restart


@dataclass
class DaemonConfig:
    round_timeout_s: float = 120.0  # how long the barrier waits for neighbours after own compute
    startup_wait_s: float = 20.0  # wait this long for the whole roster before round 0
    threads: int = 1  # torch threads (several robots often share a machine)
    wire_dtype: Literal["float32", "float16"] = "float32"  # float16 halves bytes, is lossy
    compression: Literal["zstd", "none"] = "zstd"
    max_ahead: int = 4  # rounds of a faster neighbour buffered ahead of ours
    heartbeat_s: float = 0.5  # status / liveness gossip period
    alive_expiry_s: float = 2.0  # relayed liveness evidence older than this is dropped
    linger_s: float = 3.0  # after the last round, keep serving the newest snapshot this long
    eval_every: int = 1  # rounds between PSNR evaluations on own held-out views (0 = never)
    keep_rounds: bool = False  # also save rounds/<k>.pt (field + pose) for per-round reports
    join_timeout_s: float = 5.0  # query timeout for neighbours' newest snapshots
    pull_after_s: float = 2.0  # a neighbour's snapshot missing this long is asked for (pulled; PullPacing)
    # The barrier stops waiting for a neighbour that sent nothing (heartbeat, snapshot) for this
    # long, even if its token is still seen (see LastHeard: Zenoh can keep it for 10-20 s).
    silent_after_s: float = 3.0
    # A robot that finds its neighbours this many rounds ahead when it comes back (restart, skip
    # after a freeze or a cut) takes their mean model instead of its own, and forgets its duals:
    # its own is stale, and C-ADMM would pull the neighbours back towards it. 0 = keep its own.
    adopt_after_rounds: int = 2
    resend_delay_s: float = 1.0  # re-push our snapshot this long after a neighbour's link appears
    # Initial relative pose: "identity" (the paper) or "coarse": match compact keyframe summaries
    # (descriptors + 3-D points, never images) with neighbours whose pose is already known.
    initial_pose: Literal["identity", "coarse"] = "identity"
    align_timeout_s: float = 60.0  # give up on the coarse step after this long (identity start)
    # Width of the images the keyframe summary is computed from; None: the folder's own size, even
    # when training runs smaller. On lego, features from the 400 px files place a neighbour's frame
    # 3-4x more precisely than from 100 px ones (benchmarks/bench_alignment.py, README).
    summary_width: int | None = None

    def __post_init__(self) -> None:
        if self.round_timeout_s <= 0 or self.heartbeat_s <= 0 or self.threads < 1:
            raise ValueError("round_timeout_s and heartbeat_s must be > 0, threads >= 1")
        if self.summary_width is not None and (not isinstance(self.summary_width, int) or self.summary_width < 8):
            raise ValueError(f"summary_width must be >= 8 pixels (or unset: the images' own size), got {self.summary_width!r}")
        if self.silent_after_s < 2 * self.heartbeat_s:
            raise ValueError(f"silent_after_s ({self.silent_after_s}) must be at least two heartbeats "
                             f"({2 * self.heartbeat_s} s): one lost heartbeat must not count as silence")


@dataclass(frozen=True)
class SwarmIdentity:
    """Who the swarm is: its name and the static graph of who may talk to whom."""

    name: str
    topology: Topology


class Network(Protocol):
    """What the daemon needs from a transport (``protocol.transport.ZenohTransport``)."""

    def declare_alive(self) -> None: ...
    def watch_alive(self, callback: Callable[[frozenset[int]], None]) -> Any: ...
    def subscribe(self, key_expr: str, callback: Callable[[str, bytes], None]) -> Any: ...
    def publish(self, key: str, data: bytes, block: bool = True) -> None: ...
    def set_latest(self, data: bytes | None) -> None: ...
    def query(self, key: str, timeout: float | None = None, block: bool = True) -> bytes | None: ...
    def stats(self) -> dict[str, Any]: ...


class _NewestJobThread:
    """One job at a time on its own thread, keeping only the newest job offered meanwhile.

    A job is for a round; an older job still waiting is replaced by a newer one, since nobody
    wants it any more. Subclasses say what a job does (:meth:`_do`).
    """

    def __init__(self, name: str, log: Callable[[str], None]) -> None:
        self._log = log
        self._cond = threading.Condition()
        self._slot: tuple[int, Any] | None = None
        self._not_before = 0.0
        self._busy = False
        self._closed = False
        self.last_seconds = 0.0  # duration of the last job (e.g. how long a link held a put)
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def offer(self, round_index: int, data: Any = None, delay_s: float = 0.0) -> None:
        with self._cond:
            if self._slot is not None and self._slot[0] > round_index:
                return  # a newer job is already waiting
            self._slot = (round_index, data)
            self._not_before = time.monotonic() + delay_s
            self._cond.notify_all()

    def idle(self, timeout: float) -> bool:
        """Wait until nothing is pending or in flight (e.g. before exiting)."""
        with self._cond:
            return self._cond.wait_for(lambda: self._slot is None and not self._busy, timeout)

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    def _do(self, round_index: int, data: Any) -> None:
        raise NotImplementedError

    def _run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._slot is not None or self._closed)
                if self._closed:
                    return
                pause = self._not_before - time.monotonic()
                if pause > 0:
                    self._cond.wait(pause)  # an offer meanwhile may replace the slot
                    continue
                round_index, data = self._slot
                self._slot = None
                self._busy = True
            t0 = time.monotonic()
            try:
                self._do(round_index, data)
            except Exception as e:  # the transport is closing, or the link is gone: log, go on
                self._log(f"round {round_index}: {type(e).__name__}: {e}")
            self.last_seconds = time.monotonic() - t0
            with self._cond:
                self._busy = False
                self._cond.notify_all()


class NeighbourSender(_NewestJobThread):
    """Delivers this robot's newest snapshot to one neighbour.

    A put with congestion control BLOCK can wait on a cut or congested link for seconds; with
    one sender per neighbour (and keys addressed to that neighbour) it delays that neighbour's
    copy only, never the round loop nor the other neighbours.
    """

    def __init__(self, net: "Network", key_for_round: Callable[[int], str], log: Callable[[str], None]) -> None:
        self._net = net
        self._key = key_for_round
        super().__init__("sender", log)

    def _do(self, round_index: int, data: bytes) -> None:
        self._net.publish(self._key(round_index), data)


class NeighbourPuller(_NewestJobThread):
    """Asks one neighbour for its snapshot of a round or later, through its ``latest`` queryable.

    Pushes can be lost: a put made while a link was being re-established found no subscriber,
    and a link can come back one-sided (the far end does not see our subscription; measured
    after a SIGSTOP). So the barrier asks for what is missing. The query runs here, not in the
    round loop: over a link that is dying it waits out its timeout, and that must hold up
    nobody. The neighbour answers only once it has that round, so asking early costs no bytes.
    """

    def __init__(self, pull: Callable[[int], None], log: Callable[[str], None]) -> None:
        self._pull = pull
        super().__init__("puller", log)

    def _do(self, round_index: int, data: Any) -> None:
        self._pull(round_index)


class PullPacing:
    """How long the barrier waits for a neighbour's push before asking for the snapshot (a pull).

    Asking too early duplicates a push that is merely slow: on a link with 100 ms and 10% loss,
    pulls after a fixed 2 s made it carry 1.5x the bytes (measured, fault-lossy-link). Asking
    too late leaves a lost push to the barrier deadline. So each neighbour has its own delay:
    doubled (up to ``max_s``) when a pull fetched a round its push delivered too, halved (down
    to ``base_s``) when its push arrives within half the delay or when the push of the round
    pulled before never came (that pull was needed: a one-sided link). Thread-safe.
    """

    def __init__(self, base_s: float, max_s: float) -> None:
        self.base_s = base_s
        self.max_s = max(max_s, base_s)
        self._lock = threading.Lock()
        self._delay: dict[int, float] = {}
        self._pulled: dict[int, int] = {}  # neighbour -> round of its last pulled snapshot
        self._pushed: dict[int, int] = {}  # neighbour -> round of its last pushed snapshot
        self._doubled_for: dict[int, int] = {}  # a round counted once as a wasted pull

    def delay(self, j: int) -> float:
        with self._lock:
            return self._delay.get(j, self.base_s)

    def pulled(self, j: int, round_index: int) -> None:
        with self._lock:
            before = self._pulled.get(j)
            if before is not None and before < round_index and self._pushed.get(j, -1) < before:
                self._halve(j)
            self._pulled[j] = round_index
            self._wasted(j, round_index)

    def pushed(self, j: int, round_index: int, waited_s: float) -> None:
        """A push of ``round_index`` arrived ``waited_s`` after our barrier for it began (0: before)."""
        with self._lock:
            self._pushed[j] = round_index
            if not self._wasted(j, round_index) and waited_s < self._delay.get(j, self.base_s) / 2:
                self._halve(j)

    def _halve(self, j: int) -> None:
        self._delay[j] = max(self.base_s, self._delay.get(j, self.base_s) / 2)

    def _wasted(self, j: int, round_index: int) -> bool:
        if (self._pulled.get(j) == round_index == self._pushed.get(j)
                and self._doubled_for.get(j) != round_index):
            self._doubled_for[j] = round_index
            self._delay[j] = min(2 * self._delay.get(j, self.base_s), self.max_s)
            return True
        return False


class Stop(Exception):
    """Raised inside training to leave the round loop promptly (SIGTERM, test harness)."""


def plan_catch_up(round_index: int, newest: Mapping[int, int | None], round_compute_s: float | None,
                  max_neighbour_wait_s: float) -> tuple[Literal["train", "skip"], int] | None:
    """What a robot at ``round_index`` does about neighbours two or more rounds ahead (their newest
    snapshot rounds in ``newest``): nothing (None), train through to their round (their snapshots
    stand in meanwhile; no steps lost) when that keeps them waiting at most ``max_neighbour_wait_s``,
    or skip to their round. Without a measured round time (just started) it skips."""
    ahead = [r for r in newest.values() if r is not None and r > round_index + 1]
    if not ahead:
        return None
    target = max(ahead)
    if round_compute_s is not None and (target - round_index) * round_compute_s <= max_neighbour_wait_s:
        return "train", target
    return "skip", target


def model_spec(setup: RobotSetup) -> ModelSpec:
    """Layout + architecture of theta: robots whose fields differ must not mix parameters."""
    trainer = setup.trainer
    arch = {
        "field": dataclasses.asdict(trainer.cfg.field),
        "box_from_shared": [round(float(x), 9) for x in trainer.box_from_shared.flatten()],
        "init_seed": trainer.cfg.init_seed,
    }
    arrays = {n: t.cpu().numpy() for n, t in trainer.theta().items()}
    return ModelSpec.from_tensors(arrays, arch)


def _to_numpy(theta: Mapping[str, Tensor]) -> dict[str, np.ndarray]:
    return {n: np.ascontiguousarray(t.detach().cpu().numpy(), dtype=np.float32) for n, t in theta.items()}


def _to_torch(snapshot: ThetaSnapshot) -> dict[str, Tensor]:
    return {n: torch.from_numpy(np.array(a, dtype=np.float32, copy=True)) for n, a in snapshot.tensors.items()}


def _atomic_torch_save(obj: Any, path: Path) -> None:
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    with open(tmp, "rb") as f:
        os.fsync(f.fileno())
    os.replace(tmp, path)


def pose_summary(T: Tensor) -> dict[str, Any]:
    log_s, phi, t = sim3_to_params(T.detach().double().cpu())
    return {
        "scale": math.exp(float(log_s)),
        "rotation_deg": math.degrees(float(phi.norm())),
        "translation": [float(x) for x in t],
        "params7": [float(log_s), *map(float, phi), *map(float, t)],
    }


class Daemon:
    """One robot in the swarm. ``run()`` blocks until all rounds are done (or ``stop()``)."""

    def __init__(
        self,
        robot_id: int,
        views: Views,
        box_from_shared: Tensor | None,
        swarm: SwarmIdentity,
        training: SwarmTrainingConfig,
        cfg: DaemonConfig,
        network: Network,
        run_dir: Path,
        initial_pose: Tensor | None = None,
        log: Callable[[str], None] = print,
        summary_views: Views | None = None,
    ) -> None:
        """summary_views: the same views at the resolution the keyframe summary is computed from
        (``cfg.summary_width``); None: the training views."""
        if robot_id not in swarm.topology.ids:
            raise ValueError(f"robot {robot_id} is not in the swarm's robots {list(swarm.topology.ids)}")
        if box_from_shared is None and cfg.initial_pose != "coarse":
            raise ValueError("no field box in the scene (robots with images only): the reference derives it from "
                             "its SfM and shares it with the keyframes, so daemon.initial_pose must be 'coarse'")
        torch.set_num_threads(cfg.threads)
        self.robot_id = robot_id
        # None: the box lives in the reference's SfM frame. Until a peer tells us, train nothing and
        # use a provisional box from our own views (the right one if we turn out to be the reference).
        self._box_pending = box_from_shared is None
        if box_from_shared is None:
            from agent.data.split import estimate_scene_box
            from agent.geometry import box_from_center

            center, half_size, _ = estimate_scene_box(views)
            box_from_shared = box_from_center(center, half_size)
        self.swarm = swarm
        self.training = training
        self.cfg = cfg
        self.net = network
        self.keys = Keys(swarm.name)
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.log = log
        self.setup = build_robot(robot_id, views, box_from_shared, training, initial_pose, is_reference=False)
        if summary_views is not None and (summary_views.names != views.names
                                          or not torch.allclose(summary_views.c2w, views.c2w)):
            raise ValueError("summary_views must be the training views at another resolution (same names and poses)")
        self.summary_views = summary_views if summary_views is not None else views
        self.trainer = self.setup.trainer
        self.spec = model_spec(self.setup)
        self.expect = self._expectation()
        self.status_expect = codec.Expectation(swarm=swarm.name, allowed_senders=frozenset(swarm.topology.ids))
        self.membership = Membership(swarm.topology, robot_id)
        self.alive = AliveView(robot_id, cfg.alive_expiry_s)
        self.last_heard = LastHeard()
        self.mailbox: Mailbox[ThetaSnapshot] = Mailbox(max_ahead=cfg.max_ahead, last_round=self.training.rounds)
        self.rejected: Counter[str] = Counter()
        self.round = 0
        self.elected = False  # pose frozen because this robot is the reference
        self._stop = threading.Event()
        self._state_lock = threading.Lock()
        self._last_status: dict[str, Any] = {}
        self._events = open(self.run_dir / "events.jsonl", "a")
        self._telemetry = open(self.run_dir / "telemetry.jsonl", "a")
        self._heartbeat: threading.Thread | None = None
        self._last_heard: dict[int, ThetaSnapshot] = {}
        self._round_compute_s: float | None = None  # our last round's training time: may we train through a gap?
        self._neighbour_status: dict[int, Status] = {}
        self._senders: dict[int, NeighbourSender] = {}
        self._pullers: dict[int, NeighbourPuller] = {}
        self._pacing = PullPacing(cfg.pull_after_s, cfg.round_timeout_s / 4)
        self._barrier_began: tuple[int, float] = (-1, 0.0)  # (round, monotonic) of the current barrier
        self._latest_snapshot: tuple[int, bytes] | None = None  # (round, encoded) last published
        self._last_status["alignment"] = "identity" if cfg.initial_pose == "identity" else "pending"
        with torch.no_grad():
            self._last_status["pose7"] = pose_summary(self.trainer.pose.matrix())["params7"]

    def _expectation(self) -> codec.Expectation:
        """What a neighbour's snapshot must look like: our model spec, hence our field box."""
        return codec.Expectation(
            swarm=self.swarm.name,
            spec=self.spec,
            allowed_senders=frozenset(self.swarm.topology.ids),
            max_wire_bytes=2 * self.spec.num_values * 4 + (1 << 20),
            max_decompressed_bytes=self.spec.num_values * 4 + (1 << 20),
        )

    def _adopt_box(self, box_from_shared: np.ndarray | Tensor, source: str) -> None:
        """Take the swarm's field box (images-only robots learn it at start) and the model spec it implies."""
        box = torch.as_tensor(np.asarray(box_from_shared, dtype=np.float64))
        self.trainer.set_box_from_shared(box)
        self.spec = model_spec(self.setup)
        self.expect = self._expectation()
        self._box_pending = False
        self._event("field_box", source=source, box_from_shared=[float(x) for x in box.flatten()])
        self.log(f"[robot {self.robot_id}] field box from {source}")

    def _box_to_share(self) -> np.ndarray:
        """Our box as it goes on the wire (float64 of our float32 box: every robot ends bit-identical)."""
        return self.trainer.box_from_shared.detach().cpu().double().numpy()

    # ------------------------------------------------------------------ network callbacks
    def _on_theta(self, key: str, data: bytes) -> None:
        if self._box_pending:
            return  # our spec is provisional until the box is known; the barrier pulls it later
        try:
            parsed = self.keys.parse(key)
            if parsed.receiver != self.robot_id:
                raise Rejected("bad_kind", f"snapshot addressed to robot {parsed.receiver}")
            msg = codec.decode(data, self.expect, kind="theta", key=parsed)
            self.last_heard.heard(msg.sender)
            self.mailbox.offer(msg.sender, msg.round, msg)
            barrier_round, began = self._barrier_began
            waited = time.monotonic() - began if msg.round == barrier_round else 0.0
            self._pacing.pushed(msg.sender, msg.round, waited)
        except Rejected as e:
            self._reject(e.reason, f"{key}: {e.detail}")
        except ValueError as e:  # a foreign key on our subscription
            self._reject("garbage", f"{key}: {e}")

    def _on_status(self, key: str, data: bytes) -> None:
        try:
            msg = codec.decode(data, self.status_expect, kind="status", key=self.keys.parse(key))
        except Rejected as e:
            self._reject(e.reason, f"{key}: {e.detail}")
            return
        except ValueError as e:
            self._reject("garbage", f"{key}: {e}")
            return
        self.last_heard.heard(msg.sender)
        self.alive.merge(msg.alive_ages)
        self._remember_status(msg)

    def _remember_status(self, msg: Status) -> None:
        with self._state_lock:
            self._neighbour_status[msg.sender] = msg

    def _on_alive(self, ids: frozenset[int]) -> None:
        before = self.alive.direct
        self.alive.set_direct(ids)
        for j in ids - before:
            self.last_heard.heard(j)  # a token (re)appearing is news from it too
        for j in (ids - before) & self.membership.neighbours:
            # A link (re)appeared: snapshots pushed meanwhile found no subscriber. Push ours again
            # once the new session's subscriptions are through (the barrier pulls theirs).
            latest = self._latest_snapshot
            if latest is not None and j in self._senders:
                self._senders[j].offer(*latest, delay_s=self.cfg.resend_delay_s)
        self._refresh_membership()

    def _reject(self, reason: str, detail: str) -> None:
        with self._state_lock:
            self.rejected[reason] += 1
            count = self.rejected[reason]
        if count <= 3 or count % 100 == 0:
            self.log(f"[robot {self.robot_id}] rejected a message ({reason}, #{count}): {detail[:200]}")

    def _refresh_membership(self) -> None:
        if self.membership.update(self.alive.alive()):
            self.mailbox.notify()
            m = self.membership
            self._event("membership", alive=sorted(m.alive), reference=m.reference, epoch=m.epoch)

    def _event(self, kind: str, **fields: Any) -> None:
        rec = {"event": kind, "robot": self.robot_id, "monotonic": time.monotonic(), "time": time.time(),
               "round": self.round, **fields}
        with self._state_lock:
            self._events.write(json.dumps(rec) + "\n")
            self._events.flush()

    # ------------------------------------------------------------------ reference / gauge
    def _apply_reference(self) -> None:
        """Freeze the pose when this robot becomes the reference; resume when it stops being it."""
        is_ref = self.membership.reference == self.robot_id
        if is_ref and not self.elected:
            before = self.trainer.pose.matrix().detach().clone()
            self.trainer.pose.freeze()
            self.elected = True
            jump = float((self.trainer.pose.matrix().detach() - before).abs().max())
            self._event("reference_elected", epoch=self.membership.epoch, pose_change=jump)
            self.log(f"[robot {self.robot_id}] I am the reference now (epoch {self.membership.epoch}); "
                     f"pose frozen at its current estimate")
        elif not is_ref and self.elected:
            self.trainer.pose.unfreeze()
            self.elected = False
            self._event("reference_resigned", reference=self.membership.reference, epoch=self.membership.epoch)
            self.log(f"[robot {self.robot_id}] robot {self.membership.reference} is the reference again; "
                     f"learning my pose")

    # ------------------------------------------------------------------ heartbeat
    def _status_message(self) -> Status:
        with self._state_lock:
            s = dict(self._last_status)
            rejected = dict(self.rejected)
        return Status(
            swarm=self.swarm.name, sender=self.robot_id, round=self.round, epoch=self.membership.epoch,
            reference=self.membership.reference, phase=s.get("phase", "starting"), loss=s.get("loss"),
            psnr=s.get("psnr"), pose=s["pose7"], neighbours_heard=s.get("heard", []),
            bytes_in=int(s.get("bytes_in_total", 0)), bytes_out=int(s.get("bytes_out_total", 0)),
            rejected=rejected, alignment=s.get("alignment", "n/a"), wall_time=time.time(),
            seconds_compute=float(s.get("seconds_compute", 0.0)), seconds_wait=float(s.get("seconds_wait", 0.0)),
            alive_ages=self.alive.report(),
        )

    def _heartbeat_loop(self) -> None:
        while not self._stop.is_set():
            try:
                self._refresh_membership()
                self.net.publish(self.keys.status(self.robot_id), codec.encode(self._status_message()), block=False)
            except Exception as e:  # never let telemetry kill the robot
                self.log(f"[robot {self.robot_id}] heartbeat failed: {type(e).__name__}: {e}")
            self._stop.wait(self.cfg.heartbeat_s)

    # ------------------------------------------------------------------ snapshots
    def _publish_theta(self, round_index: int) -> None:
        """Encode theta once; serve it as `latest`; hand a copy to every neighbour's sender."""
        msg = ThetaSnapshot(swarm=self.swarm.name, sender=self.robot_id, round=round_index,
                            epoch=self.membership.epoch, signature=self.spec.signature(),
                            tensors=_to_numpy(self.trainer.theta()))
        data = codec.encode(msg, wire_dtype=self.cfg.wire_dtype, compression=self.cfg.compression, spec=self.spec)
        self.net.set_latest(data, round=round_index)
        self._latest_snapshot = (round_index, data)
        for sender in self._senders.values():
            sender.offer(round_index, data)

    def _reachable_neighbours(self) -> set[int]:
        """Neighbours whose tokens we see directly: only they can deliver (gossip says who is
        alive somewhere, e.g. behind a cut link, which matters for the reference, not here)."""
        return set(self.membership.live_neighbours & self.alive.direct)

    def _barrier(self, round_index: int) -> tuple[dict[int, ThetaSnapshot], float]:
        """Neighbours' round-k snapshots, waiting until every reachable neighbour answered or the deadline.

        Pushes can be lost, so a neighbour still missing after its pull delay (:class:`PullPacing`)
        is asked for its round-k snapshot, or a later one, in the background
        (:class:`NeighbourPuller`). A neighbour whose newest snapshot is already for a later round
        passed round k without us (its round-k push was lost while the link was down) and waits
        for *our* next snapshot: its newer snapshot stands in for round k, or both sides would
        wait out ``round_timeout_s``.
        """

        given_up: set[int] = set()  # silent neighbours already reported for this barrier

        def awaited() -> set[int]:
            missing = {j for j in self._reachable_neighbours()
                       if (r := self.mailbox.newest_round(j)) is None or r <= round_index}
            silent = self.last_heard.silent(missing, self.cfg.silent_after_s)
            for j in silent - given_up:
                given_up.add(j)
                self._event("silent", sender=j, silence_s=round(self.last_heard.silence_s(j), 2))
                self.log(f"[robot {self.robot_id}] round {round_index}: robot {j} sent nothing for "
                         f"{self.cfg.silent_after_s:.0f} s though its token is still seen; not waiting for it")
            return missing - silent

        t0 = time.monotonic()
        self._barrier_began = (round_index, t0)
        deadline = t0 + self.cfg.round_timeout_s
        while True:
            slice_s = max(min(self.cfg.pull_after_s, deadline - time.monotonic()), 0.0)
            got = self.mailbox.wait(round_index, awaited, slice_s)
            if got.complete or time.monotonic() >= deadline or self._stop.is_set():
                break
            for j in sorted(got.missing):
                if j in self._pullers and time.monotonic() - t0 >= self._pacing.delay(j):
                    self._pullers[j].offer(round_index)
        got = self.mailbox.wait(round_index, awaited, 0.0)
        got.waited_s = time.monotonic() - t0
        if not got.complete:
            self.log(f"[robot {self.robot_id}] round {round_index}: no snapshot from {sorted(got.missing)} "
                     f"within {self.cfg.round_timeout_s:.0f} s; going on with {sorted(got.items)}")
        items = dict(got.items)
        newest_of = self.mailbox.newest_items()
        for j in self._reachable_neighbours() - items.keys():
            newest = newest_of.get(j)
            if newest is not None and newest[0] > round_index:
                items[j] = newest[1]
                self._event("ahead", sender=j, snapshot_round=newest[0])
        heard = {j: items[j] for j in sorted(items) if j in self.membership.neighbours}
        return heard, got.waited_s

    def _fetch_latest(self, j: int, block: bool = True, min_round: int = 0) -> ThetaSnapshot | None:
        """Neighbour j's newest snapshot if of ``min_round`` or later, from its ``latest``
        queryable, validated; None if none came."""
        data = self.net.query(self.keys.latest_since(j, min_round), timeout=self.cfg.join_timeout_s, block=block)
        if data is None:
            return None
        try:
            msg = codec.decode(data, self.expect, kind="theta")
        except Rejected as e:
            self._reject(e.reason, f"latest of robot {j}: {e.detail}")
            return None
        return msg if msg.sender == j else None

    def _pull_latest(self, j: int, min_round: int) -> None:
        """Fetch neighbour j's newest snapshot into the mailbox if it is not older than min_round."""
        # block=False: the link to j may be dying (see ZenohTransport.query)
        msg = self._fetch_latest(j, block=False, min_round=min_round)
        if msg is not None and msg.round >= min_round:
            self._offer_quietly(j, msg)
            self._pacing.pulled(j, msg.round)
            self._event("pulled", sender=j, snapshot_round=msg.round, next_pull_after_s=self._pacing.delay(j))

    def _join_current_round(self) -> None:
        """Late join / restart: fetch the neighbours' newest snapshots and move to their round."""
        newest: dict[int, ThetaSnapshot] = {}
        for j in sorted(self._reachable_neighbours()):
            if (msg := self._fetch_latest(j)) is not None:
                newest[j] = msg
        if not newest:
            return
        target = max(m.round for m in newest.values())
        if target <= self.round:
            for j, m in newest.items():
                if m.round >= self.round:
                    self._offer_quietly(j, m)
            return
        fresh_start = self.round == 0 and self.trainer.step == 0
        adopt = fresh_start or self._is_stale(target)
        if adopt:  # a new robot starts from the swarm's current model, not from theta^0
            self._adopt_mean([m for m in newest.values() if m.round == target], reset_duals=not fresh_start)
        self._event("joined", from_round=self.round, to_round=target, fresh=fresh_start, adopted=adopt)
        self.log(f"[robot {self.robot_id}] joining the swarm at round {target} (was at {self.round}"
                 f"{', taking the neighbours mean model' if adopt else ''})")
        self.round = target
        self.mailbox.advance(target)
        for j, m in newest.items():
            if m.round >= target:
                self._offer_quietly(j, m)

    def _is_stale(self, target: int) -> bool:
        return self.cfg.adopt_after_rounds > 0 and target - self.round >= self.cfg.adopt_after_rounds

    def _adopt_mean(self, snapshots: list[ThetaSnapshot], reset_duals: bool) -> None:
        """Replace theta_i by the mean of the neighbours' snapshots (all of one round)."""
        thetas = [_to_torch(m) for m in snapshots]
        self.trainer.load_theta({n: sum(t[n] for t in thetas) / len(thetas) for n in thetas[0]},
                                reset_duals=reset_duals)

    def _offer_quietly(self, sender: int, msg: ThetaSnapshot) -> None:
        try:
            self.mailbox.offer(sender, msg.round, msg)
        except Rejected:
            pass

    def _catch_up(self, heard: dict[int, ThetaSnapshot]) -> dict[int, ThetaSnapshot]:
        """If neighbours moved on without us (we were slow or cut off), catch up with them.

        A neighbour one round ahead is normal: it is waiting at its barrier for our next snapshot.
        Two or more ahead means it passed a barrier without us and now waits for our round-``target``
        snapshot. Training through costs no steps; skipping keeps it from timing out round after
        round when training through would take too long (``plan_catch_up``).
        """
        newest = {j: self.mailbox.newest_round(j) for j in self._reachable_neighbours()}
        plan = plan_catch_up(self.round, newest, self._round_compute_s, self.cfg.round_timeout_s / 2)
        if plan is None:
            return heard
        action, target = plan
        if action == "train":
            self._event("training_through", from_round=self.round, to_round=target)
            return heard
        self.mailbox.advance(target)  # first: a snapshot kept beyond the window is in place only now
        items = {j: m for j, m in self.mailbox.items(target).items() if j in self.membership.neighbours}
        adopt = self._is_stale(target) and bool(items)
        if adopt:
            self._adopt_mean(list(items.values()), reset_duals=True)
        self._event("caught_up", from_round=self.round, to_round=target, adopted=adopt)
        self.log(f"[robot {self.robot_id}] neighbours are at round {target}; skipping from {self.round}"
                 f"{', taking their mean model' if adopt else ''}")
        self.round = target
        # Neighbours already at `target` are waiting for our round-`target` snapshot: send our
        # current theta as such at once, or they time out and the swarm stays out of phase.
        self._publish_theta(target)
        return dict(sorted(items.items()))

    # ------------------------------------------------------------------ coarse initial pose
    def _coarse_alignment(self) -> None:
        """Initial T_i from keyframe summaries, propagated outward from the reference.

        A robot whose pose is known (the reference: identity; others once aligned) says so in its
        status (``alignment`` = "reference" or "coarse..."), with its pose. Robot i matches its own
        summary with such a neighbour j's (``T_j_from_i`` by RANSAC Sim(3)) and starts from
        ``T_g_from_j T_j_from_i``. No overlap anywhere -> identity start, reported in telemetry.
        """
        from agent.align import AlignConfig, Summary, estimate_relative, summarise
        from agent.geometry import sim3_from_params
        from protocol.messages import KeyframeSummary

        acfg = AlignConfig(with_scale=self.trainer.cfg.pose.mode == "sim3")
        t0 = time.monotonic()
        views, self.summary_views = self.summary_views, self.trainer.views  # the sharper copy is needed once
        own = summarise(views, cfg=acfg)
        image_bytes = int(views.images.numel())  # 8-bit channels it stands for
        msg = KeyframeSummary(swarm=self.swarm.name, sender=self.robot_id, round=0, epoch=self.membership.epoch,
                              descriptors=own.descriptors, points=own.points, keyframe_index=own.keyframe_index,
                              image_bytes=image_bytes, keypoints=own.keypoints, keyframe_cameras=own.keyframe_cameras)
        is_reference = self.membership.reference == self.robot_id
        if is_reference and self._box_pending:  # our own frame is the shared frame: our box is the box
            self._adopt_box(self._box_to_share(), "our own views (we are the reference)")

        def serve_summary() -> int:
            msg.box_from_shared = None if self._box_pending else self._box_to_share()
            data = codec.encode(msg)
            self.net.set_keyframes(data)
            return len(data)

        size = serve_summary()
        self._event("keyframes", bytes=size, image_bytes=image_bytes, points=len(own),
                    image_width=views.width, seconds=time.monotonic() - t0)
        self.log(f"[robot {self.robot_id}] keyframe summary: {len(own)} points, {size / 1e3:.0f} kB "
                 f"(its images: {image_bytes / 1e6:.1f} MB)")
        if is_reference:
            self._set_status(alignment="reference")
            return

        summaries: dict[int, Summary] = {}
        boxes: dict[int, np.ndarray | None] = {}  # the field box each aligned neighbour sent
        tried: dict[int, str] = {}
        deadline = time.monotonic() + self.cfg.align_timeout_s
        while time.monotonic() < deadline and not self._stop.is_set():
            with self._state_lock:
                statuses = dict(self._neighbour_status)
            best = None
            for j in sorted(self.membership.live_neighbours):
                st = statuses.get(j)
                if st is None or st.alignment == "pending":
                    continue  # j does not know where it is yet
                knows_pose = st.alignment == "reference" or st.alignment.startswith("coarse")
                if not knows_pose and not self._box_pending:
                    tried[j] = "it found no pose either"
                    continue
                if j not in summaries:
                    raw = self.net.query(self.keys.keyframes(j), timeout=self.cfg.join_timeout_s)
                    if raw is None:
                        continue
                    try:
                        km = codec.decode(raw, self.status_expect, kind="keyframes", key=self.keys.parse(self.keys.keyframes(j)))
                        summaries[j] = Summary(km.descriptors, km.points, km.keyframe_index, acfg.descriptor_scale,
                                               keypoints=km.keypoints, keyframe_cameras=km.keyframe_cameras)
                        boxes[j] = km.box_from_shared
                    except (Rejected, ValueError) as e:
                        self._reject(getattr(e, "reason", "bad_field"), f"keyframes of robot {j}: {e}")
                        continue
                if not knows_pose:  # but its box (from someone who had one) still makes our model agree
                    tried[j] = "it found no pose either"
                    continue
                if self._box_pending and boxes.get(j) is None:
                    tried[j] = "it sent no field box"
                    continue
                res = estimate_relative(summaries[j], own, acfg)
                tried[j] = res.reason
                if not res.success:
                    continue
                p = st.pose
                t_g_from_j = sim3_from_params(torch.tensor(p[0], dtype=torch.float64),
                                              torch.tensor(p[1:4], dtype=torch.float64),
                                              torch.tensor(p[4:7], dtype=torch.float64))
                candidate = t_g_from_j @ torch.from_numpy(res.T_a_from_b)
                if best is None or res.inliers > best[1]:
                    best = (j, res.inliers, candidate, res.rotation_sigma_deg)
            if best is not None:
                # sigma is that of the last hop only: j's own uncertainty is not in its status.
                j, inliers, T, sigma = best
                if self._box_pending:
                    self._adopt_box(boxes[j], f"robot {j}")
                    serve_summary()  # with the box: robots aligning through us need it too
                self.trainer.pose.set_initial(T.float(), sigma_deg=sigma)
                with torch.no_grad():
                    self._set_status(alignment=f"coarse via {j}: {inliers} inliers",
                                     pose7=pose_summary(self.trainer.pose.matrix())["params7"])
                lr_scale = self.trainer.pose_lr_scale()
                self._event("aligned", via=j, inliers=inliers, seconds=time.monotonic() - t0, pose_lr_scale=lr_scale,
                            rotation_sigma_deg=sigma if math.isfinite(sigma) else None)
                self.log(f"[robot {self.robot_id}] coarse alignment via robot {j}: {inliers} inliers, rotation "
                         f"sigma {sigma:.3f} deg (pose learns at {lr_scale:.3g}x)")
                return
            if tried and len(tried) == len(self.membership.live_neighbours) and all(
                    statuses.get(j) is not None and statuses[j].alignment.startswith(("reference", "coarse", "identity"))
                    for j in self.membership.live_neighbours):
                break  # every neighbour knows its pose and none matched: no overlap
            self._stop.wait(0.5)
        reason = "; ".join(f"{j}: {r}" for j, r in sorted(tried.items())) or "no aligned neighbour answered"
        if self._box_pending:
            sent = [j for j, b in sorted(boxes.items()) if b is not None]
            if sent:  # no pose, but the swarm's box: at least our model agrees with theirs
                self._adopt_box(boxes[sent[0]], f"robot {sent[0]} (without a pose)")
                serve_summary()
            else:
                self._box_pending = False
                self._event("field_box", source="own estimate (no neighbour sent one)")
                self.log(f"[robot {self.robot_id}] no neighbour sent the field box: keeping our own estimate; "
                         "neighbours with another box will refuse our snapshots (bad_signature)")
        self._set_status(alignment="identity (coarse step found nothing)")
        self._event("alignment_failed", reason=reason)
        self.log(f"[robot {self.robot_id}] coarse alignment found nothing ({reason}); starting from the identity")

    # ------------------------------------------------------------------ checkpoints
    def _checkpoint(self) -> None:
        state = {
            "round": self.round,
            "robot_id": self.robot_id,
            "trainer": self.trainer.state_dict(),
            "elected": self.elected,
            "training": self.training,  # the dataclass itself: load_for_eval rebuilds the robot from it
            "box_from_shared": self.trainer.box_from_shared.cpu(),
            "signature": self.spec.signature(),
        }
        _atomic_torch_save(state, self.run_dir / CHECKPOINT)
        if self.cfg.keep_rounds:
            (self.run_dir / "rounds").mkdir(exist_ok=True)
            snap = {"round": self.round, "field": self.trainer.field.state_dict(),
                    "grid": self.trainer.grid.state_dict(), "pose": self.trainer.pose.state_dict()}
            _atomic_torch_save(snap, self.run_dir / "rounds" / f"{self.round:05d}.pt")

    def _resume(self) -> bool:
        path = self.run_dir / CHECKPOINT
        if not path.is_file():
            return False
        try:
            state = torch.load(path, map_location=self.trainer.device, weights_only=False)
            if self._box_pending and "box_from_shared" in state:  # learnt before the restart
                self._adopt_box(state["box_from_shared"].double().cpu().numpy(), "our checkpoint")
            if state.get("signature") != self.spec.signature():
                raise ValueError("the model in the checkpoint differs from the configured one")
            self.trainer.load_state_dict(state["trainer"])
        except Exception as e:
            raise RuntimeError(f"cannot resume from {path}: {e} (move it away to start fresh)") from None
        self.round = int(state["round"])
        self.elected = bool(state.get("elected", False))
        self.mailbox.advance(self.round)
        self._event("resumed", from_round=self.round)
        self.log(f"[robot {self.robot_id}] resumed from {path} at round {self.round}")
        return True

    # ------------------------------------------------------------------ the round loop
    def stop(self) -> None:
        self._stop.set()
        self.mailbox.notify()

    def _check_stop(self, _step: int = 0) -> None:
        if self._stop.is_set():
            raise Stop()
        # A failover must not wait for the end of the round: apply it between steps.
        if (self.membership.reference == self.robot_id) != self.elected:
            self._apply_reference()

    def _wait_for_roster(self) -> None:
        deadline = time.monotonic() + self.cfg.startup_wait_s
        everyone = set(self.swarm.topology.ids)
        while time.monotonic() < deadline and not self._stop.is_set():
            self._refresh_membership()
            if set(self.membership.alive) >= everyone:
                return
            time.sleep(0.1)
        missing = sorted(everyone - set(self.membership.alive))
        if missing:
            self.log(f"[robot {self.robot_id}] starting without {missing} (not seen within "
                     f"{self.cfg.startup_wait_s:.0f} s)")

    def run(self) -> int:
        """Returns the number of rounds completed by this process."""
        cfg = self.cfg
        resumed = self._resume()
        self.net.declare_alive()
        self.net.watch_alive(self._on_alive)
        for j in sorted(self.membership.neighbours):
            self.net.subscribe(self.keys.theta_for(j, self.robot_id), self._on_theta)
            self.net.subscribe(self.keys.status(j), self._on_status)
            self._senders[j] = NeighbourSender(
                self.net, lambda k, j=j: self.keys.theta(self.robot_id, k, to=j),
                lambda text, j=j: self.log(f"[robot {self.robot_id}] snapshot to robot {j} not sent: {text}"))
            self._pullers[j] = NeighbourPuller(
                lambda k, j=j: self._pull_latest(j, min_round=k),
                lambda text, j=j: self.log(f"[robot {self.robot_id}] asking robot {j} for its snapshot: {text}"))
        self._heartbeat = threading.Thread(target=self._heartbeat_loop, name="heartbeat", daemon=True)
        self._heartbeat.start()
        completed = 0
        try:
            self._wait_for_roster()
            if cfg.initial_pose == "coarse" and not resumed:
                self._coarse_alignment()
            self._join_current_round()
            self._apply_reference()
            self._event("start", resumed=resumed, alive=sorted(self.membership.alive),
                        reference=self.membership.reference)
            stats0 = self.net.stats()
            self._publish_theta(self.round)
            heard, _ = self._barrier(self.round)
            heard = self._catch_up(heard)
            self.mailbox.advance(self.round)
            while self.round < self.training.rounds:
                self._check_stop()
                completed += self._one_round(heard_in=heard, stats_before=stats0)
                stats0 = self.net.stats()
                heard = self._last_heard
            self._write_done()
            deadline = time.monotonic() + cfg.linger_s  # our last snapshot must still get out
            for sender in self._senders.values():
                sender.idle(max(deadline - time.monotonic(), 0.0))
            self._stop.wait(max(deadline - time.monotonic(), 0.0))
        except Stop:
            self.log(f"[robot {self.robot_id}] stopped at round {self.round} (checkpoint of round "
                     f"{self.round} kept)")
        finally:
            self._stop.set()
            for worker in [*self._senders.values(), *self._pullers.values()]:
                worker.close()
            if self._heartbeat is not None:
                self._heartbeat.join(timeout=2 * cfg.heartbeat_s + 1)
            self._events.close()
            self._telemetry.close()
        return completed

    def _one_round(self, heard_in: dict[int, ThetaSnapshot], stats_before: dict[str, Any]) -> int:
        k = self.round
        t0 = time.monotonic()
        self._set_status(phase="training")
        self.trainer.begin_round(k, {j: _to_torch(m) for j, m in heard_in.items()})
        stats = self.trainer.train(self.training.steps_per_round, on_step=self._check_stop)
        self.round = k + 1
        t_compute = time.monotonic() - t0
        self._round_compute_s = t_compute
        self._publish_theta(self.round)
        self._set_status(phase="waiting")
        heard, waited = self._barrier(self.round)
        self._apply_reference()  # a failover seen while waiting takes effect now, not next round
        self.trainer.end_round({j: _to_torch(m) for j, m in heard.items()})
        heard = self._catch_up(heard)
        self.mailbox.advance(self.round)  # slide the window: keeps accepting up to round + max_ahead
        self._last_heard = heard
        self._checkpoint()

        psnr = None
        evaluate = self.cfg.eval_every > 0 and (self.round % self.cfg.eval_every == 0
                                                or self.round == self.training.rounds)
        if evaluate and self.setup.holdout is not None:
            scores = self.trainer.evaluate(self.setup.holdout, frame="local", with_ssim=False)
            psnr = sum(scores["psnr"]) / len(scores["psnr"])
        net = self.net.stats()
        bytes_in = {int(j): net["bytes_in"].get(j, 0) - stats_before["bytes_in"].get(j, 0) for j in net["bytes_in"]}
        bytes_out = net["bytes_out_total"] - stats_before["bytes_out_total"]
        with torch.no_grad():
            pose = pose_summary(self.trainer.pose.matrix())
        record = {
            "robot": self.robot_id, "round": self.round, "time": time.time(), "monotonic": time.monotonic(),
            "loss": stats.loss, "rgb_loss": stats.rgb_loss, "depth_loss": stats.depth_loss,
            "batch_psnr": stats.batch_psnr, "psnr": psnr, "samples_per_ray": stats.samples_per_ray,
            "pose": self.trainer.pose.matrix().detach().double().cpu().tolist(),
            "pose_rotation_deg": pose["rotation_deg"], "pose_translation": pose["translation"],
            "pose_scale": pose["scale"], "reference": self.membership.reference, "elected": self.elected,
            "epoch": self.membership.epoch, "live_neighbours": sorted(self.membership.live_neighbours),
            "reachable": sorted(self._reachable_neighbours()),
            "heard": sorted(heard), "bytes_in": {str(j): b for j, b in bytes_in.items() if b},
            "bytes_out": bytes_out, "seconds_compute": t_compute, "seconds_wait": waited,
            "seconds_last_put": {str(j): round(x.last_seconds, 3) for j, x in self._senders.items()},
            "steps": stats.steps, "seconds_per_step": stats.seconds / max(stats.steps, 1),
            "rejected": dict(self.rejected), "alignment": self._last_status.get("alignment"),
        }
        with self._state_lock:
            self._telemetry.write(json.dumps(record) + "\n")
            self._telemetry.flush()
        self._set_status(phase="round_done", loss=stats.loss, psnr=psnr, heard=sorted(heard),
                         bytes_in_total=net["bytes_in_total"], bytes_out_total=net["bytes_out_total"],
                         seconds_compute=t_compute, seconds_wait=waited, pose7=pose["params7"])
        live = sorted(self._reachable_neighbours())
        psnr_text = f"{psnr:5.2f} dB" if psnr is not None else "   n/a  "
        self.log(
            f"[robot {self.robot_id}] round {self.round:3d}/{self.training.rounds} | loss {stats.loss:.5f} | "
            f"psnr {psnr_text} | pose {pose['rotation_deg']:6.2f} deg, |t| "
            f"{math.sqrt(sum(x * x for x in pose['translation'])):.3f}, s {pose['scale']:.3f}"
            f"{' (ref)' if self.elected else ''} | heard {sorted(heard)}/{live} | "
            f"in {sum(bytes_in.values()) / 1e6:.1f} MB out {bytes_out / 1e6:.1f} MB | "
            f"compute {t_compute:.1f} s wait {waited:.1f} s"
        )
        return 1

    def _set_status(self, **fields: Any) -> None:
        with self._state_lock:
            self._last_status.update(fields)

    def _write_done(self) -> None:
        done = {"robot": self.robot_id, "rounds": self.round, "time": time.time(), "rejected": dict(self.rejected)}
        (self.run_dir / "done.json").write_text(json.dumps(done, indent=2) + "\n")
        self.log(f"[robot {self.robot_id}] done: {self.round} rounds")


def load_for_eval(run_dir: str | Path, data_dir: str | Path, round: int | None = None):
    """Rebuild a robot's trainer from its run folder (final checkpoint or ``rounds/<k>.pt``)."""
    from agent.data.loaders import load_views

    run_dir = Path(run_dir)
    state = torch.load(run_dir / CHECKPOINT, map_location="cpu", weights_only=False)
    training: SwarmTrainingConfig = state["training"]
    views = load_views(data_dir, width=training.image_width, sfm_cache_dir=run_dir / SFM_CACHE)  # images-only: the run's SfM
    setup = build_robot(int(state["robot_id"]), views, state["box_from_shared"], training)
    trainer = setup.trainer
    trainer.load_state_dict(state["trainer"])
    if round is not None:
        snap = torch.load(run_dir / "rounds" / f"{round:05d}.pt", map_location="cpu", weights_only=False)
        trainer.field.load_state_dict(snap["field"])
        trainer.grid.load_state_dict(snap["grid"])
        trainer.pose.load_state_dict(snap["pose"])
    return trainer
