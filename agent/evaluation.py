"""Evaluation against the truth of a split: image quality in the shared frame and pose error.

Only evaluation code reads the truth (``truth.json`` or a ``SplitResult``); the agents never do.
The shared frame g is the local frame of the split's reference robot, so the held-out views
(world frame) are mapped into g with ``inv(T_world_from_local[reference])`` and rendered by each
robot's field there: a robot whose field or pose is off in g scores badly, as it should.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from torch import Tensor

from agent.data.views import DataError, Views
from agent.geometry import pose_error, sim3_inverse, transform_c2w


@dataclass
class EvalSet:
    views: Views  # held-out views in the world frame
    seen_by: list[list[int]]  # per view: robots whose sector contains it
    reference_id: int
    T_world_from_local: dict[int, Tensor]  # truth, [4, 4] float64 per robot

    @property
    def T_shared_from_world(self) -> Tensor:
        return sim3_inverse(self.T_world_from_local[self.reference_id])

    def T_shared_from_local(self, robot_id: int) -> Tensor:
        """What robot i's relative pose should converge to.  -> [4, 4] float64."""
        return self.T_shared_from_world @ self.T_world_from_local[robot_id]

    def shared_cameras(self) -> Tensor:
        """The held-out cameras in the shared frame g.  -> [M, 4, 4]."""
        return transform_c2w(self.T_shared_from_world, self.views.c2w.double()).float()

    def others_only(self, robot_id: int) -> list[int]:
        """Indices of held-out views that only other robots saw (outside this robot's sector)."""
        return [i for i, s in enumerate(self.seen_by) if robot_id not in s]

    @classmethod
    def from_split(cls, result) -> "EvalSet":
        """From an in-memory ``agent.data.split.SplitResult``."""
        return cls(
            views=result.eval_views,
            seen_by=[list(s) for s in result.seen_by],
            reference_id=result.reference_id,
            T_world_from_local={i: r.T_world_from_local.double() for i, r in result.robots.items()},
        )

    @classmethod
    def from_dir(cls, split_dir: str | Path, width: int | None = None) -> "EvalSet":
        """From a split folder written by ``dinerf-agent split`` (eval/ and truth.json)."""
        from agent.data.folder import read_truth
        from agent.data.loaders import load_views

        split_dir = Path(split_dir)
        eval_dir = split_dir / "eval"
        views = load_views(eval_dir, width=width)
        try:
            frames = json.loads((eval_dir / "transforms.json").read_text())["frames"]
            seen_by = [list(map(int, f.get("seen_by", []))) for f in frames]
        except (OSError, KeyError, ValueError, TypeError) as e:
            raise DataError(f"{eval_dir}: cannot read 'seen_by' of the held-out views: {e}") from None
        truth = read_truth(split_dir)
        try:
            poses = {int(i): r["T_world_from_local"] for i, r in truth["robots"].items()}
            ref = int(truth["reference_id"])
        except (KeyError, TypeError, ValueError) as e:
            raise DataError(f"{split_dir}/truth.json: expected robots.*.T_world_from_local and reference_id: {e}") from None
        return cls(views=views, seen_by=seen_by, reference_id=ref, T_world_from_local=poses)


@dataclass
class RobotEval:
    robot_id: int
    psnr: list[float]  # per held-out view
    ssim: list[float]
    others_only: list[int]  # indices of views only other robots saw
    pose: dict[str, float] = field(default_factory=dict)  # rotation_deg, translation, scale_rel

    @staticmethod
    def _mean(values: list[float]) -> float:
        return sum(values) / len(values) if values else float("nan")

    @property
    def psnr_all(self) -> float:
        return self._mean(self.psnr)

    @property
    def ssim_all(self) -> float:
        return self._mean(self.ssim)

    @property
    def psnr_others(self) -> float:
        return self._mean([self.psnr[i] for i in self.others_only])

    @property
    def ssim_others(self) -> float:
        return self._mean([self.ssim[i] for i in self.others_only])

    def summary(self) -> dict[str, float]:
        return {
            "psnr": self.psnr_all,
            "ssim": self.ssim_all,
            "psnr_others_only": self.psnr_others,
            "ssim_others_only": self.ssim_others,
            **{f"pose_{k}": v for k, v in self.pose.items()},
        }


def evaluate_robot(trainer, evalset: EvalSet, robot_id: int, with_ssim: bool = True) -> RobotEval:
    """Render every held-out view with this robot's field in the shared frame; compare to truth."""
    shared = Views(
        images=evalset.views.images,
        c2w=evalset.shared_cameras(),
        intrinsics=evalset.views.intrinsics,
        names=evalset.views.names,
    )
    scores = trainer.evaluate(shared, frame="shared", with_ssim=with_ssim)
    estimate = trainer.pose.matrix().detach().double().cpu()
    return RobotEval(
        robot_id=robot_id,
        psnr=scores["psnr"],
        ssim=scores["ssim"],
        others_only=evalset.others_only(robot_id),
        pose=pose_error(estimate, evalset.T_shared_from_local(robot_id)),
    )
