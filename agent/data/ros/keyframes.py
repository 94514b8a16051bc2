"""Keyframes of a camera stream: a frame once the camera has moved enough, the sharpest near it.

Planned on the poses alone (cheap: no pixel is decoded), so that a budget can be met over the
whole trajectory before any image is read; :mod:`agent.data.ros.bag` then decodes only the frames
of each window and keeps the sharpest.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agent.data.ros.config import KeyframeConfig

__all__ = ["KeyframePlan", "plan_keyframes", "OnlineKeyframer", "AUTO_TRANSLATION_FRACTION"]

AUTO_TRANSLATION_FRACTION = 0.02  # min_translation = 0: this fraction of the trajectory's extent


@dataclass
class KeyframePlan:
    windows: list[list[int]]  # per keyframe, the frames (indices into the poses) it is chosen from
    min_translation: float  # the thresholds finally used (raised to fit the budget)
    min_rotation_deg: float
    triggers_unbudgeted: int  # keyframes the configured thresholds alone would give


def _moved_or_turned(c_j: np.ndarray, r_j: np.ndarray, c_i: np.ndarray, r_i: np.ndarray, min_t: float,
                     min_r_deg: float) -> bool:
    """Whether camera i moved ``min_t`` or turned ``min_r_deg`` from camera j (centres [3], rotations [3, 3])."""
    moved = min_t > 0 and np.linalg.norm(c_i - c_j) >= min_t
    # angle of R_j^T R_i from its trace: cos = (tr - 1) / 2
    turned = min_r_deg > 0 and (np.trace(r_j.T @ r_i) - 1) / 2 <= np.cos(np.radians(min_r_deg))
    return bool(moved or turned)


def _triggers(centres: np.ndarray, rots: np.ndarray, min_t: float, min_r_deg: float) -> list[int]:
    """Greedy: frame 0, then every frame that moved ``min_t`` or turned ``min_r_deg`` since the last trigger."""
    out = [0]
    for i in range(1, len(centres)):
        j = out[-1]
        if _moved_or_turned(centres[j], rots[j], centres[i], rots[i], min_t, min_r_deg):
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


class OnlineKeyframer:
    """The same rule applied as frames arrive (a bag replayed, a live camera), with no look-ahead.

    A frame opens a window once the camera moved or turned enough since the last window opened;
    the window's sharpest of ``sharpness_window`` frames becomes the keyframe. ``min_translation =
    0`` stands for 2% of the trajectory's extent *so far* (the whole one is not known yet). Only
    the frames of a window need their pixels (``sharpness`` is asked for those alone). The budget
    is not spread over the trajectory as the offline plan does (the trajectory is not known in
    advance): keyframes past ``max_keyframes`` are dropped and counted.
    """

    def __init__(self, cfg: KeyframeConfig) -> None:
        self.cfg = cfg
        self._last: tuple[np.ndarray, np.ndarray] | None = None  # the last window's first camera
        self._lo = self._hi = None  # the trajectory's bounding box so far
        self._window: list[tuple[float, object]] = []  # (sharpness, frame) of the open window
        self.kept = 0
        self.dropped = 0  # keyframes past the budget

    def _min_translation(self, centre: np.ndarray) -> float:
        self._lo = centre if self._lo is None else np.minimum(self._lo, centre)
        self._hi = centre if self._hi is None else np.maximum(self._hi, centre)
        if self.cfg.min_translation > 0:
            return self.cfg.min_translation
        return AUTO_TRANSLATION_FRACTION * float(np.linalg.norm(self._hi - self._lo))

    def offer(self, c2w: np.ndarray, frame: object, sharpness) -> object | None:
        """One posed frame (c2w [4, 4]); ``sharpness(frame)`` is called only for frames in a window.
        Returns the frame that completes a window as a keyframe, if this one does."""
        centre, rot = np.asarray(c2w, np.float64)[:3, 3], np.asarray(c2w, np.float64)[:3, :3]
        min_t = self._min_translation(centre)
        if not self._window:
            first = self._last is None
            if not first and not _moved_or_turned(*self._last, centre, rot, min_t, self.cfg.min_rotation_deg):
                return None
            self._last = (centre, rot)
        self._window.append((float(sharpness(frame)), frame))
        if len(self._window) < self.cfg.sharpness_window:
            return None
        return self.flush()

    def flush(self) -> object | None:
        """Close the open window (the stream ended): its sharpest frame, within the budget."""
        if not self._window:
            return None
        best = max(self._window, key=lambda w: w[0])[1]
        self._window = []
        if self.cfg.max_keyframes and self.kept >= self.cfg.max_keyframes:
            self.dropped += 1
            return None
        self.kept += 1
        return best
