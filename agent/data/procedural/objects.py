"""Analytic objects of the procedural scene: ray intersection, SDF, normal and albedo.

Each object answers ``intersect(o, d)`` (the smallest ``t > 0`` of ``o + t d``, ``inf`` on a miss;
``d`` need not be unit, so with camera directions scaled to z = -1 the ``t`` is the z-depth),
``sdf(p)``, ``normal(p)`` and ``albedo(p)``. Textures are smooth (:func:`soft`): sharp edges in
3-D texture are what a hash grid learns worst.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["Sphere", "Ellipsoid", "Box", "Cylinder", "soft", "mix", "matmul3"]

EPS = 1e-9


def soft(x: np.ndarray, k: float = 3.0) -> np.ndarray:
    """A soft square wave in [0, 1] from a signed value (``tanh`` instead of a hard sign)."""
    return 0.5 + 0.5 * np.tanh(k * x)


def matmul3(p: np.ndarray, m: np.ndarray) -> np.ndarray:
    """``p @ m`` for p: [N, 3], m: [3, 3], written out: numpy's matmul is slow for an inner size of 3."""
    return np.stack([p[:, 0] * m[0, j] + p[:, 1] * m[1, j] + p[:, 2] * m[2, j] for j in range(3)], -1)


def mix(a, b, s: np.ndarray) -> np.ndarray:
    return np.asarray(a)[None, :] * (1 - s[:, None]) + np.asarray(b)[None, :] * s[:, None]


class Sphere:
    def __init__(self, center, radius, albedo):
        self.c, self.r, self._albedo = np.asarray(center, float), float(radius), albedo

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        oc = o - self.c
        a = (d * d).sum(-1)
        b = (oc * d).sum(-1)
        cc = (oc * oc).sum(-1) - self.r**2
        disc = b * b - a * cc
        sq = np.sqrt(np.maximum(disc, 0.0))
        t0, t1 = (-b - sq) / a, (-b + sq) / a
        t = np.where(t0 > EPS, t0, t1)
        return np.where((disc >= 0) & (t > EPS), t, np.inf)

    def sdf(self, p):
        return np.linalg.norm(p - self.c, axis=-1) - self.r

    def normal(self, p):
        n = p - self.c
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    def albedo(self, p):
        return self._albedo(p, self)


class Ellipsoid:
    def __init__(self, center, radii, albedo):
        self.c, self.radii, self._albedo = np.asarray(center, float), np.asarray(radii, float), albedo

    def intersect(self, o, d):
        return Sphere(np.zeros(3), 1.0, None).intersect((o - self.c) / self.radii, d / self.radii)

    def sdf(self, p):
        # not an exact distance away from the surface, but exact zero set and first-order scale
        q = (p - self.c) / self.radii
        return (np.linalg.norm(q, axis=-1) - 1.0) * self.radii.min()

    def normal(self, p):
        n = (p - self.c) / self.radii**2
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    def albedo(self, p):
        return self._albedo(p, self)


class Box:
    """An oriented box: centre, half sizes, rotation about z by ``yaw_deg``."""

    def __init__(self, center, half, yaw_deg, albedo):
        self.c, self.h, self._albedo = np.asarray(center, float), np.asarray(half, float), albedo
        a = math.radians(yaw_deg)
        self.rot = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])

    def local(self, p):
        return matmul3(p - self.c, self.rot)  # = R^T (p - c) row-wise

    def intersect(self, o, d):
        ol, dl = self.local(o), matmul3(d, self.rot)
        # slab method, per axis with plain column arithmetic (reductions over a size-3 axis are slow);
        # a direction component of exactly 0 is nudged so that 1/d stays finite and signed
        dl = np.where(np.abs(dl) < 1e-30, 1e-30, dl)
        tmin, tmax = np.full(len(o), -np.inf), np.full(len(o), np.inf)
        for a in range(3):
            inv = 1.0 / dl[:, a]
            t1, t2 = (-self.h[a] - ol[:, a]) * inv, (self.h[a] - ol[:, a]) * inv
            tmin = np.maximum(tmin, np.minimum(t1, t2))
            tmax = np.minimum(tmax, np.maximum(t1, t2))
        t = np.where(tmin > EPS, tmin, tmax)
        return np.where((tmin <= tmax) & (t > EPS), t, np.inf)

    def sdf(self, p):
        q = np.abs(self.local(p)) - self.h
        return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(-1), 0.0)

    def normal(self, p):
        q = self.local(p) / self.h
        axis = np.abs(q).argmax(-1)
        n = np.zeros_like(q)
        n[np.arange(len(q)), axis] = np.sign(q[np.arange(len(q)), axis])
        return matmul3(n, self.rot.T)

    def albedo(self, p):
        return self._albedo(p, self)


class Cylinder:
    """A capped cylinder with a vertical axis through (x, y), from z0 to z1."""

    def __init__(self, center_xy, radius, z0, z1, albedo):
        self.cxy, self.r, self.z0, self.z1, self._albedo = np.asarray(center_xy, float), float(radius), z0, z1, albedo

    def intersect(self, o, d):
        ox, oy = o[:, 0] - self.cxy[0], o[:, 1] - self.cxy[1]
        dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
        a = dx * dx + dy * dy
        b = ox * dx + oy * dy
        c = ox * ox + oy * oy - self.r**2
        disc = b * b - a * c
        with np.errstate(divide="ignore", invalid="ignore"):
            t_side = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
            z_side = o[:, 2] + t_side * dz
            side_ok = (disc >= 0) & (a > 0) & (t_side > EPS) & (z_side >= self.z0) & (z_side <= self.z1)
            best = np.where(side_ok, t_side, np.inf)
            for zc in (self.z0, self.z1):
                tc = (zc - o[:, 2]) / dz
                x, y = ox + tc * dx, oy + tc * dy
                cap_ok = np.isfinite(tc) & (tc > EPS) & (x * x + y * y <= self.r**2)
                best = np.minimum(best, np.where(cap_ok, tc, np.inf))
        return best

    def sdf(self, p):
        radial = np.linalg.norm(p[:, :2] - self.cxy, axis=-1) - self.r
        mid, half = 0.5 * (self.z0 + self.z1), 0.5 * (self.z1 - self.z0)
        axial = np.abs(p[:, 2] - mid) - half
        q = np.stack([radial, axial], -1)
        return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(-1), 0.0)

    def normal(self, p):
        radial = np.linalg.norm(p[:, :2] - self.cxy, axis=-1) - self.r
        mid, half = 0.5 * (self.z0 + self.z1), 0.5 * (self.z1 - self.z0)
        axial = np.abs(p[:, 2] - mid) - half
        side = np.concatenate([p[:, :2] - self.cxy, np.zeros((len(p), 1))], -1)
        side /= np.maximum(np.linalg.norm(side, axis=-1, keepdims=True), 1e-12)
        cap = np.zeros_like(p)
        cap[:, 2] = np.sign(p[:, 2] - mid)
        return np.where((radial > axial)[:, None], side, cap)

    def albedo(self, p):
        return self._albedo(p, self)
