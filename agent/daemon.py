"""The long-running agent of one robot: the round loop, and the callbacks that feed it.

The daemon is the application layer between the trainer (``agent``) and the protocol
(``protocol``: keys, messages, codec, rounds, membership, exchange). It never imports Zenoh: the
network is injected (a :class:`protocol.network.Network`: ``ZenohTransport`` in production,
``LoopbackNetwork`` in tests), as rmw_zenoh and Swarm-SLAM keep transport, membership, exchange
policy and application logic apart. Its other concerns live beside it: ``agent.bootstrap``
(field box, coarse alignment), ``agent.checkpoint`` (the run folder), ``agent.telemetry``.

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
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Literal, Mapping

import numpy as np
import torch
from torch import Tensor

from agent.align import AlignConfig
from agent.bootstrap import Bootstrap, BootstrapTiming
from agent.checkpoint import CheckpointError, RobotCheckpoint, RunFolder, load_into
from agent.config_io import check
from agent.data.capture import estimate_scene_box, field_box_mismatch
from agent.data.stream import ViewStream
from agent.data.views import Views
from agent.geometry import box_from_center, pose_summary
from agent.swarm import RobotSetup, SwarmTrainingConfig, build_robot
from agent.rejoin import Rejoin, RejoinPolicy, to_torch
from agent.round_report import RoundReport, RoundTimes
from agent.telemetry import EventLog, JsonLines, PlateauRule, Reporter, StatusBoard
from agent.vigilance import Vigilance
from protocol import codec
from protocol.compression import CompressionConfig
from protocol.evidence import ClaimPace
from protocol.exchange import ExchangeTiming, SnapshotExchange
from protocol.keys import Keys
from protocol.membership import Membership, Topology
from protocol.messages import Alignment, ModelSpec, Status, ThetaSnapshot
from protocol.network import Network
from protocol.presence import Presence
from protocol.rounds import Mailbox


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
    keep_rounds: bool = False  # also save rounds/<k>.safetensors (field + pose) for per-round reports
    join_timeout_s: float = 5.0  # query timeout for neighbours' newest snapshots
    pull_after_s: float = 2.0  # a neighbour's snapshot missing this long is asked for (pulled; PullPacing)
    silent_after_s: float = 3.0  # the barrier stops waiting for a neighbour that sent nothing for this long, token or not
    # A robot that finds its neighbours this many rounds ahead when it comes back (restart, skip
    # after a freeze or a cut) takes their mean model instead of its own, and forgets its duals:
    # its own is stale, and C-ADMM would pull the neighbours back towards it. 0 = keep its own.
    adopt_after_rounds: int = 2
    resend_delay_s: float = 1.0  # re-push our snapshot this long after a neighbour's link appears
    # A neighbour's claimed round counts only as far as its pace explains: one round per our own
    # fastest recent round divided by this (protocol.evidence.ClaimPace). Robots may differ in speed.
    pace_margin: float = 2.0
    refused_after: int = 3  # a neighbour whose snapshots were refused this many rounds in a row is not waited for
    # Initial relative pose: "identity" (the paper) or "coarse": match compact keyframe summaries
    # (descriptors + 3-D points, never images) with neighbours whose pose is already known.
    # None: what the swarm's frames call for (agent.frames: identity when shared, else coarse)
    initial_pose: Literal["identity", "coarse"] | None = None
    align_timeout_s: float = 60.0  # give up on the coarse step after this long (identity start)
    # Width of the images the keyframe summary is computed from; None: the folder's own size, even
    # when training runs smaller (sharper features place a neighbour's frame more precisely).
    summary_width: int | None = None
    # An unaligned robot (its coarse step found nothing) trains alone, out of consensus, and
    # retries every this many rounds (0 = never); after realign_from_field_after rounds its
    # retries match renders of its own trained field, whose depth places every feature.
    realign_every: int = 2
    realign_from_field_after: int = 4
    plateau: PlateauRule = field(default_factory=PlateauRule)  # when a flat, high loss is worth a warning
    isolated_after: int = 3  # warn after this many rounds in a row without any neighbour's snapshot (0 = never)
    # How snapshots go on the wire ([daemon.exchange]): delta+uniform (default) | none (float32) | ...
    exchange: CompressionConfig = field(default_factory=CompressionConfig)

    def __post_init__(self) -> None:
        if self.round_timeout_s <= 0 or self.heartbeat_s <= 0 or self.threads < 1:
            raise ValueError("round_timeout_s and heartbeat_s must be > 0, threads >= 1")
        if self.summary_width is not None and (not isinstance(self.summary_width, int) or self.summary_width < 8):
            raise ValueError(f"summary_width must be >= 8 pixels (or unset: the images' own size), got {self.summary_width!r}")
        if self.wire_dtype != "float32" and self.exchange.compression != "none":
            raise ValueError(f"daemon.wire_dtype = {self.wire_dtype!r} and daemon.exchange.compression = "
                             f"{self.exchange.compression!r}: choose one (compression = \"fp16\" is float16)")
        check(self, isolated_after=">= 0", pace_margin=">= 1", refused_after=">= 1")
        if self.silent_after_s < 2 * self.heartbeat_s:
            raise ValueError(f"silent_after_s ({self.silent_after_s}) must be at least two heartbeats "
                             f"({2 * self.heartbeat_s} s): one lost heartbeat must not count as silence")

    def exchange_timing(self) -> ExchangeTiming:
        return ExchangeTiming(self.round_timeout_s, self.pull_after_s, self.silent_after_s, self.join_timeout_s,
                              self.resend_delay_s, self.refused_after)


@dataclass(frozen=True)
class SwarmIdentity:
    """Who the swarm is: its name and the static graph of who may talk to whom."""

    name: str
    topology: Topology


def _outside_consensus(alignment: Alignment) -> bool:
    return alignment in (Alignment.UNALIGNED, Alignment.PENDING)


class Stop(Exception):
    """Raised inside training to leave the round loop promptly (SIGTERM, test harness)."""


def model_spec(setup: RobotSetup) -> ModelSpec:
    """Layout + architecture of theta: robots whose fields differ must not mix parameters."""
    trainer = setup.trainer
    arch = {"field": dataclasses.asdict(trainer.cfg.field),
            "box_from_shared": [round(float(x), 9) for x in trainer.box_from_shared.flatten()],
            "init_seed": trainer.cfg.init_seed}
    return ModelSpec.from_tensors({n: t.cpu().numpy() for n, t in trainer.theta().items()}, arch)


def _to_numpy(theta: Mapping[str, Tensor]) -> dict[str, np.ndarray]:
    return {n: np.ascontiguousarray(t.detach().cpu().numpy(), dtype=np.float32) for n, t in theta.items()}


class Daemon:
    """One robot in the swarm. ``run()`` blocks until all rounds are done (or ``stop()``)."""

    def __init__(self, robot_id: int, views: Views, box_from_shared: Tensor | None, swarm: SwarmIdentity,
                 training: SwarmTrainingConfig, cfg: DaemonConfig, network: Network, run_dir: Path,
                 initial_pose: Tensor | None = None, log: Callable[[str], None] = print,
                 warn: Callable[[str], None] | None = None, summary_views: Views | None = None,
                 align: AlignConfig | None = None, stream: ViewStream | None = None) -> None:
        """summary_views: the same views at the resolution the keyframe summary is computed from
        (``cfg.summary_width``); None: the training views. stream: views that grow (its first: ``views``)."""
        if cfg.initial_pose is None or training.train.pose.mode is None:
            raise ValueError("daemon.initial_pose and training.train.pose.mode are unset: resolve them from the "
                             "swarm's frames first (agent.frames.resolve_pose_settings; load_swarm_file does)")
        if robot_id not in swarm.topology.ids:
            raise ValueError(f"robot {robot_id} is not in the swarm's robots {list(swarm.topology.ids)}")
        if box_from_shared is None and cfg.initial_pose != "coarse":
            raise ValueError("no field box in the scene (robots with images only): the reference derives it from "
                             "its SfM and shares it with the keyframes, so daemon.initial_pose must be 'coarse'")
        if summary_views is not None and (summary_views.names != views.names
                                          or not torch.allclose(summary_views.c2w, views.c2w)):
            raise ValueError("summary_views must be the training views at another resolution (same names and poses)")
        torch.set_num_threads(cfg.threads)
        self.robot_id, self.swarm, self.training, self.cfg, self.net = robot_id, swarm, training, cfg, network
        self.keys = Keys(swarm.name)
        self.folder = RunFolder(run_dir)
        self.round = 0
        self.elected = False  # pose frozen because this robot is the reference
        self._stop = threading.Event()
        self.report = Reporter(robot_id, log, EventLog(self.folder.events, robot_id), lambda: self.round, warn)
        self._telemetry = JsonLines(self.folder.telemetry)
        box_known = box_from_shared is not None
        if not box_known:  # a provisional box from our own views (the right one if we are the reference)
            center, half_size, _ = estimate_scene_box(views, training.train.field.unbounded, cameras_elsewhere=True)
            box_from_shared = box_from_center(center, half_size)
        elif (mismatch := field_box_mismatch(views, training.train.field.unbounded)) is not None:
            self.report.warn(mismatch)  # the split sized the box for the field the images call for
        self.setup = build_robot(robot_id, views, box_from_shared, training, initial_pose, stream=stream)
        self._summarised = len(views)  # training keyframes in the keyframe summary served
        self.trainer = self.setup.trainer
        self.mailbox: Mailbox[ThetaSnapshot] = Mailbox(max_ahead=cfg.max_ahead, last_round=training.rounds)
        self.pace = ClaimPace()
        self.presence = Presence(network, self.keys, robot_id, swarm.topology, cfg.alive_expiry_s, cfg.heartbeat_s,
                                 self._stop, self._status_message, self._heard_status,
                                 lambda j: self.exchange.link_appeared(j), self._membership_changed,
                                 self.report.say, self.report.reject)
        self.membership = self.presence.membership
        self.exchange = SnapshotExchange(network, self.keys, robot_id, self.membership.neighbours, self.mailbox,
                                         self.presence.last_heard, cfg.exchange_timing(), self._stop, self.report.say,
                                         self.report.event, self.report.reject, self._claimed_round,
                                         cfg.exchange)
        initial = Alignment.IDENTITY if cfg.initial_pose == "identity" else Alignment.PENDING
        with torch.no_grad():
            self.board = StatusBoard(alignment=initial, alignment_detail="",
                                     pose7=pose_summary(self.trainer.pose.matrix())["params7"])
        align = (align or AlignConfig()).for_pose_mode(self.trainer.cfg.pose.mode)
        self.bootstrap = Bootstrap(self.trainer, summary_views if summary_views is not None else views, network,
                                   self.keys, self.membership, self.board, self.report, self._stop, align,
                                   BootstrapTiming(cfg.align_timeout_s, cfg.join_timeout_s), box_known,
                                   self._model_changed)
        self._model_changed()
        self._last_heard: dict[int, ThetaSnapshot] = {}
        self._round_compute_s: float | None = None  # our last round's training time: may we train through a gap?
        self._recent_compute_s: list[float] = []  # the last rounds' compute times: the pace a neighbour may keep
        self._moves: list[dict] = []  # joins and skips of this process, for done.json
        self.rejoin = Rejoin(RejoinPolicy(training.rounds, cfg.adopt_after_rounds, cfg.round_timeout_s,
                                          cfg.heartbeat_s), self.trainer, self.exchange, self.mailbox, self.report,
                             self._stop, self._consensus_peers, self._in_consensus, self._raw_claim)
        consensus = self.trainer.consensus
        self.vigilance = Vigilance(self.report, self.pace, self.exchange.refusals,
                                   consensus.clipper if consensus is not None else None)
        self.rounds_report = RoundReport(
            robot_id, training.rounds, self.setup, network, self.exchange, self.membership, self.presence.reachable,
            self.board, self.report, self._telemetry, eval_every=cfg.eval_every, plateau=cfg.plateau,
            isolated_after=cfg.isolated_after, compression=cfg.exchange.compression)

    def _model_changed(self) -> None:
        """(Re)derive what our snapshots are and what a neighbour's must look like (our box is in it)."""
        self.spec = model_spec(self.setup)
        self.exchange.expect = None if self.bootstrap.box_pending else codec.Expectation(
            swarm=self.swarm.name, spec=self.spec, allowed_senders=frozenset(self.swarm.topology.ids),
            max_wire_bytes=2 * self.spec.float32_bytes + (1 << 20),
            max_decompressed_bytes=self.spec.float32_bytes + (1 << 20))

    # ------------------------------------------------------------------ callbacks
    def _claimed_round(self, j: int) -> int | None:
        """The round neighbour j says, in its newest heartbeat, that it has completed, as far as
        its pace explains it (``protocol.evidence.ClaimPace``)."""
        return self.pace.credible(j)

    def _raw_claim(self, j: int) -> int | None:
        """j's claimed round as it says it, for the join's quorum (a lone far claim moves nothing there)."""
        status = self.board.peers().get(j)
        return None if status is None else status.round

    def _in_consensus(self) -> bool:
        """Whether this robot's frame is placed (reference, identity by configuration, coarse)."""
        return not _outside_consensus(self.board.own()["alignment"])

    def _consensus_peers(self) -> set[int]:
        """Reachable neighbours a round waits for and averages with: all but the unaligned (a
        neighbour still aligning is waited for: it joins as soon as its frame is placed)."""
        peers = self.board.peers()
        return {j for j in self.presence.reachable() if (st := peers.get(j)) is None
                or st.alignment is not Alignment.UNALIGNED}

    def _barrier(self) -> tuple[dict[int, ThetaSnapshot], float]:
        """The round's barrier; what it returns only from neighbours still in consensus when it ends
        (one that turned unaligned meanwhile is never averaged with)."""
        quarantined = self.trainer.consensus.clipper.quarantined if self.trainer.consensus is not None else set()
        heard, waited = self.exchange.barrier(self.round, lambda: self._consensus_peers() - quarantined)
        peers = self._consensus_peers()  # a quarantined neighbour's model is still measured (agent.robust)
        return {j: m for j, m in heard.items() if j in peers}, waited

    def _maybe_realign(self, heard: dict[int, ThetaSnapshot]) -> None:
        """Every few rounds an unaligned robot tries again; placed, it takes its neighbours' model
        (its own was trained in its own frame) and enters consensus."""
        n = self.cfg.realign_every
        if n <= 0 or self.round % n:
            return
        from_field = self.round >= self.cfg.realign_from_field_after and self.setup.stream is None  # renders: fixed views
        if not self.bootstrap.retry(from_field=from_field):
            return
        if heard:
            self.rejoin.adopt(heard, reset_duals=True)
        self.trainer.reset_occupancy()
        self.report.event("entered_consensus", neighbours=sorted(heard))
        self.report.say(f"aligned at round {self.round}: taking the neighbours' model {sorted(heard)}, in consensus now")

    def _grow_summary(self) -> None:
        """A stream's keyframe summary follows its keyframes, every ``realign_every`` rounds: an
        unaligned robot retries with its new places, an aligned one serves them to those still unplaced."""
        stream, n = self.setup.stream, self.cfg.realign_every
        if stream is None or n <= 0 or self.round % n or stream.training_keyframes == self._summarised:
            return
        self._summarised = stream.training_keyframes
        self.bootstrap.refresh_summary(stream)

    def _heard_status(self, status: Status) -> None:
        """A neighbour's heartbeat; one claiming a newer round may vouch for a snapshot the barrier holds."""
        before = self.pace.credible(status.sender)
        self.board.heard_from(status.sender, status)
        self.vigilance.heard_claim(status.sender, status.round, time.monotonic(), self.round)
        if before is None or (self.pace.credible(status.sender) or 0) > before:
            self.mailbox.notify()

    def _membership_changed(self, m: Membership) -> None:
        self.mailbox.notify()
        self.report.event("membership", alive=sorted(m.alive), reference=m.reference, epoch=m.epoch)

    def _apply_reference(self) -> None:
        """Freeze the pose when this robot becomes the reference; resume when it stops being it."""
        is_ref, epoch = self.membership.reference == self.robot_id, self.membership.epoch
        if is_ref and not self.elected:
            before = self.trainer.pose.matrix().detach().clone()
            self.trainer.pose.freeze()
            self.elected = True
            jump = float((self.trainer.pose.matrix().detach() - before).abs().max())
            self.report.event("reference_elected", epoch=epoch, pose_change=jump)
            self.report.say(f"I am the reference now (epoch {epoch}); pose frozen at its current estimate")
        elif not is_ref and self.elected:
            self.trainer.pose.unfreeze()
            self.elected = False
            self.report.event("reference_resigned", reference=self.membership.reference, epoch=epoch)
            self.report.say(f"robot {self.membership.reference} is the reference again; learning my pose")

    def _status_message(self) -> Status:
        s = self.board.own()
        return Status(
            swarm=self.swarm.name, sender=self.robot_id, round=self.round, epoch=self.membership.epoch,
            reference=self.membership.reference, phase=s.get("phase", "starting"), loss=s.get("loss"),
            psnr=s.get("psnr"), pose=s["pose7"], neighbours_heard=s.get("heard", []),
            bytes_in=int(s.get("bytes_in_total", 0)), bytes_out=int(s.get("bytes_out_total", 0)),
            rejected=self.report.rejected_counts(), alignment=s["alignment"], alignment_detail=s["alignment_detail"],
            wall_time=time.time(), seconds_compute=float(s.get("seconds_compute", 0.0)),
            seconds_wait=float(s.get("seconds_wait", 0.0)), alive_ages=self.presence.alive.report(),
            suspects=self.vigilance.suspects(), views=s.get("views"))

    # ------------------------------------------------------------------ checkpoints
    def _checkpoint(self) -> None:
        self.folder.save(RobotCheckpoint(self.round, self.robot_id, self.trainer.state_dict(), self.elected,
                                         self.training, self.trainer.box_from_shared.cpu(), self.spec.signature()))
        if self.cfg.keep_rounds:
            self.folder.save_round(self.round, self.trainer, self.robot_id)

    def _resume(self) -> bool:
        """Continue from our checkpoint, if there is one. One that cannot be used stops the robot
        with one line (CheckpointError) and stays where it is: resuming from a damaged or foreign
        state, or silently starting over, would both be worse than asking the user."""
        if (stale := self.folder.remove_stale_temporaries())[0]:
            self.report.say(f"removed {stale[0]} temporary file(s) of a save that never finished ({stale[1] / 1e6:.1f} MB)")
        try:
            ck = self.folder.load(self.robot_id)
        except CheckpointError as e:
            raise CheckpointError(e.path, f"cannot resume from it: {e.reason} (move it away to start fresh)") from None
        if ck is None:
            return False
        path = self.folder.checkpoint
        try:
            if ck.round > self.training.rounds:
                raise ValueError(f"it is of round {ck.round}, past training.rounds = {self.training.rounds}")
            if self.bootstrap.box_pending:  # learnt before the restart
                self.bootstrap.adopt_box(ck.box_from_shared.double().cpu().numpy(), "our checkpoint")
            if ck.signature != self.spec.signature():
                raise ValueError("the model in the checkpoint differs from the configured one")
            load_into(self.trainer, path, ck.trainer)
        except Exception as e:
            reason = e.reason if isinstance(e, CheckpointError) else str(e)
            raise CheckpointError(path, f"cannot resume from it: {reason} (move it away to start fresh)") from None
        self.round, self.elected = ck.round, ck.elected
        self.mailbox.advance(self.round)
        self.report.event("resumed", from_round=self.round)
        self.report.say(f"resumed from {path} at round {self.round}")
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
            self.presence.refresh()
            if set(self.membership.alive) >= everyone:
                return
            time.sleep(0.1)
        missing = sorted(everyone - set(self.membership.alive))
        if missing:
            self.report.warn(f"starting without {missing} (not seen within {self.cfg.startup_wait_s:.0f} s)")

    def run(self) -> int:
        """Returns the number of rounds completed by this process."""
        resumed = self._resume()
        if not resumed and self.cfg.exchange.compression.startswith("delta"):
            self.exchange.seed(_to_numpy(self.trainer.theta()))  # theta^0, which every robot holds
        self.exchange.start()
        self.presence.start()
        completed = 0
        try:
            self._wait_for_roster()
            if self.cfg.initial_pose == "coarse" and not resumed:
                self.bootstrap.coarse_alignment()
            if (move := self.rejoin.join(self.round)) is not None:
                self.round = move.to_round
                self._moves.append(move.record())
            self._apply_reference()
            self.vigilance.arm()
            self.report.event("start", resumed=resumed, alive=sorted(self.membership.alive),
                              reference=self.membership.reference)
            self.rounds_report.start()
            if self._in_consensus():
                self._publish_theta(self.round)
            heard = self._barrier()[0]
            heard = self._catch_up(heard)
            self.mailbox.advance(self.round)
            if self._moves:  # a join or a skip leaves a checkpoint of where it landed
                self._checkpoint()
            while self.round < self.training.rounds:
                self._check_stop()
                completed += self._one_round(heard_in=heard)
                heard = self._last_heard
            self.folder.write_done(self.robot_id, self.round, self.report.rejected_counts(), steps=self.trainer.step,
                                   moves=self._moves)
            self.report.say(f"done: {self.round} rounds")
            deadline = time.monotonic() + self.cfg.linger_s  # our last snapshot must still get out
            self.exchange.wait_sent(self.cfg.linger_s)
            self._stop.wait(max(deadline - time.monotonic(), 0.0))
        except Stop:
            self.report.say(f"stopped at round {self.round} (checkpoint of round {self.round} kept)")
        finally:
            self._stop.set()
            self.exchange.close()
            self.presence.join()
            self.report.close()
            self._telemetry.close()
        return completed

    def _one_round(self, heard_in: dict[int, ThetaSnapshot]) -> int:
        k = self.round
        t0, cpu0 = time.monotonic(), time.process_time()
        aligned = self._in_consensus()
        self.board.set(phase="training")
        self.setup.admit()  # the keyframes that arrived meanwhile (a stream)
        self.trainer.begin_round(k, to_torch(heard_in if aligned else {}), own=self._as_received(k))
        stats = self.trainer.train(self.training.steps_per_round, on_step=self._check_stop)
        self.round = k + 1
        t_compute = self._round_compute_s = time.monotonic() - t0
        cpu_compute = time.process_time() - cpu0
        if aligned:  # an unaligned robot's field is in its own frame: nobody may average with it
            self._publish_theta(self.round)
        self.board.set(phase="waiting")
        self.presence.beat_now()
        heard, waited = self._barrier()  # unaligned: for the pace only
        self._apply_reference()  # a failover seen while waiting takes effect now, not next round
        self.trainer.end_round(to_torch(heard if aligned else {}), own=self._as_received(self.round),
                               rounds={j: m.round for j, m in heard.items()})
        if (consensus := self.trainer.consensus) is not None:
            self.vigilance.consensus_news(consensus.news, self.round)
        # A neighbour's pace is bounded by a round's compute, not by our barrier: a robot that waits
        # out timeouts (restarted behind its neighbours) would otherwise disbelieve honest ones.
        self._recent_compute_s = (self._recent_compute_s + [t_compute])[-8:]
        self.pace.min_round_s = min(self._recent_compute_s) / self.cfg.pace_margin
        heard = self._catch_up(heard)
        self.mailbox.advance(self.round)  # slide the window: keeps accepting up to round + max_ahead
        self._grow_summary()
        if not aligned:
            self._maybe_realign(heard)
        self._last_heard = heard
        self._checkpoint()
        factors = consensus.clipper.factors if consensus is not None else {}
        self.rounds_report.round_done(self.round, stats, sorted(heard) if aligned else None, self.elected,
                                      RoundTimes(t_compute, cpu_compute, waited), self.spec.float32_bytes,
                                      clipped={j: f for j, f in factors.items() if f < 1}, suspects=self.vigilance.suspects())
        return 1

    # ------------------------------------------------------------------ snapshots, joining, catching up
    def _publish_theta(self, round_index: int) -> None:
        msg = ThetaSnapshot(swarm=self.swarm.name, sender=self.robot_id, round=round_index,
                            epoch=self.membership.epoch, signature=self.spec.signature(),
                            tensors=_to_numpy(self.trainer.theta()))
        self.exchange.publish(msg, self.spec, self.cfg.wire_dtype, self.cfg.compression)

    def _as_received(self, round_index: int) -> dict[str, Tensor] | None:
        """Our theta of ``round_index`` as the neighbours rebuilt it, when a lossy exchange made it
        differ: C-ADMM then prices the same disagreement at both ends of an edge (y_ij = -y_ji)."""
        held = self.exchange.encoder.held_by_receivers()
        if held is None or held[0] != round_index:
            return None
        return {n: torch.from_numpy(np.array(a, dtype=np.float32, copy=True)) for n, a in held[1].items()}

    def _catch_up(self, heard: dict[int, ThetaSnapshot]) -> dict[int, ThetaSnapshot]:
        """Skip to the round a quorum of neighbours reached without us (``agent.rejoin``)."""
        move = self.rejoin.catch_up(self.round, self._round_compute_s)
        if move is None:
            return heard
        self.round = move.to_round
        self._moves.append(move.record())
        # Neighbours already at the target are waiting for our snapshot of it: send our current
        # theta as such at once, or they time out and the swarm stays out of phase.
        self._publish_theta(move.to_round)
        return move.heard
