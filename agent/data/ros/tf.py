"""The tf tree of a recording: where a frame was at a stamp, interpolated, never extrapolated.

``/tf_static`` gives fixed parent -> child transforms, ``/tf`` time series of them (odometry,
the robot's joints). A lookup walks both frames up to the tree's root and composes, as tf2
does; between two samples of a dynamic link the translation is interpolated linearly and the
rotation by slerp. A stamp outside a link's samples, or in a gap wider than the tolerance, has no
transform (:class:`NoTransform` says which link and why): a pose is never guessed.
"""

from __future__ import annotations

from bisect import bisect_left
from dataclasses import dataclass, field

import numpy as np

__all__ = ["TfTree", "NoTransform", "quaternion_matrix", "matrix_quaternion", "slerp"]


class NoTransform(LookupError):
    """No transform between two frames at a stamp; ``reason`` is a short key for counting."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason


def quaternion_matrix(t: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Translation [3] and unit quaternion [4] (x, y, z, w: ROS order) -> [4, 4]."""
    x, y, z, w = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    m = np.eye(4)
    m[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    m[:3, 3] = t
    return m


def matrix_quaternion(m: np.ndarray) -> np.ndarray:
    """The rotation of [4, 4] (or [3, 3]) as a unit quaternion [4] (x, y, z, w), w >= 0."""
    r = np.asarray(m, dtype=np.float64)[:3, :3]
    tr = np.trace(r)
    if tr > 0:
        s = 2 * np.sqrt(tr + 1)
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, s / 4]
    else:
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2 * np.sqrt(1 + r[i, i] - r[j, j] - r[k, k])
        q = [0.0, 0.0, 0.0, (r[k, j] - r[j, k]) / s]
        q[i], q[j], q[k] = s / 4, (r[j, i] + r[i, j]) / s, (r[k, i] + r[i, k]) / s
    q = np.asarray(q)
    return q / np.linalg.norm(q) * (1 if q[3] >= 0 else -1)


def slerp(q0: np.ndarray, q1: np.ndarray, s: float) -> np.ndarray:
    """Unit quaternions [4] -> the one a fraction ``s`` of the way along the shorter arc."""
    dot = float(np.dot(q0, q1))
    if dot < 0:  # the shorter way round
        q1, dot = -q1, -dot
    if dot > 0.9995:
        q = q0 + s * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = np.arccos(min(dot, 1.0))
    return (np.sin((1 - s) * theta) * q0 + np.sin(s * theta) * q1) / np.sin(theta)


@dataclass
class _Link:
    """One parent -> child edge: static, or samples in time (stamps in ns, sorted on finish())."""

    parent: str
    static: np.ndarray | None = None  # [4, 4]
    stamps: list[int] = field(default_factory=list)
    translations: list[np.ndarray] = field(default_factory=list)
    rotations: list[np.ndarray] = field(default_factory=list)

    def at(self, stamp: int, child: str, max_gap_ns: int) -> np.ndarray:
        if self.static is not None:
            return self.static
        i = bisect_left(self.stamps, stamp)
        if i < len(self.stamps) and self.stamps[i] == stamp:
            return quaternion_matrix(self.translations[i], self.rotations[i])
        where = f"{self.parent} -> {child}"
        if i == 0 or i == len(self.stamps):
            side = "before the first" if i == 0 else "after the last"
            raise NoTransform("outside_tf", f"stamp {stamp * 1e-9:.3f} s is {side} transform {where} (no extrapolation)")
        t0, t1 = self.stamps[i - 1], self.stamps[i]
        if t1 - t0 > max_gap_ns:
            raise NoTransform("tf_gap", f"{where}: {(t1 - t0) * 1e-9:.3f} s between the transforms around stamp "
                                        f"{stamp * 1e-9:.3f} s (more than data.ros.tf_max_gap_s)")
        s = (stamp - t0) / (t1 - t0)
        t = (1 - s) * self.translations[i - 1] + s * self.translations[i]
        return quaternion_matrix(t, slerp(self.rotations[i - 1], self.rotations[i], s))


class TfTree:
    """Links child -> parent from /tf and /tf_static; :meth:`lookup` composes them at a stamp."""

    def __init__(self, max_gap_s: float) -> None:
        self.links: dict[str, _Link] = {}
        self.max_gap_ns = int(max_gap_s * 1e9)
        self.dynamic_span: tuple[int, int] | None = None  # first and last stamp of /tf

    def add(self, parent: str, child: str, stamp: int, translation, rotation, static: bool) -> None:
        """One TransformStamped; a child has one parent (tf's rule), a second one is refused."""
        parent, child = parent.lstrip("/"), child.lstrip("/")
        link = self.links.get(child)
        if link is None:
            link = self.links[child] = _Link(parent)
        elif link.parent != parent:
            raise ValueError(f"frame {child!r} has two parents in the tf tree ({link.parent!r} and {parent!r})")
        q = np.asarray(rotation, dtype=np.float64)
        if not (np.isfinite(q).all() and np.isfinite(translation).all()) or np.linalg.norm(q) < 1e-9:
            raise ValueError(f"transform {parent} -> {child} at {stamp * 1e-9:.3f} s is not finite or has a zero quaternion")
        if static:
            link.static = quaternion_matrix(np.asarray(translation, dtype=np.float64), q)
            return
        link.stamps.append(int(stamp))
        link.translations.append(np.asarray(translation, dtype=np.float64))
        link.rotations.append(q / np.linalg.norm(q))
        lo, hi = self.dynamic_span or (stamp, stamp)
        self.dynamic_span = (min(lo, stamp), max(hi, stamp))

    def finish(self) -> "TfTree":
        """Sort each link's samples by stamp (bags are ordered by receive time, not header stamp)."""
        for link in self.links.values():
            if link.stamps:
                order = np.argsort(link.stamps, kind="stable")
                link.stamps = [link.stamps[i] for i in order]
                link.translations = [link.translations[i] for i in order]
                link.rotations = [link.rotations[i] for i in order]
        return self

    @property
    def frames(self) -> set[str]:
        return set(self.links) | {link.parent for link in self.links.values()}

    def chain(self, frame: str) -> list[str]:
        """``frame`` and its ancestors up to the root."""
        out = [frame.lstrip("/")]
        while out[-1] in self.links:
            out.append(self.links[out[-1]].parent)
            if len(out) > len(self.links) + 1:
                raise ValueError(f"the tf tree has a cycle through {frame!r}")
        return out

    def root(self, frame: str) -> str:
        return self.chain(frame)[-1]

    def roots(self) -> list[str]:
        return sorted({self.root(f) for f in self.frames})

    def describe(self, frame: str) -> str:
        """``odom -> base_link -> camera_optical`` (s: static link) for the frame's chain."""
        chain = self.chain(frame)[::-1]
        parts = [chain[0]] + [f"{c}{' (s)' if self.links[c].static is not None else ''}" for c in chain[1:]]
        return " -> ".join(parts)

    def _to_root(self, frame: str, stamp: int) -> np.ndarray:
        m = np.eye(4)
        for child in self.chain(frame)[:-1]:
            m = self.links[child].at(stamp, child, self.max_gap_ns) @ m
        return m

    def lookup(self, target: str, source: str, stamp: int) -> np.ndarray:
        """T_target_from_source [4, 4] at ``stamp`` (ns); :class:`NoTransform` when there is none."""
        target, source = target.lstrip("/"), source.lstrip("/")
        if source not in self.frames:
            raise NoTransform("no_tf_link", f"frame {source!r} is not in the tf tree (frames: {sorted(self.frames)[:8]})")
        if self.root(source) != self.root(target):
            raise NoTransform("no_tf_link", f"no tf link from {source!r} to {target!r}: their trees' roots are "
                                            f"{self.root(source)!r} and {self.root(target)!r}")
        return np.linalg.inv(self._to_root(target, stamp)) @ self._to_root(source, stamp)
