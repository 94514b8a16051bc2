"""Per-image appearance: an affine colour transform of each image, private to its robot.

Robots are not identical cameras: exposure and white balance differ between them, and between
the images of one robot (auto exposure). A shared field cannot match all of them; without a
place to put the difference, consensus averages it into the field (washed-out colour). Here each
image ``m`` gets ``rgb' = A_m rgb + b_m`` on the field's radiance, before the background
(a synthetic background is no part of the camera's response). Like the depth scale/shift it
stays on the robot: it is never in theta and never averaged. A small penalty keeps it near the
identity, since a common colour shift of all images and the field's colour are otherwise one.

Held-out views have no transform of their own. :meth:`ColourAffine.nearest` gives the one of
the training view nearest in pose (the NeRF-W / nerfacto practice for test views from the same
cameras); ``agent.evaluation`` can also fit one per view, or use none (test views from the
reference camera of a synthetic split).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from agent.config_io import check

__all__ = ["AppearanceConfig", "ColourAffine"]


@dataclass
class AppearanceConfig:
    enabled: bool = False
    lr: float = 2e-3  # Adam on the 12 numbers of each image
    start_step: int = 0
    weight: float = 1e-2  # L2 penalty towards the identity, against the field's own colour

    def __post_init__(self) -> None:
        check(self, lr=">= 0", start_step=">= 0", weight=">= 0")


class ColourAffine(nn.Module):
    """``params: [M, 12]``: per image a 3x3 matrix offset from the identity and a 3-vector offset."""

    def __init__(self, num_images: int, cfg: AppearanceConfig, device: torch.device | str = "cpu") -> None:
        super().__init__()
        self.cfg = cfg
        self.params = nn.Parameter(torch.zeros(num_images, 12, device=device), requires_grad=cfg.enabled)

    @staticmethod
    def matrix(params: Tensor) -> Tensor:
        """One image's transform as a 4x4 affine matrix.  params: [12] -> [4, 4]."""
        m = torch.eye(4, dtype=params.dtype, device=params.device)
        m[:3, :3] += params[:9].reshape(3, 3)
        m[:3, 3] = params[9:]
        return m

    @staticmethod
    def apply(params: Tensor, rgb: Tensor, opacity: Tensor, background: Tensor) -> Tensor:
        """A render composited onto ``background`` -> the same with the field's radiance transformed:
        ``A fg + b alpha + (1 - alpha) bg``.  params: [N, 12]; rgb: [N, 3]; opacity: [N];
        background: [N, 3] or [3]."""
        alpha = opacity[:, None]
        fg = rgb - (1 - alpha) * background  # the field's own contribution
        a = params[:, :9].reshape(-1, 3, 3) + torch.eye(3, device=params.device, dtype=params.dtype)
        return (a @ fg[:, :, None]).squeeze(-1) + params[:, 9:] * alpha + (1 - alpha) * background

    def penalty(self) -> Tensor:
        return self.cfg.weight * (self.params ** 2).mean()

    @torch.no_grad()
    def nearest(self, train_c2w: Tensor, query_c2w: Tensor) -> Tensor:
        """The transform of the training view nearest each query camera (same frame).

        train_c2w: [M, 4, 4], query_c2w: [Q, 4, 4] -> [Q, 12]. Distance: camera centres, plus
        the angle of the viewing axes (in units of the cameras' spread), so a view from the
        other side of the object does not count as near."""
        ct, cq = train_c2w[:, :3, 3], query_c2w[:, :3, 3]
        spread = float((ct - ct.mean(0)).norm(dim=-1).mean()) or 1.0
        d = torch.cdist(cq.double(), ct.double()) / spread
        cos = (query_c2w[:, :3, 2].double() @ train_c2w[:, :3, 2].double().T).clamp(-1, 1)
        return self.params.detach()[(d + torch.arccos(cos)).argmin(-1)]
