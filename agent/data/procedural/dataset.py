"""The procedural dataset: the views of a :class:`ProceduralConfig`, rendered, with their metadata."""

from __future__ import annotations

from agent.camera import DISTORTION_KEYS
from agent.data.procedural.config import ProceduralConfig, procedural_cameras
from agent.data.procedural.render import render_procedural
from agent.data.procedural.scene import SCENE_BOX_WORLD
from agent.data.views import Views

__all__ = ["procedural_views"]


def procedural_views(cfg: ProceduralConfig | None = None) -> Views:
    """The procedural dataset: ``cfg.num_views`` views with exact depth, deterministic in ``seed``.

    RGBA on an empty background, or RGB inside the room (``cfg.room``: no pixel is empty, as in a
    real capture). With a distorting lens the images are as that lens records them and
    ``meta["distortion"]`` says how (:mod:`agent.data.views`); depth is the z-depth along each
    pixel's true ray.
    """
    cfg = cfg or ProceduralConfig()
    c2w, intr = procedural_cameras(cfg)
    rgba, depth = render_procedural(c2w, intr, cfg.width, cfg.height, cfg.supersample, room=cfg.room,
                                    distortion=cfg.distortion)
    meta = {
        "source": "procedural",
        "format": "procedural",
        "config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(cfg).items()},
        "scene_box_world": dict(SCENE_BOX_WORLD),
        "depth_sparse": False,
        "depth_kind": "exact z-depth",
        "notes": [],
    }
    if cfg.distortion is not None:
        meta["distortion"] = dict(zip(DISTORTION_KEYS, cfg.distortion))
    return Views(
        images=rgba[..., :3].contiguous() if cfg.room else rgba,
        c2w=c2w,
        intrinsics=intr,
        names=[f"view_{i:03d}" for i in range(cfg.num_views)],
        depth=depth,
        meta=meta,
    )
