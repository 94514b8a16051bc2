"""A finished swarm for other programs: every robot's cameras as one transforms.json, the field's
geometry as a PLY point cloud and a marching-cubes mesh.

Everything is in the shared frame g, the frame the robots' poses map into: the cameras through
each robot's learnt pose (and its refined per-view corrections), the points and the mesh from
the field's box through ``inv(box_from_shared)``. The transforms.json is nerfstudio's and
instant-ngp's layout (``camera_model``, ``w``/``h``, per-frame ``fl_x``/``fl_y``/``cx``/``cy``
when they differ, ``frames[].transform_matrix`` OpenGL c2w), written by the same code as the
robot folders of ``dinerf-agent split`` (``agent.data.folder.write_views_folder``), with the
robots' images beside it.

Geometry comes from the density sampled at the centres of a ``resolution^3`` lattice over the
box (over the box only, also for unbounded fields: the contracted shell is not geometry). The
point cloud keeps the lattice points whose density is above ``density_threshold`` (per box unit
of length, the renderer's unit); the mesh is the iso-surface at that density (PyMCubes). Points
and vertices are coloured by the field's radiance towards the robot's nearest camera.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from agent.config_io import check
from agent.data.folder import write_views_folder
from agent.data.views import Views
from agent.geometry import sim3_inverse, transform_points
from agent.trainer import RobotTrainer

__all__ = ["GeometryConfig", "export_cameras", "sample_density", "Geometry", "export_geometry", "write_ply"]


@dataclass
class GeometryConfig:
    resolution: int = 128  # lattice points per axis over the box
    density_threshold: float = 10.0  # per box unit: ~2% of the box at this density blocks 1/3 of the light
    chunk: int = 65536  # points per field evaluation

    def __post_init__(self) -> None:
        check(self, resolution="in [2, 1024]", density_threshold="> 0", chunk=">= 1")


def export_cameras(robots: dict[int, RobotTrainer], out: Path) -> dict:
    """Every robot's views in the shared frame as ``out/transforms.json`` + ``out/images/``; the json's content.

    Frame names are ``robot<i>_<name>``; each frame also says its ``robot``."""
    images, c2w, intrinsics, names, robot_of = [], [], [], [], []
    sizes = {(t.views.width, t.views.height) for t in robots.values()}
    if len(sizes) > 1:
        raise ValueError(f"the robots' images differ in size {sorted(sizes)}: one transforms.json needs one size")
    for i, trainer in sorted(robots.items()):
        with torch.no_grad():
            c2w.append(trainer.cameras_shared().detach().cpu().float())  # [M, 4, 4] refined, through T_i
            intrinsics.append(trainer.camera_intrinsics().detach().cpu().float())  # [M, 4]
        images.append(trainer.views.images)
        names += [f"robot{i}_{n}" for n in trainer.views.names]
        robot_of += [i] * len(trainer.views)
    views = Views(torch.cat(images), torch.cat(c2w), torch.cat(intrinsics), names)
    return write_views_folder(views, out, frame_extra=[{"robot": i} for i in robot_of],
                              top_extra={"dinerf_frame": "shared"})


def _lattice(resolution: int) -> Tensor:
    """Cell centres of a ``resolution^3`` lattice over [-1, 1]^3, x slowest.  -> [R^3, 3] box coordinates."""
    c = (torch.arange(resolution, dtype=torch.float32) + 0.5) * (2.0 / resolution) - 1.0
    return torch.stack(torch.meshgrid(c, c, c, indexing="ij"), -1).reshape(-1, 3)


@torch.no_grad()
def sample_density(trainer: RobotTrainer, points_box: Tensor, chunk: int = 65536) -> Tensor:
    """The field's density at points in box coordinates.  [N, 3] -> [N] (per box unit, CPU).

    Points in cells the occupancy grid marks empty get 0 without evaluating the field: the
    renderer skips those cells too, so nothing there is ever seen (and a 128^3 lattice costs
    only its occupied fraction)."""
    field, lw = trainer.field, trainer.level_weights()
    out = torch.zeros(len(points_box))
    for start in range(0, len(points_box), chunk):
        grid_x = field.to_grid(points_box[start:start + chunk].to(trainer.device))
        live = trainer.grid.is_occupied(grid_x)
        if bool(live.any()):
            out[start:start + chunk][live.cpu()] = field.density(grid_x[live], lw)[0].cpu()
    return out


@torch.no_grad()
def field_colours(trainer: RobotTrainer, points_box: Tensor, chunk: int = 65536) -> Tensor:
    """The field's radiance at points, seen from the nearest of the robot's cameras.  [N, 3] -> [N, 3] in [0, 1].

    View-dependent colour is only learnt for directions some camera looked along; from elsewhere
    (below the floor, say) it is whatever the MLP extrapolates, so each point takes the direction
    from which the closest camera saw it."""
    field, lw, dev = trainer.field, trainer.level_weights(), trainer.device
    eyes = transform_points(trainer.box_from_shared, trainer.cameras_shared().detach()[:, :3, 3])  # [M, 3] box
    out = []
    for p in points_box.split(chunk):
        p = p.to(dev)
        near = eyes[torch.cdist(p, eyes).argmin(dim=1)]  # [n, 3]
        dirs = torch.nn.functional.normalize(p - near, dim=-1)
        _, geo = field.density(field.to_grid(p), lw)  # [n, G]
        out.append(field.color(geo, dirs).cpu())
    return torch.cat(out) if out else torch.zeros(0, 3)


def _to_shared(trainer: RobotTrainer, points_box: Tensor) -> np.ndarray:
    shared_from_box = sim3_inverse(trainer.box_from_shared.double().cpu())
    return transform_points(shared_from_box, points_box.double()).numpy()


@dataclass
class Geometry:
    points: int  # in the point cloud
    vertices: int  # of the mesh
    faces: int
    max_density: float  # over the lattice, per box unit: what --density can be set below


def export_geometry(trainer: RobotTrainer, out: Path, cfg: GeometryConfig) -> Geometry:
    """``out/points.ply`` (lattice points denser than the threshold) and ``out/mesh.ply`` (the iso-surface
    at the threshold, empty when nothing is that dense), coloured, in the shared frame."""
    import mcubes

    r = cfg.resolution
    lattice = _lattice(r)
    sigma = sample_density(trainer, lattice, cfg.chunk)  # [R^3], x slowest
    keep = lattice[sigma > cfg.density_threshold]
    write_ply(out / "points.ply", _to_shared(trainer, keep), field_colours(trainer, keep, cfg.chunk).numpy())
    grid = sigma.reshape(r, r, r).numpy().astype(np.float64)
    verts, faces = np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    if grid.max() > cfg.density_threshold:
        verts, faces = mcubes.marching_cubes(grid, cfg.density_threshold)
    box = torch.from_numpy((verts + 0.5) * (2.0 / r) - 1.0).float()  # lattice index -> box coordinates
    # density is high inside, so PyMCubes' triangles are counter-clockwise seen from outside (normals out)
    write_ply(out / "mesh.ply", _to_shared(trainer, box), field_colours(trainer, box, cfg.chunk).numpy(), faces)
    return Geometry(len(keep), len(verts), len(faces), float(sigma.max()) if len(sigma) else 0.0)


def write_ply(path: Path, points: np.ndarray, colours: np.ndarray, faces: np.ndarray | None = None) -> None:
    """A binary PLY: vertices [N, 3] with 8-bit colours [N, 3] in [0, 1], and triangles [F, 3] if given."""
    from plyfile import PlyData, PlyElement

    vertex = np.empty(len(points), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"),
                                          ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for k, name in enumerate("xyz"):
        vertex[name] = points[:, k]
    q = np.round(np.clip(colours, 0, 1) * 255).astype(np.uint8).reshape(-1, 3)
    for k, name in enumerate(("red", "green", "blue")):
        vertex[name] = q[:, k]
    elements = [PlyElement.describe(vertex, "vertex")]
    if faces is not None:
        face = np.empty(len(faces), dtype=[("vertex_indices", "i4", (3,))])
        face["vertex_indices"] = np.asarray(faces, dtype=np.int32).reshape(-1, 3)
        elements.append(PlyElement.describe(face, "face"))
    PlyData(elements, text=False).write(str(path))
