"""The in-memory form of a set of posed images, shared by every loader and consumer.

Conventions (the same everywhere in the project, see ``agent.camera``):
- ``c2w`` are camera-to-world matrices in the OpenGL/Blender convention (camera looks down -Z,
  +Y up in the image, +X right).
- ``intrinsics`` are per view ``(fx, fy, cx, cy)`` in pixels of *this* resolution, with the
  pixel centre of column u at ``u + 0.5``.
- ``depth`` is z-depth along the optical axis in scene units, 0 where unknown (background,
  no prior). A depth sensor, an SfM point or a synthetic renderer all give z-depth.
- ``images`` hold straight (not premultiplied) colour in [0, 1]; RGBA keeps its alpha so that
  training can composite onto a random background. Captures with a background everywhere (real
  ones, the procedural room) are RGB: no alpha channel rather than an alpha of 1.
- ``meta["distortion"]``, when present, is the lens that recorded the images: ``{k1, k2, p1, p2}``
  of OpenCV's radial-tangential model (``agent.camera``), the names nerfstudio writes next to
  ``camera_model: OPENCV``. Without it the images are pinhole images.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor


class DataError(ValueError):
    """A data folder or file is missing or malformed. The message says what was expected."""


# What agent.data.loaders.load_views accepts, for the messages of the errors a user can fix.
EXPECTED_LAYOUTS = (
    "expected transforms.json, transforms_train.json, a COLMAP model (sparse/0/ or cameras/images/points3D "
    ".bin|.txt), an LLFF folder (poses_bounds.npy with images/ or images_N/), a folder of images, a ROS 2 bag "
    "(rosbag2 folder, .mcap or .db3), or 'procedural[:views=100,width=64,seed=0]'"
)


@dataclass
class Views:
    images: Tensor  # [M, H, W, C] float32 in [0, 1], C = 3 (RGB) or 4 (RGBA)
    c2w: Tensor  # [M, 4, 4] float32
    intrinsics: Tensor  # [M, 4] float32: fx, fy, cx, cy
    names: list[str]  # [M] stable identifiers (file stems)
    depth: Tensor | None = None  # [M, H, W] float32 z-depth, 0 = unknown
    meta: dict = field(default_factory=dict)  # loader-specific extras (source path, scale ...)

    def __post_init__(self) -> None:
        m = self.images.shape[0]
        if self.images.ndim != 4 or self.images.shape[-1] not in (3, 4):
            raise DataError(f"images must be [M, H, W, 3|4], got {tuple(self.images.shape)}")
        if tuple(self.c2w.shape) != (m, 4, 4):
            raise DataError(f"c2w must be [{m}, 4, 4], got {tuple(self.c2w.shape)}")
        if tuple(self.intrinsics.shape) != (m, 4):
            raise DataError(f"intrinsics must be [{m}, 4], got {tuple(self.intrinsics.shape)}")
        if len(self.names) != m:
            raise DataError(f"{len(self.names)} names for {m} images")
        if self.depth is not None and tuple(self.depth.shape) != tuple(self.images.shape[:3]):
            raise DataError(f"depth must be {tuple(self.images.shape[:3])}, got {tuple(self.depth.shape)}")

    @property
    def height(self) -> int:
        return int(self.images.shape[1])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])

    def __len__(self) -> int:
        return int(self.images.shape[0])

    @property
    def has_alpha(self) -> bool:
        return int(self.images.shape[-1]) == 4

    @property
    def shows_surroundings(self) -> bool:
        """RGB without alpha or masks: every pixel sees something, so the field must model all of
        space (unbounded, contracted) and its box must hold the cameras. Decided by the format, not
        the pixels, so that every robot of a swarm on one capture builds the same field."""
        return not self.has_alpha

    def rgb(self, background: float | tuple[float, float, float] | Tensor = 1.0) -> Tensor:
        """Colour composited onto ``background`` (straight alpha): ``rgb * a + bg * (1 - a)``.

        background: a grey level, an RGB triple, or a tensor broadcastable to [M, H, W, 3]
        (e.g. a random colour per pixel, which training uses so that empty space stays empty).
        Returns [M, H, W, 3]. RGB images are returned unchanged.
        """
        if not self.has_alpha:
            return self.images
        bg = torch.as_tensor(background, dtype=self.images.dtype)
        if bg.ndim == 0:
            bg = bg.expand(3)
        alpha = self.images[..., 3:4]
        return self.images[..., :3] * alpha + bg * (1 - alpha)

    def subset(self, index: list[int] | Tensor) -> "Views":
        idx = torch.as_tensor(index, dtype=torch.long)
        return Views(
            images=self.images[idx],
            c2w=self.c2w[idx],
            intrinsics=self.intrinsics[idx],
            names=[self.names[int(i)] for i in idx],
            depth=None if self.depth is None else self.depth[idx],
            meta=dict(self.meta),
        )
