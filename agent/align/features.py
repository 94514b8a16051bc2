"""A robot's own views as its summary reads them: numpy cameras and SIFT features, each image detected once."""

from __future__ import annotations

import cv2
import numpy as np
import torch

from agent.align.config import AlignConfig
from agent.align.payload import DESC_DIM
from agent.data.views import Views

__all__ = ["OwnViews"]


def _grey_uint8(image: torch.Tensor | np.ndarray) -> np.ndarray:
    """[H, W, 3|4] float in [0, 1] -> [H, W] uint8, RGBA composited on white as everywhere else."""
    img = image.detach().cpu().numpy() if isinstance(image, torch.Tensor) else np.asarray(image)
    if img.shape[-1] == 4:
        img = img[..., :3] * img[..., 3:4] + (1.0 - img[..., 3:4])
    grey = img[..., :3] @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
    return np.clip(np.rint(grey * 255.0), 0, 255).astype(np.uint8)


def _rootsift(desc: np.ndarray) -> np.ndarray:
    """OpenCV SIFT [N, 128] -> RootSIFT (L1-normalise, square root): Hellinger kernel as a dot product."""
    d = desc.astype(np.float32)
    d /= d.sum(1, keepdims=True) + 1e-7
    return np.sqrt(d)


class OwnViews:
    """Cameras, depth and (lazily) the RootSIFT features of one robot's views."""

    def __init__(self, views: Views, cfg: AlignConfig) -> None:
        self.images = views.images
        self.c2w = views.c2w.detach().cpu().double().numpy()  # [M, 4, 4]
        self.intr = views.intrinsics.detach().cpu().double().numpy()  # [M, 4]
        self.depth = None if views.depth is None else views.depth.detach().cpu().numpy()  # [M, H, W]
        self.matcher = cv2.BFMatcher(cv2.NORM_L2)
        self._sift = cv2.SIFT_create(nfeatures=cfg.sift_features, contrastThreshold=cfg.sift_contrast)
        self._features: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def features(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """View i's (OpenCV keypoints xy [N, 2], RootSIFT [N, 128], SIFT response [N])."""
        if i not in self._features:
            kps, desc = self._sift.detectAndCompute(_grey_uint8(self.images[i]), None)
            if desc is None or not kps:
                self._features[i] = (np.zeros((0, 2)), np.zeros((0, DESC_DIM), np.float32), np.zeros(0))
            else:
                self._features[i] = (np.array([k.pt for k in kps], dtype=np.float64), _rootsift(desc),
                                     np.array([k.response for k in kps]))
        return self._features[i]
