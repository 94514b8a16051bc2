"""A robot's field rendered along cameras of the shared frame: colour and depth, as PNGs and a video.

Depth is z-depth in shared-frame units (``agent.nerf.renderer``), written as a colour map whose
range is fixed over the whole sequence (2nd-98th percentile of the depth where the field is
opaque), so that a video does not flicker; the raw depths go to ``depth.npy``. The video shows
colour and depth side by side: a GIF through Pillow or an MP4 through imageio-ffmpeg's ffmpeg.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
from torch import Tensor

from agent.data.folder import write_png
from agent.trainer import RobotTrainer

__all__ = ["RenderedViews", "render_views", "depth_colours", "video_frames", "write_video", "write_frames", "write_renders",
           "VIDEO_FORMATS"]

VIDEO_FORMATS = ("gif", "mp4", "none")


@dataclass
class RenderedViews:
    rgb: np.ndarray  # [N, H, W, 3] float32 in [0, 1], on a white background
    depth: np.ndarray  # [N, H, W] float32 z-depth, shared-frame units (0 where empty)
    opacity: np.ndarray  # [N, H, W] float32 accumulated alpha

    def __len__(self) -> int:
        return len(self.rgb)


def render_views(trainer: RobotTrainer, c2w: Tensor, intrinsics: Tensor, width: int, height: int,
                 on_view: Callable[[int], None] | None = None) -> RenderedViews:
    """Render cameras of the shared frame.  c2w: [N, 4, 4], intrinsics: [N, 4] (at width x height)."""
    rgb, depth, opacity = [], [], []
    for i in range(len(c2w)):
        out = trainer.render(c2w[i], intrinsics[i], width, height)
        rgb.append(out["rgb"].cpu().numpy())
        depth.append(out["depth"].cpu().numpy())
        opacity.append(out["opacity"].cpu().numpy())
        if on_view is not None:
            on_view(i + 1)
    return RenderedViews(np.stack(rgb).astype(np.float32), np.stack(depth).astype(np.float32),
                         np.stack(opacity).astype(np.float32))


def depth_colours(depth: np.ndarray, opacity: np.ndarray) -> np.ndarray:
    """Depth [N, H, W] as a turbo colour map over one range for all views, faded to white where empty.  -> [N, H, W, 3]."""
    from matplotlib import colormaps

    solid = depth[opacity > 0.5]
    lo, hi = (np.percentile(solid, [2, 98]) if solid.size else (0.0, 1.0))
    scaled = np.clip((depth - lo) / max(hi - lo, 1e-9), 0, 1)
    colour = colormaps["turbo"](scaled)[..., :3].astype(np.float32)
    a = np.clip(opacity, 0, 1)[..., None]
    return colour * a + (1 - a)


def video_frames(views: RenderedViews) -> list[np.ndarray]:
    """Colour | depth side by side, 8-bit, padded to even sizes (H.264 needs them)."""
    side = np.concatenate([views.rgb, depth_colours(views.depth, views.opacity)], axis=2)  # [N, H, 2W, 3]
    q = np.round(np.clip(side, 0, 1) * 255).astype(np.uint8)
    n, h, w, _ = q.shape
    padded = np.full((n, h + h % 2, w + w % 2, 3), 255, np.uint8)
    padded[:, :h, :w] = q
    return list(padded)


def write_video(path: Path, views: RenderedViews, fps: float) -> None:
    """Colour | depth side by side, as a GIF or (any other suffix) an H.264 MP4."""
    write_frames(path, np.stack(video_frames(views)), fps)


def write_frames(path: Path, frames: np.ndarray, fps: float) -> None:
    """8-bit frames [N, H, W, 3] (even H and W for an MP4) as a looping GIF or an MP4, by ``path``'s suffix."""
    import imageio.v3 as iio

    if path.suffix == ".gif":
        iio.imwrite(path, frames, extension=".gif", duration=1000.0 / fps, loop=0)
    else:
        iio.imwrite(path, frames, plugin="FFMPEG", fps=fps, codec="libx264", macro_block_size=2,
                    ffmpeg_log_level="error")


def write_renders(out: Path, views: RenderedViews, video: str = "gif", fps: float = 15.0) -> dict[str, object]:
    """``rgb/NNNN.png``, ``depth/NNNN.png``, ``depth.npy`` and ``video.<gif|mp4>`` under ``out``; what was written."""
    if video not in VIDEO_FORMATS:
        raise ValueError(f"video must be one of {VIDEO_FORMATS}, got {video!r}")
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(exist_ok=True)
    depth_rgb = depth_colours(views.depth, views.opacity)
    for i in range(len(views)):
        write_png(out / "rgb" / f"{i:04d}.png", views.rgb[i])
        write_png(out / "depth" / f"{i:04d}.png", depth_rgb[i])
    np.save(out / "depth.npy", views.depth)
    written: dict[str, object] = {"frames": len(views), "rgb": str(out / "rgb"), "depth": str(out / "depth")}
    if video != "none":
        path = out / f"video.{video}"
        write_video(path, views, fps)
        written["video"] = str(path)
    return written
