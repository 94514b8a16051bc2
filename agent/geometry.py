"""Pose math for the whole project: SO(3), SE(3) and Sim(3) as 4x4 matrices.

One module owns this so that the data split, the trainer, the coarse alignment and the
evaluation agree on every convention:

- Cameras are camera-to-world (c2w) 4x4 matrices in the OpenGL/Blender convention
  (the camera looks down -Z, +Y is up in the image); pixels, projection and depth are
  :mod:`agent.camera`'s.
- A similarity ``T = (s, R, t)`` is stored as ``[[s R, t], [0, 1]]`` and maps a point
  ``x -> s R x + t``. SE(3) is the special case ``s = 1``.
- A robot's relative pose ``T_i`` maps its local frame into the shared frame ``g``. A camera
  moves with it as ``[R R_c | s R t_c + t]``: the rotation stays orthonormal, only the
  camera centre is scaled (:func:`transform_c2w`).

Everything is differentiable in torch where it needs to be (``so3_exp``, ``sim3_from_params``,
``transform_c2w``); the logarithm and the error metrics are for evaluation.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = [
    "skew",
    "so3_exp",
    "so3_log",
    "sim3_from_params",
    "sim3_to_params",
    "pose_summary",
    "sim3_decompose",
    "sim3_compose",
    "sim3_inverse",
    "transform_points",
    "transform_c2w",
    "rotation_angle_deg",
    "pose_error",
    "umeyama",
    "umeyama_batched",
    "look_at",
    "random_rotation",
    "box_from_center",
]


def skew(v: Tensor) -> Tensor:
    """Cross-product matrix: ``skew(v) @ x == v x x``.  v: [..., 3] -> [..., 3, 3]."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack(
        [torch.stack([o, -z, y], -1), torch.stack([z, o, -x], -1), torch.stack([-y, x, o], -1)], -2
    )


def so3_exp(phi: Tensor) -> Tensor:
    """Rodrigues' formula, stable (value and gradient) at and near zero.  phi: [..., 3] -> [..., 3, 3].

    ``R = I + A K + B K^2`` with ``A = sin(th)/th``, ``B = (1 - cos th)/th^2 = 2 sin^2(th/2)/th^2``.
    Below th ~ 1e-2 the Taylor series is exact to float precision; the half-angle form of B
    avoids the cancellation of ``1 - cos`` in float32.
    """
    theta2 = (phi * phi).sum(-1)
    small = theta2 < 1e-4
    theta2_safe = torch.where(small, torch.ones_like(theta2), theta2)
    theta = theta2_safe.sqrt()
    a = torch.where(small, 1 - theta2 / 6 + theta2 * theta2 / 120, torch.sin(theta) / theta)
    half = torch.sin(theta / 2) / theta
    b = torch.where(small, 0.5 - theta2 / 24 + theta2 * theta2 / 720, 2 * half * half)
    k = skew(phi)
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device).expand(k.shape)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def so3_log(rot: Tensor) -> Tensor:
    """Axis-angle of a rotation matrix, valid over [0, pi].  rot: [..., 3, 3] -> [..., 3].

    Uses ``atan2`` for the angle (accurate at 0 and pi alike) and, near pi where
    ``R - R^T`` vanishes, recovers the axis from the symmetric part ``(R + R^T)/2 - cos I``.
    """
    rot = rot.to(torch.float64) if rot.dtype != torch.float64 else rot
    vee = torch.stack(
        [rot[..., 2, 1] - rot[..., 1, 2], rot[..., 0, 2] - rot[..., 2, 0], rot[..., 1, 0] - rot[..., 0, 1]],
        -1,
    )  # = 2 sin(th) axis
    sin_theta = 0.5 * vee.norm(dim=-1)
    cos_theta = 0.5 * (rot.diagonal(dim1=-2, dim2=-1).sum(-1) - 1)
    theta = torch.atan2(sin_theta, cos_theta)

    # Generic case (theta not near pi): axis * theta = vee * theta / (2 sin theta).
    factor = torch.where(sin_theta > 1e-12, theta / (2 * sin_theta.clamp_min(1e-300)), torch.full_like(theta, 0.5))
    generic = vee * factor[..., None]

    # Near pi: (R + R^T)/2 - cos(th) I = (1 - cos th) a a^T. Take the best-conditioned column.
    sym = 0.5 * (rot + rot.transpose(-1, -2))
    eye = torch.eye(3, dtype=rot.dtype, device=rot.device)
    aat = (sym - cos_theta[..., None, None] * eye) / (1 - cos_theta).clamp_min(1e-12)[..., None, None]
    col = aat.diagonal(dim1=-2, dim2=-1).argmax(-1)
    axis = torch.gather(aat, -1, col[..., None, None].expand(*aat.shape[:-1], 1)).squeeze(-1)
    axis = axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    # Resolve the sign with the antisymmetric part where it still carries information.
    sign = torch.sign((axis * vee).sum(-1))
    sign = torch.where(sign == 0, torch.ones_like(sign), sign)
    near_pi = axis * (theta * sign)[..., None]
    return torch.where((cos_theta < -0.99)[..., None], near_pi, generic)


def sim3_from_params(log_scale: Tensor, phi: Tensor, translation: Tensor) -> Tensor:
    """Differentiable ``[[exp(log_scale) R(phi), t], [0, 1]]``.

    log_scale: [...], phi: [..., 3], translation: [..., 3] -> [..., 4, 4].
    The scale is parameterised by its log so that it stays positive under gradient steps.
    """
    rot = so3_exp(phi)
    top = torch.cat([torch.exp(log_scale)[..., None, None] * rot, translation[..., :, None]], -1)
    bottom = torch.zeros(*top.shape[:-2], 1, 4, dtype=top.dtype, device=top.device)
    bottom[..., 0, 3] = 1
    return torch.cat([top, bottom], -2)


def sim3_decompose(transform: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``T -> (s, R, t)``.  transform: [..., 4, 4] -> ([...], [..., 3, 3], [..., 3])."""
    sr = transform[..., :3, :3]
    scale = torch.linalg.det(sr).abs().pow(1.0 / 3.0)
    return scale, sr / scale[..., None, None], transform[..., :3, 3]


def sim3_to_params(transform: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Inverse of :func:`sim3_from_params`: ``(log_scale [...], phi [..., 3], t [..., 3])``."""
    scale, rot, trans = sim3_decompose(transform)
    return torch.log(scale), so3_log(rot).to(transform.dtype), trans


def pose_summary(transform: Tensor) -> dict:
    """A pose for logs and the wire: scale, rotation angle (deg), translation, and the 7 parameters
    ``[log s, phi (3), t (3)]`` of :func:`sim3_from_params`.  transform: [4, 4]."""
    log_s, phi, t = sim3_to_params(transform.detach().double().cpu())
    return {"scale": math.exp(float(log_s)), "rotation_deg": math.degrees(float(phi.norm())),
            "translation": [float(x) for x in t], "params7": [float(log_s), *map(float, phi), *map(float, t)]}


def sim3_compose(a: Tensor, b: Tensor) -> Tensor:
    """``a o b`` (apply b first).  [..., 4, 4] x [..., 4, 4] -> [..., 4, 4]."""
    return a @ b


def sim3_inverse(transform: Tensor) -> Tensor:
    """Exact inverse ``[[R^T / s, -R^T t / s], [0, 1]]`` (no general matrix inverse)."""
    scale, rot, trans = sim3_decompose(transform)
    rot_inv = rot.transpose(-1, -2) / scale[..., None, None]
    out = torch.zeros_like(transform)
    out[..., :3, :3] = rot_inv
    out[..., :3, 3] = -(rot_inv @ trans[..., :, None]).squeeze(-1)
    out[..., 3, 3] = 1
    return out


def transform_points(transform: Tensor, points: Tensor) -> Tensor:
    """``x -> s R x + t``.  transform: [4, 4], points: [N, 3] -> [N, 3]."""
    return points @ transform[:3, :3].transpose(0, 1) + transform[:3, 3]


def transform_c2w(transform: Tensor, c2w: Tensor) -> Tensor:
    """Move cameras by a similarity: ``[R R_c | s R t_c + t]``.

    transform: [4, 4] (or [..., 4, 4] broadcastable), c2w: [..., 4, 4] -> [..., 4, 4].
    The camera rotation stays orthonormal; only its centre is scaled. Differentiable in both.
    """
    sr = transform[..., :3, :3]
    scale = torch.linalg.det(sr).abs().pow(1.0 / 3.0)
    rot = sr / scale[..., None, None]
    new_rot = rot @ c2w[..., :3, :3]
    new_t = (sr @ c2w[..., :3, 3:4]).squeeze(-1) + transform[..., :3, 3]
    top = torch.cat([new_rot, new_t[..., None]], -1)
    return torch.cat([top, c2w[..., 3:4, :]], -2)


def rotation_angle_deg(rot_a: Tensor, rot_b: Tensor) -> Tensor:
    """Geodesic angle between two rotations in degrees (atan2 form: accurate near 0 and 180)."""
    rel = rot_a.transpose(-1, -2).to(torch.float64) @ rot_b.to(torch.float64)
    return so3_log(rel).norm(dim=-1) * (180.0 / math.pi)


def pose_error(estimate: Tensor, truth: Tensor) -> dict[str, float]:
    """Errors of an estimated similarity against the truth.

    Returns rotation error (deg), translation error (in the units of the target frame) and the
    relative scale error ``|s_est / s_true - 1|``.
    """
    s_e, r_e, t_e = sim3_decompose(estimate.to(torch.float64))
    s_t, r_t, t_t = sim3_decompose(truth.to(torch.float64))
    return {
        "rotation_deg": float(rotation_angle_deg(r_e, r_t)),
        "translation": float((t_e - t_t).norm()),
        "scale_rel": float((s_e / s_t - 1).abs()),
    }


def umeyama(src: Tensor, dst: Tensor, with_scale: bool = True, weights: Tensor | None = None) -> Tensor:
    """Least-squares similarity with ``dst ~ s R src + t`` (Umeyama 1991).

    src, dst: [N, 3] (N >= 3, not collinear); weights: [N] or None -> T [4, 4] (float64).
    """
    src = src.to(torch.float64)
    dst = dst.to(torch.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or src.shape[0] < 3:
        raise ValueError(f"umeyama needs two [N>=3, 3] point sets, got {tuple(src.shape)} and {tuple(dst.shape)}")
    w = torch.ones(src.shape[0], dtype=torch.float64) if weights is None else weights.to(torch.float64)
    w = w / w.sum()
    mu_s = (w[:, None] * src).sum(0)
    mu_d = (w[:, None] * dst).sum(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = (w[:, None] * xd).T @ xs  # [3, 3]
    u, sig, vt = torch.linalg.svd(cov)
    d = torch.ones(3, dtype=torch.float64)
    if torch.linalg.det(u) * torch.linalg.det(vt) < 0:
        d[2] = -1
    rot = u @ torch.diag(d) @ vt
    var_s = (w * (xs * xs).sum(1)).sum()
    scale = (sig * d).sum() / var_s if with_scale else torch.tensor(1.0, dtype=torch.float64)
    out = torch.eye(4, dtype=torch.float64)
    out[:3, :3] = scale * rot
    out[:3, 3] = mu_d - scale * rot @ mu_s
    return out


def umeyama_batched(src: Tensor, dst: Tensor, with_scale: bool = True) -> Tensor:
    """:func:`umeyama` for many small problems at once (RANSAC hypotheses), unweighted.

    src, dst: [B, N, 3] (N >= 3) -> T [B, 4, 4] float64. Degenerate sets (collinear, coincident)
    give a finite but meaningless T (scale 0 when ``src`` has no spread): callers screen them.
    """
    src = src.to(torch.float64)
    dst = dst.to(torch.float64)
    if src.shape != dst.shape or src.ndim != 3 or src.shape[-1] != 3 or src.shape[1] < 3:
        raise ValueError(f"umeyama_batched needs two [B, N>=3, 3] sets, got {tuple(src.shape)} and {tuple(dst.shape)}")
    mu_s, mu_d = src.mean(1, keepdim=True), dst.mean(1, keepdim=True)  # [B, 1, 3]
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.transpose(1, 2) @ xs / src.shape[1]  # [B, 3, 3]
    u, sig, vt = torch.linalg.svd(cov)
    d = torch.ones(src.shape[0], 3, dtype=torch.float64)
    d[:, 2] = torch.sign(torch.linalg.det(u) * torch.linalg.det(vt))
    d[d[:, 2] == 0, 2] = 1
    rot = u @ torch.diag_embed(d) @ vt
    if with_scale:
        var_s = (xs * xs).sum((1, 2)) / src.shape[1]
        scale = (sig * d).sum(1) / var_s.clamp_min(1e-300)
    else:
        scale = torch.ones(src.shape[0], dtype=torch.float64)
    out = torch.eye(4, dtype=torch.float64).repeat(src.shape[0], 1, 1)
    out[:, :3, :3] = scale[:, None, None] * rot
    out[:, :3, 3] = mu_d[:, 0] - (out[:, :3, :3] @ mu_s[:, 0, :, None])[..., 0]
    return out


def look_at(eye: Tensor, target: Tensor, up: Tensor) -> Tensor:
    """OpenGL camera-to-world looking from ``eye`` at ``target``.  [3], [3], [3] -> [4, 4]."""
    eye, target, up = (x.to(torch.float64) for x in (eye, target, up))
    back = eye - target
    back = back / back.norm()
    right = torch.linalg.cross(up, back)
    if right.norm() < 1e-9:
        raise ValueError("look_at: 'up' is parallel to the viewing direction")
    right = right / right.norm()
    cam_up = torch.linalg.cross(back, right)
    out = torch.eye(4, dtype=torch.float64)
    out[:3, 0], out[:3, 1], out[:3, 2], out[:3, 3] = right, cam_up, back, eye
    return out


def random_rotation(generator: torch.Generator, max_angle_deg: float = 180.0) -> Tensor:
    """A rotation with a uniformly random axis and an angle uniform in [0, max_angle_deg]. -> [3, 3]."""
    axis = torch.randn(3, generator=generator, dtype=torch.float64)
    axis = axis / axis.norm()
    angle = torch.rand((), generator=generator, dtype=torch.float64) * math.radians(max_angle_deg)
    return so3_exp(axis * angle)


def box_from_center(center: Tensor, half_size: float) -> Tensor:
    """The similarity mapping the cube ``center +- half_size`` onto [-1, 1]^3: ``(x - c) / h``. -> [4, 4] float64."""
    out = torch.eye(4, dtype=torch.float64) / half_size
    out[3, 3] = 1.0
    out[:3, 3] = -torch.as_tensor(center, dtype=torch.float64) / half_size
    return out


def __getattr__(name: str):
    """``unproject_depth`` lives in :mod:`agent.camera`; it is still reachable here, imported lazily
    because agent.camera builds on this module."""
    if name == "unproject_depth":
        from agent.camera import unproject_depth

        return unproject_depth
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
