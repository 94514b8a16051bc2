"""The radiance field: hash grid -> density MLP -> view-dependent colour head.

The field lives in grid coordinates ``[-1, 1]^3``: the scene's box itself for a bounded scene,
or all of space contracted into it (``unbounded``, :mod:`agent.nerf.contraction`) for captures
that show what lies around the object. :meth:`NGPField.to_grid` maps box coordinates there;
the renderer maps rays into the box. All of its parameters are the ``theta`` that consensus
drives to agreement.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor, nn

from agent.config_io import check
from agent.nerf.contraction import contract
from agent.nerf.encoding import HashGrid, HashGridConfig


@dataclass
class FieldConfig:
    grid: HashGridConfig = field(default_factory=HashGridConfig)
    density_hidden: int = 64
    geo_features: int = 15
    color_hidden: int = 64
    color_layers: int = 2
    sh_degree: int = 4  # spherical harmonics of the view direction: degree**2 coefficients
    density_bias: float = -1.0  # start nearly empty so the occupancy grid prunes early
    # Model all of space, contracted into the cube, not only the box: for images without alpha
    # or masks, which show the surroundings too. None: decided from the images (no alpha: True).
    unbounded: bool | None = None

    def __post_init__(self) -> None:
        check(self, density_hidden=">= 1", geo_features=">= 0", color_hidden=">= 1", color_layers=">= 0",
              sh_degree="in [1, 4]")


class _TruncExp(torch.autograd.Function):
    """exp with a clamped backward: keeps large densities from producing exploding gradients."""

    @staticmethod
    def forward(ctx, x: Tensor) -> Tensor:
        ctx.save_for_backward(x)
        return torch.exp(x)

    @staticmethod
    def backward(ctx, g: Tensor) -> Tensor:
        (x,) = ctx.saved_tensors
        return g * torch.exp(x.clamp(max=15))


def trunc_exp(x: Tensor) -> Tensor:
    return _TruncExp.apply(x)


def spherical_harmonics(dirs: Tensor, degree: int) -> Tensor:
    """Real SH basis of unit directions.  dirs: [N, 3] -> [N, degree**2]."""
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, 0.28209479177387814)]
    if degree > 1:
        out += [-0.4886025119029199 * y, 0.4886025119029199 * z, -0.4886025119029199 * x]
    if degree > 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [
            1.0925484305920792 * xy,
            -1.0925484305920792 * yz,
            0.31539156525252005 * (2 * zz - xx - yy),
            -1.0925484305920792 * xz,
            0.5462742152960396 * (xx - yy),
        ]
        if degree > 3:
            out += [
                -0.5900435899266435 * y * (3 * xx - yy),
                2.890611442640554 * xy * z,
                -0.4570457994644658 * y * (4 * zz - xx - yy),
                0.3731763325901154 * z * (2 * zz - 3 * xx - 3 * yy),
                -0.4570457994644658 * x * (4 * zz - xx - yy),
                1.445305721320277 * z * (xx - yy),
                -0.5900435899266435 * x * (xx - 3 * yy),
            ]
    return torch.stack(out, -1)


class NGPField(nn.Module):
    def __init__(self, cfg: FieldConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.encoding = HashGrid(cfg.grid)
        self.density_mlp = nn.Sequential(
            nn.Linear(self.encoding.output_dim, cfg.density_hidden),
            nn.ReLU(inplace=True),
            nn.Linear(cfg.density_hidden, 1 + cfg.geo_features),
        )
        layers: list[nn.Module] = []
        width_in = cfg.geo_features + cfg.sh_degree**2
        for _ in range(cfg.color_layers):
            layers += [nn.Linear(width_in, cfg.color_hidden), nn.ReLU(inplace=True)]
            width_in = cfg.color_hidden
        layers.append(nn.Linear(width_in, 3))
        self.color_mlp = nn.Sequential(*layers)

    @property
    def unbounded(self) -> bool:
        return bool(self.cfg.unbounded)

    def to_grid(self, x: Tensor) -> Tensor:
        """Box coordinates [N, 3] -> the field's grid coordinates [N, 3] (the same when bounded)."""
        return contract(x) if self.cfg.unbounded else x

    def density(self, x: Tensor, level_weights: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """x: [N, 3] grid coordinates in [-1, 1] -> (sigma [N], geo [N, G]). Outside: zero density."""
        unit = (x + 1) * 0.5
        inside = ((unit >= 0) & (unit <= 1)).all(-1)
        h = self.density_mlp(self.encoding(unit.clamp(0, 1), level_weights))
        sigma = trunc_exp(h[:, 0] + self.cfg.density_bias) * inside
        return sigma, h[:, 1:]

    def color(self, geo: Tensor, dirs: Tensor) -> Tensor:
        """geo: [N, G], dirs: [N, 3] unit -> rgb [N, 3] in (0, 1)."""
        sh = spherical_harmonics(dirs, self.cfg.sh_degree)
        return torch.sigmoid(self.color_mlp(torch.cat([geo, sh], -1)))

    def forward(self, x: Tensor, dirs: Tensor, level_weights: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """x: [N, 3] grid coordinates, dirs: [N, 3] unit -> (sigma [N], rgb [N, 3])."""
        sigma, geo = self.density(x, level_weights)
        return sigma, self.color(geo, dirs)
