"""Keyframes of a camera stream: a frame once the camera has moved enough, the sharpest near it.

Planned on the poses alone (cheap: no pixel is decoded), so that a budget can be met over the
whole trajectory before any image is read; :mod:`agent.data.ros.bag` then decodes only the frames
of each window and keeps the sharpest.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agent.data.ros.config import KeyframeConfig

__all__ = ["KeyframePlan", "plan_keyframes", "AUTO_TRANSLATION_FRACTION"]

AUTO_TRANSLATION_FRACTION = 0.02  # min_translation = 0: this fraction of the trajectory's extent


@dataclass
class KeyframePlan:
    windows: list[list[int]]  # per keyframe, the frames (indices into the poses) it is chosen from
    min_translation: float  # the thresholds finally used (raised to fit the budget)
    min_rotation_deg: float
    triggers_unbudgeted: int  # keyframes the configured thresholds alone would give


def _triggers(centres: np.ndarray, rots: np.ndarray, min_t: float, min_r_deg: float) -> list[int]:
    """Greedy: frame 0, then every frame that moved ``min_t`` or turned ``min_r_deg`` since the last trigger."""
    out = [0]
    cos_min = np.cos(np.radians(min_r_deg) if min_r_deg > 0 else np.inf)
    for i in range(1, len(centres)):
        j = out[-1]
        moved = min_t > 0 and np.linalg.norm(centres[i] - centres[j]) >= min_t
        # angle of R_j^T R_i from its trace: cos = (tr - 1) / 2
        turned = min_r_deg > 0 and (np.trace(rots[j].T @ rots[i]) - 1) / 2 <= cos_min
        if moved or turned:
            out.append(i)
    return out


def plan_keyframes(c2w: np.ndarray, cfg: KeyframeConfig) -> KeyframePlan:
    """c2w: [N, 4, 4] posed frames in time order -> the windows the keyframes are chosen from."""
    n = len(c2w)
    if n == 0:
        return KeyframePlan([], cfg.min_translation, cfg.min_rotation_deg, 0)
    centres, rots = c2w[:, :3, 3].astype(np.float64), c2w[:, :3, :3].astype(np.float64)
    min_t = cfg.min_translation
    if min_t == 0:
        extent = float(np.linalg.norm(centres.max(0) - centres.min(0)))
        min_t = AUTO_TRANSLATION_FRACTION * extent
    min_r = cfg.min_rotation_deg
    triggers = _triggers(centres, rots, min_t, min_r)
    unbudgeted = len(triggers)
    if cfg.max_keyframes and len(triggers) > cfg.max_keyframes:
        if min_t <= 0 and min_r <= 0:  # nothing to raise: spread the budget evenly
            triggers = sorted({int(round(x)) for x in np.linspace(0, n - 1, cfg.max_keyframes)})
        else:
            lo, hi = 1.0, 2.0
            while len(_triggers(centres, rots, min_t * hi, min(min_r * hi, 180.0))) > cfg.max_keyframes and hi < 1e6:
                lo, hi = hi, hi * 2
            for _ in range(30):  # the smallest factor that fits the budget
                mid = 0.5 * (lo + hi)
                if len(_triggers(centres, rots, min_t * mid, min(min_r * mid, 180.0))) > cfg.max_keyframes:
                    lo = mid
                else:
                    hi = mid
            min_t, min_r = min_t * hi, min(min_r * hi, 180.0)
            triggers = _triggers(centres, rots, min_t, min_r)
    ends = triggers[1:] + [n]
    windows = [list(range(t, min(t + cfg.sharpness_window, end))) for t, end in zip(triggers, ends)]
    return KeyframePlan(windows, min_t, min_r, unbudgeted)
