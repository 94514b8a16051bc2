"""What a robot says about each round it completes: the record (one line of ``telemetry.jsonl``),
what its next heartbeat carries, its log line, and the warnings a run of rounds calls for (a
flat loss, a robot that hears nobody).

The daemon hands over what only the round knows (its training stats, the neighbours heard, its
times); the figures that accumulate between records (traffic, CPU) are kept here, so that a
record's window starts where the last one ended.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from agent.data.stream import StreamRound
from agent.geometry import pose_summary
from agent.swarm import RobotSetup
from agent.telemetry import JsonLines, PlateauRule, Reporter, RoundRecord, StatusBoard
from agent.trainer import StepStats
from protocol.exchange import SnapshotExchange
from protocol.membership import Membership
from protocol.messages import Alignment
from protocol.network import Network

__all__ = ["RoundTimes", "RoundReport"]


def _record_views(s: StreamRound | None) -> dict:
    """The stream's figures for the round's record (none when the views were all given at start)."""
    if s is None:
        return {}
    return {"keyframes": s.keyframes, "keyframes_admitted": s.admitted, "keyframes_held_out": s.held_out,
            "keyframes_dropped": s.dropped, "keyframe_age_s": s.newest_age_s, "coverage": s.coverage}


def _status_views(s: StreamRound | None) -> dict | None:
    """What a heartbeat says of the robot's views so far (``protocol.messages.Status.views``)."""
    if s is None:
        return None
    return {"keyframes": s.keyframes, "held_out": s.held_out_total, "dropped": s.dropped_total,
            "newest_age_s": s.newest_age_s, "coverage": s.coverage}


@dataclass(frozen=True)
class RoundTimes:
    compute_s: float  # wall time of the round's training steps
    cpu_compute_s: float  # CPU time (all threads) of those steps
    wait_s: float  # at the barrier


class RoundReport:
    """Records, logs and warns, round after round, for one robot."""

    def __init__(self, robot_id: int, rounds: int, setup: RobotSetup, net: Network, exchange: SnapshotExchange,
                 membership: Membership, reachable: Callable[[], set[int]], board: StatusBoard, report: Reporter,
                 telemetry: JsonLines, *, eval_every: int, plateau: PlateauRule, isolated_after: int,
                 compression: str) -> None:
        self.robot_id, self.rounds, self.setup, self.net, self.exchange = robot_id, rounds, setup, net, exchange
        self.membership, self.reachable, self.board, self.report, self.telemetry = (membership, reachable, board,
                                                                                    report, telemetry)
        self.eval_every, self.plateau, self.isolated_after, self.compression = (eval_every, plateau, isolated_after,
                                                                                compression)
        self._traffic_at_record: dict = {}  # the counters at the last record: the next window starts there
        self._cpu_at_record = 0.0  # the process's CPU time at the last record
        self._rgb_losses: list[float] = []
        self._warned_flat = False
        self._isolated_rounds = 0  # consecutive rounds in consensus without hearing any neighbour

    def start(self) -> None:
        """The first record's window starts now."""
        self._traffic_at_record = self._traffic()
        self._cpu_at_record = time.process_time()

    def round_done(self, round_index: int, stats: StepStats, heard: list[int] | None, elected: bool,
                   times: RoundTimes, float32_bytes: int, **extra) -> RoundRecord:
        """Write the record of ``round_index`` (completed), set the heartbeat's fields, log the
        round's line and any warning. ``heard`` None: out of consensus (unaligned).
        ``extra``: further RoundRecord fields (the robust consensus' figures)."""
        matrix, summary = self._pose()
        views = self.setup.stream.round_stats() if self.setup.stream is not None else None
        extra = {**extra, **_record_views(views)}
        record = self._record(round_index, stats, heard or [], elected, matrix, summary, times, float32_bytes, extra)
        self.telemetry.write_line(record.to_json())
        net = self.net.stats()
        self.board.set(phase="round_done", loss=stats.loss, psnr=record.psnr, heard=record.heard,
                       bytes_in_total=net["bytes_in_total"], bytes_out_total=net["bytes_out_total"],
                       seconds_compute=times.compute_s, seconds_wait=times.wait_s, pose7=summary["params7"],
                       views=_status_views(views))
        (self.report.warn if record.alignment == "unaligned" else self.report.say)(record.log_line(self.rounds))
        self._warn_if_flat(stats.rgb_loss)
        self._warn_if_isolated(heard, float32_bytes)
        return record

    # ------------------------------------------------------------------ the record
    def _traffic(self) -> dict:
        """The network's counters and, per neighbour, the snapshot bytes pushed so far."""
        return {**self.net.stats(), "links": self.exchange.bytes_sent()}

    @staticmethod
    def _link_bytes(now: dict, before: dict, raw: int) -> tuple[dict[int, int], float | None]:
        """Per neighbour the snapshot bytes pushed this round, and their mean over the raw float32 size."""
        was = before.get("links", {})
        links = {j: b - was.get(j, 0) for j, b in now["links"].items()}
        links = {j: b for j, b in links.items() if b}
        return links, (sum(links.values()) / len(links) / raw if links and raw else None)

    def _cpu_since_record(self) -> float:
        """What the round cost this robot in CPU (all threads), whatever else the machine ran."""
        now, before = time.process_time(), self._cpu_at_record
        self._cpu_at_record = now
        return now - before

    def _pose(self) -> tuple[Tensor, dict]:
        """The pose estimate ``[4, 4]`` and its summary, computed once for the record and the status."""
        with torch.no_grad():
            matrix = self.setup.trainer.pose.matrix().detach()
            return matrix, pose_summary(matrix)

    def _own_psnr(self, round_index: int) -> float | None:
        """PSNR on the robot's own held-out views, when this round is one to evaluate."""
        every = self.eval_every
        if every <= 0 or self.setup.holdout is None or (round_index % every and round_index != self.rounds):
            return None
        scores = self.setup.trainer.evaluate(self.setup.holdout, frame="local", with_ssim=False)["psnr"]
        return sum(scores) / len(scores)

    def _record(self, round_index: int, stats: StepStats, heard: list[int], elected: bool, matrix: Tensor,
                summary: dict, times: RoundTimes, float32_bytes: int, extra: dict) -> RoundRecord:
        psnr = self._own_psnr(round_index)
        # Counted from the end of the last round's window: a neighbour already a round ahead may
        # be counted in the round before the one its snapshot is for, but no byte goes uncounted.
        before, net = self._traffic_at_record, self._traffic()
        self._traffic_at_record = net
        bytes_in = {int(j): net["bytes_in"].get(j, 0) - before["bytes_in"].get(j, 0) for j in net["bytes_in"]}
        links, ratio = self._link_bytes(net, before, float32_bytes)
        s = self.board.own()
        return RoundRecord(
            robot=self.robot_id, round=round_index, time=time.time(), monotonic=time.monotonic(), loss=stats.loss,
            rgb_loss=stats.rgb_loss, depth_loss=stats.depth_loss, batch_psnr=stats.batch_psnr, psnr=psnr,
            samples_per_ray=stats.samples_per_ray, pose=matrix.double().cpu().tolist(),
            pose_rotation_deg=summary["rotation_deg"], pose_translation=summary["translation"], pose_scale=summary["scale"],
            reference=self.membership.reference, elected=elected, epoch=self.membership.epoch,
            live_neighbours=sorted(self.membership.live_neighbours), reachable=sorted(self.reachable()),
            heard=heard, bytes_in={j: b for j, b in bytes_in.items() if b},
            bytes_out=net["bytes_out_total"] - before["bytes_out_total"], bytes_out_links=links,
            wire_ratio=ratio, seconds_compute=times.compute_s,
            seconds_wait=times.wait_s, cpu_seconds=self._cpu_since_record(), cpu_seconds_compute=times.cpu_compute_s,
            seconds_last_put=self.exchange.last_put_seconds(), steps=stats.steps,
            seconds_per_step=stats.seconds / max(stats.steps, 1), rejected=self.report.rejected_counts(),
            alignment=Alignment(s["alignment"]).value, alignment_detail=s["alignment_detail"], **extra)

    # ------------------------------------------------------------------ warnings
    def _warn_if_isolated(self, heard: list[int] | None, float32_bytes: int) -> None:
        """Say it when an aligned robot hears none of its neighbours for ``isolated_after`` rounds
        in a row (it trains alone, and nothing else in its log line says why), and when it hears
        them again. ``heard`` None: not in consensus (unaligned), which has warnings of its own."""
        neighbours = sorted(self.exchange.neighbours)
        if heard is None or heard or not neighbours:
            if heard and self._isolated_rounds >= self.isolated_after > 0:
                self.report.say(f"hears its neighbours again ({heard}) after {self._isolated_rounds} rounds alone")
            self._isolated_rounds = 0
            return
        self._isolated_rounds += 1
        if self._isolated_rounds != self.isolated_after:
            return
        self.report.event("isolated", rounds=self._isolated_rounds, neighbours=neighbours)
        self.report.warn(f"heard none of its neighbours {neighbours} for {self._isolated_rounds} "
                         f"rounds: it trains alone. Are they up and reachable? On a slow link a snapshot may never get "
                         f"through: this field is {float32_bytes / 1e6:.1f} MB at float32, sent as "
                         f"{self.compression!r} (daemon.exchange.compression)")

    def _warn_if_flat(self, rgb_loss: float) -> None:
        """Say it once when the photometric loss stops moving while still high (agent.telemetry.PlateauRule)."""
        self._rgb_losses.append(rgb_loss)
        if self._warned_flat or not self.plateau.is_flat(self._rgb_losses):
            return
        self._warned_flat = True
        last = self._rgb_losses[-self.plateau.window:]
        mean = sum(last) / len(last)
        self.report.event("loss_flat", rgb_loss=mean, rounds=len(last))
        self.report.warn(f"the training loss has been flat at {mean:.4f} ({-10 * math.log10(mean):.1f} dB) for "
                         f"{len(last)} rounds: the field may not model what the cameras see (an RGB capture needs "
                         "an unbounded field: training.train.field.unbounded; see `dinerf-agent inspect` warnings)")
