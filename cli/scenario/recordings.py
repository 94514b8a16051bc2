"""A scenario whose robots record ROS 2 bags, as a team's own robots would, and run from them.

After the split, each robot's views become a rosbag2 (:func:`agent.data.ros.record.record_bag`)
in an odometry frame of its own (a random rigid offset of the split's frame), with its camera
on a tilted mount, ``/tf`` between the images and a lens in ``CameraInfo``. The robot folders then
hold only the bag and ``tls/``: the robots start from ``init``'s kind of swarm file (local frames,
no scene file: the reference derives the field box), exactly as robots with their own recordings.

``truth.json`` and ``scene.json`` are rewritten for the evaluation only: each robot's local frame
is now its odometry frame, so the report's pose errors are against the offsets applied here.
The summary keeps which view each robot recorded at which stamp: with ``record.replay`` the report
tells when two robots' keyframes first showed the same place (:mod:`cli.scenario.meeting`).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import torch

from agent.data.folder import matrix_to_list, write_json
from agent.data.loaders import load_views
from agent.data.ros.record import RecordConfig, bag_storage_file, record_bag
from agent.geometry import random_rotation

__all__ = ["record_robots", "recording_of"]


def recording_of(robot_dir: Path) -> Path:
    """The bag a robot folder of a recording scenario holds: its ``.mcap`` file, or its ``bag/`` folder."""
    files = sorted(robot_dir.glob("*.mcap"))
    if files:
        return files[0]
    return robot_dir / "bag"


def _odometry_offset(rng: torch.Generator, translation: float) -> np.ndarray:
    """T_odom_from_local [4, 4]: a random rotation and a translation of length ``translation``."""
    m = np.eye(4)
    m[:3, :3] = random_rotation(rng).double().numpy()
    direction = torch.randn(3, generator=rng, dtype=torch.float64).numpy()
    m[:3, 3] = translation * direction / np.linalg.norm(direction)
    return m


def record_robots(spec, data: Path, echo=print) -> dict:
    """Turn the split in ``data`` into one bag per robot (see the module docstring); returns a summary."""
    rec = spec.record
    rng = torch.Generator().manual_seed(rec.seed)
    truth = json.loads((data / "truth.json").read_text())
    scene = json.loads((data / "scene.json").read_text())
    ref = int(truth["reference_id"])
    offsets: dict[int, np.ndarray] = {}
    summary = {}
    for k, i in enumerate(spec.ids):
        folder = data / f"robot{i}"
        views = load_views(folder, load_depth=False)  # pinhole, in the split's local frame of robot i
        if i in rec.reverse:  # its path runs the other way: it meets a forward neighbour only at the end
            views = views.subset(list(range(len(views)))[::-1])
        offsets[i] = _odometry_offset(rng, rec.offset_translation)
        storage = rec.storage[k % len(rec.storage)]
        cfg = RecordConfig(storage=storage, image_rate_hz=rec.image_rate_hz, tf_rate_factor=rec.tf_rate_factor,
                           encoding=rec.encoding, mount_tilt_deg=rec.mount_tilt_deg, k1=rec.k1,
                           start_s=1_700_000_000.0 + 1000.0 * i)
        for p in ("images", "depth", "transforms.json", "camera.json"):  # the robot keeps only its bag and tls/
            target = folder / p
            shutil.rmtree(target) if target.is_dir() else target.unlink(missing_ok=True)
        written = record_bag(views, folder / "bag", offsets[i], cfg)
        if storage == "mcap":  # a lone .mcap file is a bag too: `up --data robot1.mcap`
            bag_storage_file(folder / "bag").rename(folder / f"robot{i}.mcap")
            shutil.rmtree(folder / "bag")
        summary[i] = {"storage": storage, "images": written["images"], "tf": written["tf"],
                      "recording": str(recording_of(folder).relative_to(data)),
                      "views": list(views.names), "stamps_s": written["stamps_s"]}  # which view is at which stamp
        echo(f"[scenario] robot {i}: {written['images']} images and {written['tf']} transforms recorded as "
             f"{storage} ({summary[i]['recording']})")
    world_from_odom = {i: np.array(truth["robots"][str(i)]["T_world_from_local"]) @ np.linalg.inv(offsets[i])
                       for i in spec.ids}
    for i in spec.ids:
        entry = truth["robots"][str(i)]
        entry["T_world_from_local"] = matrix_to_list(world_from_odom[i])
        entry["T_shared_from_local"] = matrix_to_list(np.linalg.inv(world_from_odom[ref]) @ world_from_odom[i])
        entry["T_odom_from_split_frame"] = matrix_to_list(offsets[i])
    truth["shared_frame"] = f"the odometry frame of robot {ref} (its bag's fixed frame)"
    truth["note"] += " Each robot's local frame is the odometry frame of its bag (recorded by the scenario)."
    write_json(data / "truth.json", truth)
    if scene.get("box_from_shared") is not None:  # evaluation only: the robots run without a scene file
        box = np.array(scene["box_from_shared"]) @ np.linalg.inv(offsets[ref])
        scene["box_from_shared"] = matrix_to_list(box)
        scene["description"] = "evaluation only (the robots derive the box themselves): " + scene["description"]
        write_json(data / "scene.json", scene)
    return summary
