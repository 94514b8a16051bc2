"""Writing a split: robot folders, ``eval/``, ``truth.json``, ``split.json`` and ``scene.json``."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

from agent.data.folder import matrix_to_list, write_json, write_views_folder
from agent.data.split.core import SplitResult
from agent.data.views import DataError
from agent.geometry import sim3_decompose

__all__ = ["write_split", "robot_folder"]


def robot_folder(split_dir: str | Path, robot_id: int) -> Path:
    """Robot ``robot_id``'s views in a split written by :func:`write_split`."""
    return Path(split_dir) / f"robot{robot_id}"


def _owned_outputs(out: Path) -> list[Path]:
    return sorted(out.glob("robot*")) + [out / n for n in ("eval", "truth.json", "split.json", "scene.json")]


def write_split(result: SplitResult, out: str | Path, *, overwrite: bool = False) -> Path:
    """Write robot folders, ``eval/``, ``truth.json``, ``split.json`` and ``scene.json`` under ``out``.

    An existing non-empty ``out`` is refused unless ``overwrite``, which removes only what a
    split writes (``robot*/``, ``eval/`` and the three json files) so that no stale robot of an
    earlier split with more robots survives.
    """
    out = Path(out)
    _prepare_output(out, overwrite)
    _write_view_folders(result, out)
    write_json(out / "truth.json", _truth(result))
    write_json(out / "split.json", _split_record(result))
    write_json(out / "scene.json", _scene(result))
    return out


def _prepare_output(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise DataError(f"{out}: exists and is not a folder")
    if out.exists() and any(out.iterdir()):
        if not overwrite:
            raise DataError(f"{out}: folder is not empty; choose a new --out or pass --force to replace a previous split")
        for p in _owned_outputs(out):
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()
    out.mkdir(parents=True, exist_ok=True)


def _write_view_folders(result: SplitResult, out: Path) -> None:
    """``robot<id>/`` (local frame; images only without poses) and ``eval/`` (world frame)."""
    cfg = result.config
    for rid, rob in result.robots.items():
        write_views_folder(
            rob.views,
            robot_folder(out, rid),
            write_poses=not cfg.images_only,
            top_extra={
                "dinerf": {
                    "robot_id": rid,
                    "frame": "local",
                    "depth_prior": cfg.depth_prior,
                    "depth_sparse": bool(rob.views.meta.get("depth_sparse", False)) and rob.views.depth is not None,
                }
            },
        )
        if cfg.calibrated_cameras:  # the camera's calibration, not a pose: what a robot knows of its camera
            from agent.data.sfm import write_camera_file

            write_camera_file(robot_folder(out, rid), float(rob.views.intrinsics[:, 0].median()), rob.views.width)
    if len(result.eval_indices):
        write_views_folder(
            result.eval_views,
            out / "eval",
            frame_extra=[{"seen_by": s} for s in result.seen_by],
            top_extra={
                "scene_box_world": {"center": result.box_center_world.tolist(), "half_size": result.box_half_size},
                "dinerf": {"frame": "world", "test_every": cfg.test_every},
            },
        )


def _truth(result: SplitResult) -> dict:
    """``truth.json``: what only the evaluation may read."""
    cfg = result.config
    t_shared = result.T_shared_from_local
    truth = {
        "note": "Evaluation only: the agents never read this file.",
        "reference_id": result.reference_id,
        "frame": cfg.frame,
        "shared_frame": f"local frame of robot {result.reference_id}",
        "scene_box_world": {"center": result.box_center_world.tolist(), "half_size": result.box_half_size},
        "robots": {},
    }
    if cfg.images_only:
        # A robot's local frame will be its own SfM's, unknown here: no T_world_from_local, but the
        # true world cameras of its views, to which the evaluation aligns its SfM cameras.
        truth["images_only"] = True
        truth["shared_frame"] = (f"the SfM frame of robot {result.reference_id}, made at run time; the evaluation "
                                 "calibrates every robot's SfM frame on cameras_world")
    for rid, rob in result.robots.items():
        entry: dict = {}
        if cfg.images_only:
            entry["cameras_world"] = {n: matrix_to_list(m) for n, m in zip(rob.views.names, rob.cameras_world)}
        else:
            entry = {
                "T_world_from_local": matrix_to_list(rob.T_world_from_local),
                "T_shared_from_local": matrix_to_list(t_shared[rid]),
                "scale": float(sim3_decompose(rob.T_world_from_local)[0]),
            }
        if rob.depth_affine is not None:
            entry["depth_affine"] = {
                "definition": "prior = a * true_local_z_depth + b (where the true depth is known)",
                "per_view": {n: [float(a), float(b)] for n, (a, b) in zip(rob.views.names, rob.depth_affine)},
            }
        truth["robots"][str(rid)] = entry
    return truth


def _split_record(result: SplitResult) -> dict:
    """``split.json``: how the split was made and what each robot got."""
    cfg = result.config
    return {
        "source": result.source,
        "config": dataclasses.asdict(cfg),
        "center": result.center.tolist(),
        "up": result.up.tolist(),
        "layout": result.layout,
        "sector_margin_deg": result.margin_deg,
        "segment_margin_views": result.margin_views,
        "target_overlap": cfg.overlap,
        "mean_overlap": result.mean_overlap,
        "robots": {
            str(rid): {
                "count": len(rob.indices),
                "views": rob.views.names,
                "sector_deg": list(rob.sector_deg),
                "overlap": rob.overlap,
            }
            for rid, rob in result.robots.items()
        },
        "eval": {
            "test_every": cfg.test_every,
            "views": result.eval_views.names,
            "seen_by": result.seen_by,
        },
        "notes": result.notes,
    }


def _scene(result: SplitResult) -> dict:
    """``scene.json``: the shared frame's field box and what the robots' images are, which every robot reads."""
    views = result.robots[result.reference_id].views
    capture = {"unbounded": views.shows_surroundings, "width": views.width}  # agent.defaults.Capture
    if result.config.images_only:
        return {
            "reference_id": result.reference_id,
            "capture": capture,
            "box_from_shared": None,
            "description": (
                "The robots have images only, so the shared frame g is the reference robot's own SfM frame, "
                "unknown when the data was split: the reference derives box_from_shared (g -> the normalised "
                "field box [-1, 1]^3) from its own SfM at start and shares it with its peers."
            ),
        }
    return {
        "reference_id": result.reference_id,
        "capture": capture,
        "box_from_shared": matrix_to_list(result.box_from_shared),
        "description": (
            "box_from_shared maps the shared frame g (the local frame of the reference robot) into the "
            "normalised field box [-1, 1]^3; robot i maps its local points with box_from_shared @ T_i."
        ),
    }
