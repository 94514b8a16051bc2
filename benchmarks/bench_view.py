"""How long `dinerf-agent view` takes to draw one picture on the CPU: a reload and renders per width.

The model is robot ``--robot``'s checkpoint in a run folder (the layouts of ``agent.runs``);
the camera is the viewer's home view (out between two training cameras, the whole scene in
sight). Printed: seconds to rebuild the model from its checkpoint (what each new round costs the
viewer), and the median of ``--repeats`` renders at each width, with 1 torch thread as `view` uses.

    .venv/bin/python benchmarks/bench_view.py runs/swarm1 --widths 48,64,128,160
    PYTHONPATH=. .venv/bin/python benchmarks/bench_view.py --train /tmp/bench-view   # the viewer test's swarm
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from agent.runs import open_run
from agent.viewer.scene import home_view, render_at_camera
from agent.viewer.source import RobotModel


def look_at_c2w(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """OpenGL c2w [4, 4] at ``eye`` looking at ``target``."""
    back = (eye - target) / np.linalg.norm(eye - target)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([right, np.cross(back, right), back], axis=1)
    c2w[:3, 3] = eye
    return c2w


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir", type=Path, nargs="?")
    ap.add_argument("--data", type=Path)
    ap.add_argument("--robot", type=int)
    ap.add_argument("--widths", default="48,64,128,160")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--train", type=Path, help="First train the viewer test's swarm (2 robots) in this new folder "
                    "and measure on it (run_dir and --data are then ignored)")
    args = ap.parse_args()
    if args.train:
        from tests.viewer.test_view_browser import tiny_swarm

        swarm = tiny_swarm(args.train)
        swarm.start_all()
        swarm.wait_all()
        args.run_dir = swarm.root / "run"  # its run dirs record their data folders
    torch.set_num_threads(1)
    sources = open_run(args.run_dir, args.data, pending=True).robots
    model = RobotModel(sources[args.robot if args.robot is not None else min(sources)])
    model.refresh()  # views loaded once
    model._stamp = None  # noqa: SLF001 - measure a reload as a new round makes it
    t0 = time.perf_counter()
    assert model.refresh(), model.error
    print(f"reload of robot {model.source.robot_id}'s round {model.round}: {time.perf_counter() - t0:.2f} s")
    home = home_view(model.trainer)
    c2w = look_at_c2w(np.array(home.position), np.array(home.look_at), np.array(home.up))
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    for width in map(int, args.widths.split(",")):
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            image = render_at_camera(model.trainer, c2w, home.fov_y, 4 / 3, width)
            times.append(time.perf_counter() - t0)
        print(f"{image.shape[1]} x {image.shape[0]} px: {statistics.median(times):.3f} s median of {args.repeats}")


if __name__ == "__main__":
    main()
