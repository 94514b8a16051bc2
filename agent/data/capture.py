"""Geometry of a capture, in the world frame of its cameras: the scene centre, the up axis, each
camera's azimuth, and the box the scene fits in (OpenGL cameras, :mod:`agent.camera`)."""

from __future__ import annotations

import torch
from torch import Tensor

from agent.camera import fov_from_focal, optical_axis, unproject_depth
from agent.data.views import DataError, Views

__all__ = ["scene_center", "mean_up", "azimuths_deg", "estimate_scene_box", "field_box_mismatch", "box_from_bounds",
           "view_bounds", "capture_warnings", "DEPTH_BOX_QUANTILE", "DEPTH_BOX_PADDING", "CAMERA_BOX_MARGIN"]


def scene_center(c2w: Tensor) -> Tensor:
    """Least-squares point closest to all optical axes.  c2w: [M, 4, 4] -> [3] float64.

    Minimises ``sum_i |(I - d_i d_i^T)(p - o_i)|^2`` (distance of p to each axis). When the axes
    are (nearly) parallel, e.g. a forward-facing capture, the mean camera centre is used instead.
    """
    c2w = c2w.to(torch.float64)
    o = c2w[:, :3, 3]
    d = optical_axis(c2w)
    d = d / d.norm(dim=-1, keepdim=True)
    proj = torch.eye(3, dtype=torch.float64) - d[:, :, None] * d[:, None, :]  # [M, 3, 3]
    a = proj.sum(0)
    b = (proj @ o[:, :, None]).sum(0)[:, 0]
    if torch.linalg.eigvalsh(a).min() < 1e-3 * len(c2w):
        return o.mean(0)
    return torch.linalg.solve(a, b)


def mean_up(c2w: Tensor) -> Tensor:
    """The up axis of a capture.  c2w: [M, 4, 4] -> [3] unit float64.

    Starts from the mean of the cameras' up vectors (their +Y axes). That mean leans towards
    wherever the cameras happen to be (cameras looking down at an object from random azimuths
    tilt it by several degrees), so when the cameras have no roll, i.e. their x axes are all
    horizontal as in the Blender scenes and most captures, the axis orthogonal to every x axis
    is used instead (smallest eigenvector of sum x x^T, signed like the mean up), which is exact.
    """
    c2w = c2w.to(torch.float64)
    up = c2w[:, :3, 1].mean(0)
    if up.norm() < 1e-6:
        raise DataError("the cameras' up vectors cancel out; give the up axis explicitly")
    up = up / up.norm()
    right = c2w[:, :3, 0]
    evals, evecs = torch.linalg.eigh(right.T @ right)
    # roll-free cameras: x axes orthogonal to one direction (< ~2 deg rms), and spread enough to define it
    if len(c2w) >= 3 and evals[0] < 1e-3 * len(c2w) and evals[1] > 0.05 * len(c2w):
        normal = evecs[:, 0]
        return normal if normal @ up > 0 else -normal
    return up


def _plane_basis(up: Tensor) -> tuple[Tensor, Tensor]:
    """Two unit vectors spanning the plane orthogonal to ``up``; e1 from the world axis least
    aligned with up (so that for up = +z the azimuth is the usual atan2(y, x))."""
    axis = torch.zeros(3, dtype=torch.float64)
    axis[int(up.abs().argmin())] = 1.0
    e1 = axis - (axis @ up) * up
    e1 = e1 / e1.norm()
    return e1, torch.linalg.cross(up, e1)


def azimuths_deg(c2w: Tensor, center: Tensor, up: Tensor) -> Tensor:
    """Azimuth in [0, 360) of each camera centre about ``up`` through ``center``.  -> [M] float64."""
    e1, e2 = _plane_basis(up.to(torch.float64))
    v = c2w[:, :3, 3].to(torch.float64) - center.to(torch.float64)
    return torch.rad2deg(torch.atan2(v @ e2, v @ e1)) % 360.0


DEPTH_BOX_QUANTILE = 0.01  # per axis, each side: sparse SfM depth has outliers far from the scene
DEPTH_BOX_PADDING = 0.2  # of the quantile bounds' largest extent
CAMERA_BOX_MARGIN = 0.1  # a capture that shows its surroundings: the box reaches this far past its cameras


def estimate_scene_box(views: Views, unbounded: bool | None = None,
                       cameras_elsewhere: bool = False) -> tuple[Tensor, float, str]:
    """The world box of the scene: (centre [3], half-size, where the object's box came from).

    unbounded: the field the box is for (``field.unbounded``); None: what the images call for
    (``views.shows_surroundings``), as the field itself decides when the setting is unset.

    A capture that shows its surroundings gets an unbounded field, linear only inside the box and
    contracted outside it, where a grid cell spans ~|x|^2 times more space. Cameras left out there
    see their near space through cells a scene unit deep, the room's wall and the camera's own
    neighbourhood fall into the same few cells, and a few views on an arc are then fitted by
    floaters in front of the lens (docs/results.md, the room). So, as nerfstudio and mip-NeRF 360
    put the cameras inside the uncontracted region, the box grows about its centre to hold every
    camera centre (plus ``CAMERA_BOX_MARGIN``).

    cameras_elsewhere: other robots' cameras, which these views do not show, must fit too (the
    reference derives the box for a swarm with no scene file): the box holds the sphere through the
    farthest camera, so cameras as far from the centre in any direction are inside.
    """
    centre, half, source = _object_box(views)
    if views.shows_surroundings if unbounded is None else unbounded:
        offsets = views.c2w[:, :3, 3].to(torch.float64) - centre.to(torch.float64)  # [M, 3]
        reach = offsets.norm(dim=-1).amax() if cameras_elsewhere else offsets.abs().amax()
        half = max(half, float(reach) * (1 + CAMERA_BOX_MARGIN))
    return centre, half, source


def field_box_mismatch(views: Views, unbounded: bool | None) -> str | None:
    """One line when ``field.unbounded`` is set against what the images show (None when it is unset
    or agrees). A split sizes the swarm's box for the field the images call for, before any
    training setting is known, so a field set the other way trains in a box meant for the other."""
    if unbounded is None or unbounded == views.shows_surroundings:
        return None
    if unbounded:
        return ("training.train.field.unbounded = true, but these images have alpha or masks: the split's box is the "
                "object's, so the cameras sit in the contracted shell and see their near space through coarse cells "
                "(expect floaters in front of the lens); unset it, or give images without alpha")
    return ("training.train.field.unbounded = false, but these RGB images without alpha or masks show their "
            "surroundings: the field ends at the box (grown to hold the cameras) and must fit everything seen beyond "
            "it inside; unset it (an unbounded field), or give masks (masks/ beside images/)")


def _object_box(views: Views) -> tuple[Tensor, float, str]:
    """The world box of the object or scene the cameras look at: (centre [3], half-size, source).

    In order of trust: ``meta['scene_box_world']`` (the procedural scene knows it exactly; a json
    may carry it); the bounds of the depth unprojected into the world (1st-99th percentile per
    axis, padded by 20%); the per-view near/far bounds of LLFF (:func:`box_from_bounds`); else
    the cameras: centre of the optical axes and the half-width of the median frustum at that
    distance (for the Blender scenes this gives ~1.45, close to the customary [-1.5, 1.5]^3).

    The depth bounds must not clip the object: a box that cuts off its extremities leaves them
    unrenderable. The 2nd-98th percentile padded by 10% cut 1.4% of lego's SfM points inside the
    true box; an images-only swarm on it fitted its own training views at 29.93 / 32.16 dB, and at
    32.67 / 33.44 in the true box (same true cameras, one in-process run each). With this rule the
    box is as large as the true one (half-size 1.45) and cuts 0.04%, and the lego-2-images-only
    scenario scores 30.19 / 30.06 dB held out instead of 29.02 / 28.90 (README).
    """
    box = views.meta.get("scene_box_world")
    if isinstance(box, dict) and "center" in box and "half_size" in box:
        return torch.tensor(box["center"], dtype=torch.float64), float(box["half_size"]), "dataset"
    if views.depth is not None and bool((views.depth > 0).any()):
        p = torch.cat([unproject_depth(views.depth[i], views.intrinsics[i], views.c2w[i]) for i in range(len(views))])
        if len(p) > 200_000:
            p = p[torch.randperm(len(p), generator=torch.Generator().manual_seed(0))[:200_000]]
        lo, hi = torch.quantile(p, DEPTH_BOX_QUANTILE, dim=0), torch.quantile(p, 1 - DEPTH_BOX_QUANTILE, dim=0)
        return 0.5 * (lo + hi), float(0.5 * (1 + DEPTH_BOX_PADDING) * (hi - lo).max()), "depth"
    bounds = view_bounds(views)
    if bounds is not None:
        centre, half = box_from_bounds(views.c2w, bounds)
        return centre, half, "bounds"
    center = scene_center(views.c2w)
    dist = (views.c2w[:, :3, 3].to(torch.float64) - center).norm(dim=-1)
    fov = torch.minimum(fov_from_focal(views.width, views.intrinsics[:, 0]), fov_from_focal(views.height, views.intrinsics[:, 1]))
    half_fov = (0.5 * fov).to(torch.float64)
    return center, float((dist * torch.tan(half_fov)).median()), "cameras"


def view_bounds(views: Views) -> Tensor | None:
    """[M, 2] near/far depth bounds of every view from ``meta['bounds']`` ({name: [near, far]}), or None."""
    table = views.meta.get("bounds")
    if not isinstance(table, dict) or not all(n in table for n in views.names):
        return None
    return torch.tensor([table[n] for n in views.names], dtype=torch.float64)


def box_from_bounds(c2w: Tensor, near_far: Tensor) -> tuple[Tensor, float]:
    """The box the per-view depth bounds put the scene in: (centre [3], half-size).

    c2w: [M, 4, 4], near_far: [M, 2] z-depth bounds (LLFF's: the 0.1th-99.9th percentile depth
    of the SfM points each view sees). Centred on the point nearest the optical axes
    (:func:`scene_center`); the half-size is the farthest the bounds reach from it along any
    camera's axis, ``max(d - near, far - d)`` with ``d`` the centre's z-depth in that camera. An
    object seen from all round is inside (what one view sees at its edge is on another's axis);
    a forward-facing capture, whose centre is the mean camera, gets the box of its far bound.
    """
    centre = scene_center(c2w)
    c2w, nf = c2w.to(torch.float64), near_far.to(torch.float64)
    axis = optical_axis(c2w)
    d = ((centre - c2w[:, :3, 3]) * axis).sum(-1) / axis.norm(dim=-1)  # [M] z-depth of the centre
    reach = torch.maximum(d - nf[:, 0], nf[:, 1] - d)
    return centre, float(reach.max())


def capture_warnings(views: Views, box_source: str) -> list[str]:
    """What in a dataset would train badly, one line each (``dinerf-agent inspect`` prints them).

    box_source: where :func:`estimate_scene_box` found the box.
    """
    out = []
    if views.shows_surroundings:
        out.append("RGB images without alpha or masks: everything the cameras see must be modelled, by an unbounded "
                   "field (scene contraction, its box grown to hold the cameras); to train an object alone, "
                   "give masks (masks/ beside images/)")
    elif bool((views.images[..., 3] >= 1.0).all()):
        out.append("alpha opaque in every pixel: the field stays in the scene box, which cuts off what the cameras "
                   "see around the object; give real masks, or images without alpha for an unbounded field")
    if box_source == "cameras":
        out.append("scene box estimated from the cameras only (the frustum width where the optical axes meet): "
                   "check that it holds the whole scene")
    lens = views.meta.get("lens")
    if isinstance(lens, dict) and not lens.get("undistorted"):
        out.append(f"lens distortion ignored ({', '.join(lens.get('models', []))}): rays miss their pixels "
                   "towards the image edges")
    return out
