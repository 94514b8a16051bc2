"""Before round 0: agree on the field box, then find where this robot's frame lies (coarse alignment).

The box maps the shared frame onto the field's [-1, 1]^3. A split that knows the scene gives it
to every robot; robots with images only cannot be told (it lives in the reference's SfM frame),
so the reference derives it from its own views and it travels outward with the keyframe
summaries. Until then the robot's model is provisional and it takes no snapshots.

The coarse alignment propagates outward from the reference: a robot whose pose is known (the
reference; others once aligned) says so in its status (:class:`protocol.messages.Alignment`),
with its pose. Robot i matches its keyframe summary with such a neighbour j's (``T_j_from_i`` by
RANSAC Sim(3), :mod:`agent.align`) and starts from ``T_g_from_j T_j_from_i``. No overlap
anywhere: an identity start, reported as ``unaligned``.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
from torch import Tensor

from agent.align import AlignConfig, Summary, estimate_relative, summarise
from agent.data.stream import ViewStream
from agent.data.views import Views
from agent.geometry import pose_summary, sim3_from_params
from agent.telemetry import Reporter, StatusBoard
from agent.trainer import RobotTrainer
from protocol import codec
from protocol.keys import Keys
from protocol.membership import Membership
from protocol.messages import KEYFRAME_CAMERA_DIM, Alignment, KeyframeSummary, Rejected, Status
from protocol.network import Network

__all__ = ["Bootstrap", "BootstrapTiming"]


def _keyframe_cap(align: AlignConfig) -> int:
    """Decompressed bytes a neighbour's summary may declare: the codec's cap, or our own budget if larger.

    Every robot summarises under the same AlignConfig; its cameras (4 bytes x KEYFRAME_CAMERA_DIM
    per keyframe) can come on top of ``max_bytes`` when the budget is smaller than they are.
    """
    budget = align.max_bytes + align.num_keyframes * KEYFRAME_CAMERA_DIM * 4
    return max(codec.Expectation.max_keyframe_bytes, budget)


@dataclass(frozen=True)
class BootstrapTiming:
    align_timeout_s: float  # give up on the coarse step after this long (identity start)
    query_timeout_s: float  # one query for a neighbour's keyframe summary


class Bootstrap:
    """The field box (known, or pending until a neighbour sends it) and the coarse initial pose."""

    def __init__(self, trainer: RobotTrainer, summary_views: Views, net: Network, keys: Keys,
                 membership: Membership, board: StatusBoard, report: Reporter, stop: threading.Event,
                 align: AlignConfig, timing: BootstrapTiming, box_known: bool,
                 on_box: Callable[[], None]) -> None:
        self.trainer, self.summary_views = trainer, summary_views
        self.net, self.keys, self.membership = net, keys, membership
        self.board, self.report, self.stop = board, report, stop
        self.align, self.timing = align, timing
        self.box_pending = not box_known
        self._on_box = on_box  # the daemon rebuilds its model spec from the new box
        self._peer_expect = codec.Expectation(swarm=keys.swarm, allowed_senders=frozenset(membership.topology.ids),
                                              max_keyframe_bytes=_keyframe_cap(align))
        self._summaries: dict[int, Summary] = {}  # neighbours' keyframe summaries, fetched again on a retry
        self._boxes: dict[int, np.ndarray | None] = {}  # the field box each neighbour sent
        self._own: Summary | None = None
        self._msg: KeyframeSummary | None = None  # what we serve (set by the coarse step)
        self._summary_width = summary_views.width  # the width our summary's images had

    # ------------------------------------------------------------------ the field box
    def adopt_box(self, box_from_shared: np.ndarray | Tensor, source: str) -> None:
        """Take the swarm's field box (images-only robots learn it at start) and the model spec it implies."""
        box = torch.as_tensor(np.asarray(box_from_shared, dtype=np.float64))
        self.trainer.set_box_from_shared(box)
        self.box_pending = False
        self._on_box()
        self.report.event("field_box", source=source, box_from_shared=[float(x) for x in box.flatten()])
        self.report.say(f"field box from {source}")

    def _box_to_share(self) -> np.ndarray:
        """Our box as it goes on the wire (float64 of our float32 box: every robot ends bit-identical)."""
        return self.trainer.box_from_shared.detach().cpu().double().numpy()

    def _settle_box_without_pose(self, boxes: dict[int, np.ndarray | None], serve: Callable[[], int]) -> None:
        """No pose found: still take the swarm's box if a neighbour sent one, so our model agrees."""
        sent = [j for j, b in sorted(boxes.items()) if b is not None]
        if sent:
            self.adopt_box(boxes[sent[0]], f"robot {sent[0]} (without a pose)")
            serve()
            return
        self.box_pending = False
        self._on_box()
        self.report.event("field_box", source="own estimate (no neighbour sent one)")
        self.report.warn("no neighbour sent the field box: keeping our own estimate; "
                        "neighbours with another box will refuse our snapshots (bad_signature)")

    # ------------------------------------------------------------------ coarse alignment
    def coarse_alignment(self) -> None:
        """Initial T_i from keyframe summaries, propagated outward from the reference (module docstring)."""
        t0 = time.monotonic()
        views, self.summary_views = self.summary_views, self.trainer.views  # the sharper copy is needed once
        own, msg = self._summarise(views)
        is_reference = self.membership.is_reference
        if is_reference and self.box_pending:  # our own frame is the shared frame: our box is the box
            self.adopt_box(self._box_to_share(), "our own views (we are the reference)")

        self._own, self._msg = own, msg
        serve = self._serve_summary
        size = serve()
        self.report.event("keyframes", bytes=size, image_bytes=msg.image_bytes, points=len(own),
                          image_width=views.width, views=len(views), seconds=time.monotonic() - t0)
        self.report.say(f"keyframe summary: {len(own)} points, {size / 1e3:.0f} kB "
                        f"(its images: {msg.image_bytes / 1e6:.1f} MB)")
        if is_reference:
            self.board.set(alignment=Alignment.REFERENCE, alignment_detail="")
            return
        self._align_with_neighbours(own, serve, t0)

    def _summarise(self, views: Views) -> tuple[Summary, KeyframeSummary]:
        own = summarise(views, cfg=self.align)
        return own, KeyframeSummary(swarm=self.keys.swarm, sender=self.membership.self_id, round=0,
                                    epoch=self.membership.epoch, descriptors=own.descriptors, points=own.points,
                                    keyframe_index=own.keyframe_index, image_bytes=int(views.images.numel()),
                                    keypoints=own.keypoints, keyframe_cameras=own.keyframe_cameras)

    def _serve_summary(self) -> int:
        """(Re)serve our summary, with the box once known; -> bytes."""
        self._msg.box_from_shared = None if self.box_pending else self._box_to_share()
        data = codec.encode(self._msg)
        self.net.set_keyframes(data)
        return len(data)

    def refresh_summary(self, stream: ViewStream) -> int:
        """Serve a summary of all the stream's training keyframes so far (its neighbours place
        themselves against the places it has seen since, on their next query); at most
        ``summary_pool`` of them, spread over all, are read. -> points."""
        if self._msg is None:
            return 0  # the coarse step has not run yet: it summarises what there is then
        views = stream.spread_views(self.align.summary_pool, self._summary_width)
        self._own, self._msg = self._summarise(views)
        size = self._serve_summary()
        self.report.event("keyframes", bytes=size, image_bytes=self._msg.image_bytes, points=len(self._own),
                          image_width=views.width, views=len(views), refreshed=True)
        return len(self._own)

    def retry(self, from_field: bool) -> bool:
        """One more attempt of an unaligned robot: with every neighbour (some may have aligned
        since), from our summary or, ``from_field``, from one of renders of our own trained field
        (its depth places every feature, where our images alone could triangulate too few)."""
        if self._own is None or self._msg is None or self.box_pending:
            return False
        own = self._field_summary() if from_field else self._own
        self._summaries.clear()  # a neighbour whose keyframes grow serves more of them now
        tried: dict[int, str] = {}
        best = self._best_match(own, self.board.peers(), self._summaries, self._boxes, tried)
        if best is None:
            self.board.set(alignment_detail=f"retrying ({'own field' if from_field else 'summaries'}): "
                                            + "; ".join(f"{j}: {r}" for j, r in sorted(tried.items()))[:200])
            return False
        self._start_from(best, self._boxes, self._serve_summary, time.monotonic(),
                         how=" from renders of its own field" if from_field else " on a retry")
        return True

    @torch.no_grad()
    def _field_summary(self) -> Summary:
        """A keyframe summary of renders of our field through our own cameras, with their depth."""
        tr = self.trainer
        scale = self._summary_width / tr.views.width
        k = tr.camera_intrinsics().cpu() * scale
        w, h = self._summary_width, round(tr.views.height * scale)
        cams = tr.cameras_shared().cpu()  # = local while unaligned (the identity pose)
        renders = [tr.render(cams[i], k[i], w, h) for i in range(len(cams))]
        views = Views(torch.stack([r["rgb"].cpu() for r in renders]), cams, k, list(tr.views.names),
                      torch.stack([r["depth"].cpu() * (r["opacity"].cpu() > 0.5) for r in renders]), {})
        return summarise(views, points_source="depth", cfg=self.align)

    def _align_with_neighbours(self, own: Summary, serve: Callable[[], int], t0: float) -> None:
        summaries, boxes = self._summaries, self._boxes
        tried: dict[int, str] = {}
        deadline = time.monotonic() + self.timing.align_timeout_s
        while time.monotonic() < deadline and not self.stop.is_set():
            statuses: dict[int, Status] = self.board.peers()
            best = self._best_match(own, statuses, summaries, boxes, tried)
            if best is not None:
                self._start_from(best, boxes, serve, t0)
                return
            live = self.membership.live_neighbours
            if tried and len(tried) == len(live) and all(
                    statuses.get(j) is not None and statuses[j].alignment.settled for j in live):
                break  # every neighbour has settled and none matched: no overlap
            self.stop.wait(0.5)
        reason = "; ".join(f"{j}: {r}" for j, r in sorted(tried.items())) or "no aligned neighbour answered"
        if self.box_pending:
            self._settle_box_without_pose(boxes, serve)
        self.board.set(alignment=Alignment.UNALIGNED, alignment_detail="coarse step found nothing")
        self.report.event("alignment_failed", reason=reason)
        self.report.warn(f"coarse alignment found nothing ({reason}): unaligned, training alone and out of consensus "
                        "until a retry places our frame")

    def _best_match(self, own: Summary, statuses: dict[int, Status], summaries: dict[int, Summary],
                    boxes: dict[int, np.ndarray | None], tried: dict[int, str]):
        """The aligned neighbour whose summary matches ours with most inliers: (j, inliers, T, sigma) or None."""
        best = None
        for j in sorted(self.membership.live_neighbours):
            st = statuses.get(j)
            if st is None or not st.alignment.settled:
                continue  # j does not know where it is yet
            knows_pose = st.alignment.knows_pose
            if not knows_pose and not self.box_pending:
                tried[j] = "it found no pose either"
                continue
            if j not in summaries and not self._fetch_summary(j, summaries, boxes):
                continue
            if not knows_pose:  # but its box (from someone who had one) still makes our model agree
                tried[j] = "it found no pose either"
                continue
            if self.box_pending and boxes.get(j) is None:
                tried[j] = "it sent no field box"
                continue
            res = estimate_relative(summaries[j], own, self.align)
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
        return best

    def _fetch_summary(self, j: int, summaries: dict[int, Summary], boxes: dict[int, np.ndarray | None]) -> bool:
        raw = self.net.query(self.keys.keyframes(j), timeout=self.timing.query_timeout_s)
        if raw is None:
            return False
        try:
            km = codec.decode(raw, self._peer_expect, kind="keyframes", key=self.keys.parse(self.keys.keyframes(j)))
            summaries[j] = Summary(km.descriptors, km.points, km.keyframe_index, self.align.descriptor_scale,
                                   keypoints=km.keypoints, keyframe_cameras=km.keyframe_cameras)
            boxes[j] = km.box_from_shared
        except (Rejected, ValueError) as e:
            self.report.reject(getattr(e, "reason", "bad_field"), f"keyframes of robot {j}: {e}")
            return False
        return True

    def _start_from(self, best, boxes: dict[int, np.ndarray | None], serve: Callable[[], int], t0: float,
                    how: str = "") -> None:
        # sigma is that of the last hop only: j's own uncertainty is not in its status.
        j, inliers, T, sigma = best
        if self.box_pending:
            self.adopt_box(boxes[j], f"robot {j}")
            serve()  # with the box: robots aligning through us need it too
        self.trainer.pose.set_initial(T.float(), sigma_deg=sigma, step=self.trainer.step)
        with torch.no_grad():
            self.board.set(alignment=Alignment.COARSE, alignment_detail=f"via {j}{how}: {inliers} inliers",
                           pose7=pose_summary(self.trainer.pose.matrix())["params7"])
        lr_scale = self.trainer.pose_lr_scale()
        self.report.event("aligned", via=j, inliers=inliers, seconds=time.monotonic() - t0, pose_lr_scale=lr_scale,
                          rotation_sigma_deg=sigma if math.isfinite(sigma) else None, how=how.strip() or "start")
        self.report.say(f"coarse alignment via robot {j}{how}: {inliers} inliers, rotation "
                        f"sigma {sigma:.3f} deg (pose learns at {lr_scale:.3g}x)")
