"""How a swarm trains: the shared schedule, the per-robot set-up, and the in-process simulation.

``build_robot`` is the single place where a robot's trainer is made, used by both the daemon
and :class:`Simulation`, so that the simulation "runs exactly the trainer code the daemon will
run": same seeds, same held-out views, same order of operations within a round:

    begin_round(k, theta_j^k)  ->  B steps  ->  publish theta_i^{k+1}
    ->  receive theta_j^{k+1}  ->  end_round (dual update)
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Callable, Mapping

import numpy as np
import torch
from torch import Tensor

from agent.consensus import ConsensusConfig, disagreement
from agent.data.stream import ViewStream
from agent.data.views import Views
from agent.geometry import pose_summary
from agent.telemetry import RoundRecord
from agent.trainer import RobotTrainer, StepStats, TrainConfig
from protocol import codec
from protocol.compression import BaseBook, CompressionConfig, SnapshotEncoder
from protocol.messages import ModelSpec, ThetaSnapshot


@dataclass
class SwarmTrainingConfig:
    """Settings every robot of a swarm must share (they define theta^0 and the schedules)."""

    rounds: int = 10
    steps_per_round: int = 100
    seed: int = 0
    own_holdout_every: int = 10  # every k-th of a robot's own views is kept for its log line's PSNR; 0 = none
    # Train on the robot's images downscaled to this width (None: as they are). A folder of
    # images only still gets its SfM from the full-size images, which need the detail.
    image_width: int | None = None
    consensus: ConsensusConfig = field(default_factory=ConsensusConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    def __post_init__(self) -> None:
        if self.rounds < 1 or self.steps_per_round < 1:
            raise ValueError("rounds and steps_per_round must be >= 1")
        if self.own_holdout_every < 0:
            raise ValueError("own_holdout_every must be >= 0")
        if self.image_width is not None and self.image_width < 8:
            raise ValueError(f"image_width must be >= 8 pixels, got {self.image_width}")

    @property
    def total_steps(self) -> int:
        return self.rounds * self.steps_per_round


def robot_seed(swarm_seed: int, robot_id: int) -> int:
    """Each robot's sampling seed: distinct per robot, reproducible from the swarm seed."""
    return swarm_seed * 100_003 + robot_id


def own_holdout_split(views: Views, every: int) -> tuple[Views, Views | None]:
    """Own views -> (training views, held-out views): indices k-1, 2k-1, ... are held out.

    The first view is never held out: in the paper's convention it defines the local frame.
    """
    if every <= 0 or len(views) < 2:
        return views, None
    held = [i for i in range(len(views)) if i % every == every - 1]
    if not held:
        return views, None
    keep = [i for i in range(len(views)) if i % every != every - 1]
    return views.subset(keep), views.subset(held)


@dataclass
class RobotSetup:
    robot_id: int
    trainer: RobotTrainer
    holdout: Views | None  # the robot's own held-out views (local frame), for its log line
    stream: ViewStream | None = None  # views that arrive while it trains (None: all given at start)

    def admit(self) -> None:
        """Take in the keyframes that arrived (a stream), and the held-out views they bring."""
        if self.stream is not None:
            self.stream.admit()
            self.holdout = self.stream.holdout_views()


def build_robot(
    robot_id: int,
    views: Views,
    box_from_shared: Tensor,
    cfg: SwarmTrainingConfig,
    initial_pose: Tensor | None = None,
    is_reference: bool = False,
    stream: ViewStream | None = None,
    view_rows: int | None = None,
) -> RobotSetup:
    """stream: the robot's views grow while it trains; ``views`` are then its training keyframes so
    far (:meth:`ViewStream.initial_views`), and the stream holds its own held-out ones out.
    view_rows: the per-view state's rows of a checkpoint to load (:func:`agent.checkpoint.view_rows`)."""
    if stream is None:
        train_views, holdout = own_holdout_split(views, cfg.own_holdout_every)
    else:
        train_views, holdout = views, stream.holdout_views()
    tcfg = dataclasses.replace(
        cfg.train, seed=robot_seed(cfg.seed, robot_id), init_seed=cfg.seed, total_steps=cfg.total_steps
    )
    trainer = RobotTrainer(train_views, tcfg, box_from_shared, initial_pose, consensus=cfg.consensus, rays=stream,
                           view_rows=view_rows)
    if stream is not None:
        stream.attach(trainer)
    if is_reference:
        trainer.pose.freeze()
    return RobotSetup(robot_id, trainer, holdout, stream)


class ProtocolWire:
    """What neighbours receive of a robot's theta in the simulation: the daemon's own encode,
    decode and base resolution (:mod:`protocol.compression`), so a compressed swarm trains in one
    process on exactly the models the daemons would hold; ``sent[i]`` lists the push sizes."""

    SWARM = "simulation"

    def __init__(self, cfg: CompressionConfig, theta0: Mapping[str, Tensor], robots: list[int]) -> None:
        numpy0 = {n: t.detach().cpu().numpy().astype(np.float32) for n, t in theta0.items()}
        self.spec = ModelSpec.from_tensors(numpy0)
        self.expect = codec.Expectation(self.SWARM, self.spec, max_wire_bytes=8 * self.spec.num_values + (1 << 20),
                                        max_decompressed_bytes=8 * self.spec.num_values + (1 << 20))
        self.encoders = {i: SnapshotEncoder(cfg) for i in robots}
        self.book = BaseBook()  # every receiver of a sender holds the same reconstruction
        self.sent: dict[int, list[int]] = {i: [] for i in robots}
        if cfg.compression.startswith("delta"):  # as the daemons: theta^0 is everyone's first base
            for i in robots:
                self.encoders[i].seed(numpy0)
                self.book.seed(i, numpy0)

    def __call__(self, sender: int, round_index: int, theta: Mapping[str, Tensor]) -> dict[str, Tensor]:
        tensors = {n: np.ascontiguousarray(t.detach().cpu().numpy(), dtype=np.float32) for n, t in theta.items()}
        msg = ThetaSnapshot(self.SWARM, sender, round_index, 0, self.spec.signature(), tensors)
        push, _ = self.encoders[sender].encode(msg, self.spec, "zstd")
        self.sent[sender].append(len(push))
        got = self.book.resolve(codec.decode(push, self.expect, kind="theta"), self.spec)
        assert isinstance(got, ThetaSnapshot), f"robot {sender} round {round_index}: {got}"
        return {n: torch.from_numpy(np.array(a, copy=True)) for n, a in got.tensors.items()}


class Simulation:
    """N robots on a topology in one process, exchanging theta through memory (or a ``wire``:
    ``wire(sender, round, theta) -> what its neighbours receive``, e.g. :class:`ProtocolWire`)."""

    def __init__(
        self,
        robots: Mapping[int, Views],
        neighbours: Mapping[int, frozenset[int] | set[int]],
        box_from_shared: Tensor,
        cfg: SwarmTrainingConfig,
        initial_poses: Mapping[int, Tensor] | None = None,
        reference_id: int | None = None,
        wire: Callable[[int, int, Mapping[str, Tensor]], dict[str, Tensor]] | None = None,
        streams: Mapping[int, ViewStream] | None = None,
    ) -> None:
        """streams: robots whose views grow while they train (``robots[i]`` its first keyframes)."""
        self.cfg = cfg
        self.wire = wire
        # With a lossy wire, C-ADMM runs on what both ends of an edge hold: each robot's own
        # theta as its neighbours received it (the public copy), so y_ij = -y_ji stays exact.
        self.on_public = True
        # Benchmarks only: the anchors (theta_i^k + theta_j^k) / 2 from the robot's exact theta_i^k
        # rather than its public copy, duals still on the public copies (no gain on lego: results.md)
        self.anchor_on_exact = False
        # Tests and benchmarks of a hostile robot: ``forge(sender, round, public) -> what its
        # neighbours receive instead`` (None: the public copy). The sender still anchors on its
        # public copy, as a real robot that forges only what it sends does.
        self.forge: Callable[[int, int, dict[str, Tensor]], dict[str, Tensor] | None] | None = None
        # ... and of one that falls silent: robot -> the first round whose snapshot nobody hears
        self.silent_from: dict[int, int] = {}
        self.public: dict[int, dict[str, Tensor]] = {}
        self.neighbours = {i: sorted(neighbours[i]) for i in robots}
        self.reference_id = min(robots) if reference_id is None else reference_id
        initial_poses = initial_poses or {}
        self.robots = {
            i: build_robot(i, v, box_from_shared, cfg, initial_poses.get(i), is_reference=(i == self.reference_id),
                           stream=(streams or {}).get(i))
            for i, v in sorted(robots.items())
        }
        self.thetas = {i: r.trainer.theta() for i, r in self.robots.items()}  # theta^0
        self.round = 0

    @property
    def trainers(self) -> dict[int, RobotTrainer]:
        return {i: r.trainer for i, r in self.robots.items()}

    def run_round(self) -> dict[int, RoundRecord]:
        """One round of every robot -> each robot's record (``round`` = rounds completed)."""
        k = self.round
        stats = {}
        for i, robot in self.robots.items():
            anchor_own = None if self.anchor_on_exact else self.public.get(i)
            robot.trainer.begin_round(k, {j: self.thetas[j] for j in self._heard(i, k)}, own=anchor_own)
            stats[i] = robot.trainer.train(self.cfg.steps_per_round)
        own = new = {i: r.trainer.theta() for i, r in self.robots.items()}
        if self.wire is not None:
            new = {i: self.wire(i, k + 1, theta) for i, theta in own.items()}
            if self.on_public:
                self.public = new
        if self.forge is not None:
            new = {i: self.forge(i, k + 1, theta) or theta for i, theta in new.items()}
        for i, robot in self.robots.items():
            robot.trainer.end_round({j: new[j] for j in self._heard(i, k + 1)}, own=self.public.get(i))
        self.thetas = new
        self.round += 1
        ids = list(self.robots)
        dis = dict(zip(ids, disagreement([list(own[i].values()) for i in ids])))
        return {i: self._record(i, stats[i], dis[i]) for i in ids}

    def _heard(self, i: int, round_index: int) -> list[int]:
        """Robot i's neighbours whose snapshot of ``round_index`` reaches it."""
        return [j for j in self.neighbours[i] if round_index < self.silent_from.get(j, round_index + 1)]

    def _record(self, i: int, stats: StepStats, disagreement_i: float) -> RoundRecord:
        T = self.robots[i].trainer.pose.matrix().detach().double().cpu()
        pose = pose_summary(T)
        return RoundRecord(
            robot=i, round=self.round, time=time.time(), monotonic=time.monotonic(), loss=stats.loss,
            rgb_loss=stats.rgb_loss, depth_loss=stats.depth_loss, batch_psnr=stats.batch_psnr,
            samples_per_ray=stats.samples_per_ray, pose=T.tolist(), pose_rotation_deg=pose["rotation_deg"],
            pose_translation=pose["translation"], pose_scale=pose["scale"], reference=self.reference_id,
            elected=i == self.reference_id, live_neighbours=self.neighbours[i], reachable=self.neighbours[i],
            heard=self._heard(i, self.round), seconds_compute=stats.seconds, steps=stats.steps,
            seconds_per_step=stats.seconds / max(stats.steps, 1), disagreement=disagreement_i)

    def run(self, on_round: Callable[[dict[int, RoundRecord]], None] | None = None) -> list[dict[int, RoundRecord]]:
        history = []
        while self.round < self.cfg.rounds:
            rec = self.run_round()
            history.append(rec)
            if on_round is not None:
                on_round(rec)
        return history
