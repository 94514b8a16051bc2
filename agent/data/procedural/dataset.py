"""The procedural dataset: the views of a :class:`ProceduralConfig`, rendered, with their metadata."""

from __future__ import annotations

from agent.data.procedural.config import ProceduralConfig, procedural_cameras
from agent.data.procedural.render import render_procedural
from agent.data.procedural.scene import SCENE_BOX_WORLD
from agent.data.views import Views

__all__ = ["procedural_views"]


def procedural_views(cfg: ProceduralConfig | None = None) -> Views:
    """The procedural dataset: ``cfg.num_views`` RGBA views with exact depth, deterministic in ``seed``."""
    cfg = cfg or ProceduralConfig()
    c2w, intr = procedural_cameras(cfg)
    rgba, depth = render_procedural(c2w, intr, cfg.width, cfg.height, cfg.supersample)
    return Views(
        images=rgba,
        c2w=c2w,
        intrinsics=intr,
        names=[f"view_{i:03d}" for i in range(cfg.num_views)],
        depth=depth,
        meta={
            "source": "procedural",
            "format": "procedural",
            "config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(cfg).items()},
            "scene_box_world": dict(SCENE_BOX_WORLD),
            "depth_sparse": False,
            "depth_kind": "exact z-depth",
            "notes": [],
        },
    )
