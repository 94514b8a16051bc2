"""The viewer's geometry and pictures, free of any web server: frustums, the free camera, the panel.

The viewer's world is the shared frame g. Browser cameras (viser's) are OpenCV-style: the
rotation ``wxyz`` maps camera to world, the camera looks down +Z with +Y down; ours are OpenGL
(agent.camera): the two differ by a flip of the camera's Y and Z axes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from agent.camera import OPENCV_FROM_OPENGL
from agent.data.capture import mean_up
from agent.geometry import sim3_inverse
from agent.trainer import RobotTrainer
from agent.viewer.source import RobotStatus

__all__ = ["PALETTE", "colour_of", "Frustum", "frustums", "quat_from_matrix", "matrix_from_quat",
           "c2w_from_browser", "HomeView", "home_view", "render_at_camera", "RenderScheduler", "panel_markdown"]

# Saturated and far from the white background and from each other.
PALETTE = [(230, 25, 75), (0, 130, 200), (60, 180, 75), (245, 130, 48), (145, 30, 180), (240, 50, 230),
           (70, 200, 200), (128, 128, 0)]


def colour_of(robot_id: int) -> tuple[int, int, int]:
    """Robot 1 red, 2 blue, 3 green ...: by id, so a robot keeps its colour when others appear."""
    return PALETTE[(robot_id - 1) % len(PALETTE)]


def quat_from_matrix(rot: np.ndarray) -> np.ndarray:
    """A rotation [3, 3] -> unit quaternion [4] (w, x, y, z), w >= 0 (Shepperd's method)."""
    m = np.asarray(rot, dtype=np.float64)
    tr = np.trace(m)
    cands = [tr, m[0, 0], m[1, 1], m[2, 2]]
    k = int(np.argmax(cands))
    if k == 0:
        s = 2.0 * math.sqrt(max(1.0 + tr, 1e-12))
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    else:
        i, j, l = k - 1, k % 3, (k + 1) % 3
        s = 2.0 * math.sqrt(max(1.0 + m[i, i] - m[j, j] - m[l, l], 1e-12))
        q = [0.0] * 4
        q[0] = (m[l, j] - m[j, l]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + l] = (m[l, i] + m[i, l]) / s
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def matrix_from_quat(wxyz: np.ndarray) -> np.ndarray:
    """A quaternion [4] (w, x, y, z) -> rotation [3, 3]."""
    w, x, y, z = np.asarray(wxyz, dtype=np.float64) / np.linalg.norm(wxyz)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def c2w_from_browser(wxyz: np.ndarray, position: np.ndarray) -> np.ndarray:
    """The browser camera (OpenCV rotation, centre) -> our OpenGL c2w [4, 4] in frame g."""
    c2w = np.eye(4)
    c2w[:3, :3] = matrix_from_quat(wxyz)
    c2w[:3, 3] = position
    return c2w @ OPENCV_FROM_OPENGL


@dataclass(frozen=True)
class Frustum:
    """One training camera, placed as the browser draws it."""

    name: str  # scene node path: /cameras/robot<i>/<k>
    wxyz: tuple[float, float, float, float]  # OpenCV camera -> frame g
    position: tuple[float, float, float]
    fov_y: float  # radians
    aspect: float  # width / height
    colour: tuple[int, int, int]


@torch.no_grad()
def frustums(trainer: RobotTrainer, robot_id: int, colour: tuple[int, int, int]) -> list[Frustum]:
    """The robot's cameras in frame g, as it currently places them (pose T_i and its refinements)."""
    c2w = trainer.cameras_shared().double().cpu().numpy() @ OPENCV_FROM_OPENGL  # [M, 4, 4] OpenCV
    fy = trainer.camera_intrinsics()[:, 1].double().cpu().numpy()  # [M]
    w, h = trainer.views.width, trainer.views.height
    return [Frustum(f"/cameras/robot{robot_id}/{k}", tuple(quat_from_matrix(c[:3, :3])), tuple(c[:3, 3]),
                    2.0 * math.atan(h / (2.0 * f)), w / h, colour) for k, (c, f) in enumerate(zip(c2w, fy))]


@dataclass(frozen=True)
class HomeView:
    """Where the browser's camera starts: out between two training cameras, looking at the field box's centre."""

    position: tuple[float, float, float]
    look_at: tuple[float, float, float]
    up: tuple[float, float, float]
    fov_y: float
    frustum_scale: float  # drawn frustum size: a small fraction of the cameras' distance


@torch.no_grad()
def home_view(trainer: RobotTrainer) -> HomeView:
    c2w = trainer.cameras_shared().double().cpu()  # [M, 4, 4]
    centre = sim3_inverse(trainer.box_from_shared.double().cpu())[:3, 3]  # box origin in frame g
    offsets = c2w[:, :3, 3] - centre  # [M, 3]
    dist = float(offsets.norm(dim=-1).median())
    fy = float(trainer.camera_intrinsics()[0, 1])
    units = offsets / offsets.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    between = units[0] + units[int((units[1:] @ units[0]).argmax()) + 1] if len(units) > 1 else units[0]
    if between.norm() < 1e-6:  # two cameras facing each other across the scene
        between = units[0]
    eye = centre + 1.6 * dist * between / between.norm()  # between two cameras, further out: no frustum in the way
    return HomeView(tuple(eye.tolist()), tuple(centre.tolist()), tuple(mean_up(c2w).tolist()),
                    2.0 * math.atan(trainer.views.height / (2.0 * fy)), 0.06 * dist)


@torch.no_grad()
def render_at_camera(trainer: RobotTrainer, c2w: np.ndarray, fov_y: float, aspect: float, width: int) -> np.ndarray:
    """The field seen from an OpenGL camera c2w [4, 4] in frame g -> RGB uint8 [H, W, 3], H = W / aspect.

    Square pixels; the colour transform of the nearest training view when appearance is learnt."""
    height = max(1, round(width / max(aspect, 1e-3)))
    fy = 0.5 * height / math.tan(0.5 * fov_y)
    intrinsics = torch.tensor([fy, fy, 0.5 * width, 0.5 * height])
    pose = torch.as_tensor(c2w, dtype=torch.float32)
    code = trainer.appearance_for(pose[None])
    out = trainer.render(pose, intrinsics, width, height, appearance=None if code is None else code[0])
    return (out["rgb"].clamp(0, 1) * 255).round().to(torch.uint8).cpu().numpy()


class RenderScheduler:
    """What to render next for one browser: small while the camera moves, sharp once it is still.

    A CPU renders about 10^4-10^5 rays a second, so a moving camera gets ``moving_width`` pixels
    across and, after ``settle_s`` without a move, one render at ``still_width``. A new model
    (a checkpoint reloaded) is rendered again at the current camera.
    """

    def __init__(self, moving_width: int, still_width: int, settle_s: float = 0.3) -> None:
        self.moving_width, self.still_width = min(moving_width, still_width), max(moving_width, still_width)
        self.settle_s = settle_s
        self._camera = self._model = 0
        self._moved_at = -math.inf
        self._shown: tuple[int, int, int] | None = None  # (camera, model, width) of the picture on screen

    def camera_moved(self, now: float) -> None:
        self._camera += 1
        self._moved_at = now

    def model_changed(self) -> None:
        self._model += 1

    def next(self, now: float) -> tuple[int, tuple[int, int, int]] | None:
        """(width, token) of the render to make now, or None; pass the token to :meth:`shown`."""
        still = now - self._moved_at >= self.settle_s
        width = self.still_width if still else self.moving_width
        if self._shown is not None:
            camera, model, shown_width = self._shown
            if (camera, model) == (self._camera, self._model) and shown_width >= width:
                return None
        return width, (self._camera, self._model, width)

    def shown(self, token: tuple[int, int, int]) -> None:
        self._shown = token


def _cell(value: float | int | None, fmt: str = "{}") -> str:
    return "-" if value is None else fmt.format(value)


def panel_markdown(statuses: list[RobotStatus], shown: int | None, shown_round: int | None,
                   colours: dict[int, tuple[int, int, int]], errors: dict[int, str]) -> str:
    """The panel: one row per robot (round, PSNR, frame), which model is drawn, and what failed."""
    lines = ["| robot | round | PSNR (dB) | frame | last event |", "|---|---|---|---|---|"]
    for s in statuses:
        r, g, b = colours[s.robot_id]
        name = f"<span style='color:rgb({r},{g},{b})'>&#9632;</span> {s.robot_id}"
        psnr = "-" if s.psnr is None else f"{s.psnr:.2f} (round {s.psnr_round})"
        round_text = _cell(s.round) + (" done" if s.done else "")
        lines.append(f"| {name} | {round_text} | {psnr} | {s.frame} | {s.last_event or '-'} |")
    lines.append("")
    lines.append(f"Field drawn: robot {shown}'s model, round {shown_round}." if shown_round is not None
                 else f"Field drawn: robot {shown}'s model (no checkpoint yet).")
    for rid, text in sorted(errors.items()):
        lines.append(f"\n**robot {rid}**: {text}")
    return "\n".join(lines)
