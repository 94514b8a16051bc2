"""Online mapping's data path: live-camera latency over Zenoh, and a robot's memory as its keyframes grow.

    flock /tmp/dinerf-heavy.lock python benchmarks/bench_stream.py [--frames 100] [--sizes 100,300,1000]

1. Latency. A Zenoh router on loopback (the robot's rmw_zenohd), a publisher process writing a
   recorded camera (10 Hz, rgb8, /tf at 200 Hz) on rmw_zenoh's keys at its recorded pace, and the
   stream's subscriber (``up --live``), with a small trainer training meanwhile. Per image:
   publish -> decoded message (transport), -> keyframe ready (posed from /tf, chosen; sharpness
   window 1, so a keyframe waits for no later frame; with the default window of 5 it waits ~4
   frames, 400 ms, more), -> admitted by the trainer (written to keyframes/, taken at the next
   step: up to one step later).
2. Memory. One process per size: N keyframes (160x120, a camera circling one place, so the scene
   and its box stay the same size) admitted into a view stream while a small
   trainer trains, then the keyframe summary served again (from a pool spread over them; and, for
   comparison, from every keyframe), against the same N views held in memory as a loaded folder
   is. Peak RSS.
3. Sampling on a growing set (``--sampling``): the procedural object's views arrive in capture
   order, a few per round, while one robot trains; ``recency`` against ``uniform`` at the same
   steps and seed, and all views given at start (offline). PSNR on every held-out view at the
   end, and after each round on the held-out views of the places seen last.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def latency(frames: int, width: int, height: int) -> dict:
    """Publish -> decoded (transport), -> keyframe ready (posed), -> admitted by a trainer that trains meanwhile."""
    import torch

    from agent.data.ros.config import KeyframeConfig, RosBagConfig
    from agent.data.ros.intake import FrameIntake
    from agent.data.stream import StreamConfig, ViewStream
    from agent.geometry import box_from_center
    from agent.swarm import SwarmTrainingConfig, build_robot
    from protocol.ros_camera import RosTopicSubscriber, open_router
    from tests.data.bags import camera_bag
    from tests.protocol.helpers import free_port

    torch.set_num_threads(1)
    tmp = Path(tempfile.mkdtemp(prefix="bench-stream-"))
    bag = camera_bag(tmp / "bag", n=frames, w=width, h=height, tf_dt=0.005, moves=0.5)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router([endpoint])
    intake = FrameIntake(RosBagConfig(keyframes=KeyframeConfig(sharpness_window=1, max_keyframes=0)),
                         "/camera/image_raw", "/camera/camera_info", tf_wait_s=5.0)
    transport, published = [], {}
    lock = threading.Lock()

    def on_message(m) -> None:
        if m.topic == "/camera/image_raw":
            stamp = m.message.header.stamp.sec * 1_000_000_000 + m.message.header.stamp.nanosec
            with lock:
                published[stamp] = m.attachment.source_timestamp_ns
                transport.append((time.time_ns() - m.attachment.source_timestamp_ns) * 1e-6)
        intake.feed(m.topic, m.ros_type, m.message, m.received_ns)

    topics = [("/camera/image_raw", "sensor_msgs/msg/Image"), ("/camera/camera_info", "sensor_msgs/msg/CameraInfo"),
              ("/tf", "tf2_msgs/msg/TFMessage"), ("/tf_static", "tf2_msgs/msg/TFMessage")]
    sub = RosTopicSubscriber([endpoint], topics, on_message).open()
    cmd = [sys.executable, str(ROOT / "tools" / "rmw_zenoh_publish.py"), str(bag), "--connect", endpoint, "--mode",
           "client", "--rate", "1.0", "--match-timeout", "3"]
    publisher = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    stream = ViewStream(StreamConfig(start_keyframes=1), intake, tmp / "keyframes", 64, 0, frames)
    stream.wait_for_start()
    training = SwarmTrainingConfig(rounds=1, steps_per_round=1, own_holdout_every=0, train=_small_field(64))
    box = box_from_center(torch.tensor([0.25 * frames, 0.0, 0.0]), torch.tensor(0.3 * frames + 1))
    setup = build_robot(0, stream.initial_views(), box, training, stream=stream)
    steps, t0 = 0, time.monotonic()
    while publisher.poll() is None:  # the robot trains while its camera streams; each step admits what arrived
        setup.trainer.train(1)
        steps += 1
    train_s = time.monotonic() - t0
    setup.trainer.train(2)
    sub.close()
    router.close()
    if publisher.returncode != 0:
        raise SystemExit(publisher.stderr.read())
    posed = [(f["ready_ns"], f["admitted_ns"], published[f["stamp_ns"]]) for f in stream.store.frames[1:]]
    ready = [(r - p) * 1e-6 for r, _, p in posed]
    admitted = [(a - p) * 1e-6 for _, a, p in posed]
    return {"frames": frames, "size": f"{width}x{height}", "received": len(transport), "keyframes": len(posed),
            "transport_median_ms": statistics.median(transport), "transport_p95_ms": _p95(transport),
            "ready_median_ms": statistics.median(ready), "ready_p95_ms": _p95(ready),
            "to_trainer_median_ms": statistics.median(admitted), "to_trainer_p95_ms": _p95(admitted),
            "step_ms": 1000 * train_s / max(steps, 1)}


def _small_field(width: int):
    """The field and sampler agent.defaults fits to an RGB capture of this width (the quickstart's field)."""
    from agent.defaults import Capture
    from cli.options import load_train_config

    return load_train_config(None, [], 1000, capture=Capture(unbounded=True, width=width))


def _p95(xs: list[float]) -> float:
    return sorted(xs)[min(len(xs) - 1, int(0.95 * len(xs)))]


def memory_child(n: int, mode: str, width: int, height: int, steps_every: int) -> dict:
    """Runs in its own process: N keyframes through a stream (or held as a folder is), training meanwhile."""
    import numpy as np
    import torch

    from agent.align.config import AlignConfig
    from agent.align.summary import summarise
    from agent.data.ros.intake import Keyframe
    from agent.data.stream import StreamConfig, ViewStream
    from agent.data.views import Views
    from agent.geometry import box_from_center, look_at
    from agent.swarm import SwarmTrainingConfig, build_robot

    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    k = (width * 0.8, width * 0.8, width / 2, height / 2)

    def keyframe(i: int) -> Keyframe:
        # a robot that patrols one place: the keyframes grow, the scene and its box do not (a box that
        # grew with them would measure a larger scene's training step, not the data held)
        a = 2 * np.pi * i / 97
        eye = torch.tensor([2 * np.cos(a), 2 * np.sin(a), 0.5 + 0.2 * np.sin(7 * a)])
        c2w = look_at(eye, torch.zeros(3), torch.tensor([0.0, 0.0, 1.0])).numpy()
        return Keyframe(f"frame_{i:06d}", rng.random((height, width, 3), dtype=np.float32), c2w, k, i, time.time_ns())

    training = SwarmTrainingConfig(rounds=1, steps_per_round=1, own_holdout_every=0, train=_small_field(width))
    box = box_from_center(torch.zeros(3), torch.tensor(3.0))
    t0 = time.monotonic()
    if mode.startswith("stream"):
        with tempfile.TemporaryDirectory() as tmp:
            stream = ViewStream(StreamConfig(), _NoIntake(), Path(tmp) / "keyframes", None, 0, n)
            stream._admit([keyframe(i) for i in range(4)])
            setup = build_robot(0, stream.initial_views(), box, training, stream=stream)
            setup.trainer.train(2)
            for i in range(4, n):
                stream._admit([keyframe(i)])
                if i % steps_every == 0:
                    setup.trainer.train(2)
            # the keyframe summary served again as they grow, from the camera's full-size images: of a
            # spread pool (agent.bootstrap.refresh_summary), or of every keyframe (before the pool)
            summarise(stream.initial_views(None) if mode == "stream-all" else
                      stream.spread_views(AlignConfig().summary_pool, None))
    else:  # every view in memory, as a folder loaded at start
        kfs = [keyframe(i) for i in range(n)]
        views = Views(torch.from_numpy(np.stack([kf.image for kf in kfs])),
                      torch.from_numpy(np.stack([kf.c2w for kf in kfs])).float(),
                      torch.tensor([k] * n, dtype=torch.float32), [kf.name for kf in kfs])
        del kfs
        setup = build_robot(0, views, box, training)
        setup.trainer.train(2)
        for i in range(4, n):
            if i % steps_every == 0:
                setup.trainer.train(2)
    return {"keyframes": n, "mode": mode, "peak_rss_mb": _peak_rss_mb(), "seconds": time.monotonic() - t0,
            "samples_per_ray": setup.trainer.samples_per_ray}


def _peak_rss_mb() -> float:
    """This process's own peak RSS (VmHWM). Not getrusage's ru_maxrss: Linux keeps that across fork and
    exec, so a child spawned by a parent that had trained reported the parent's peak (1451 MB for
    every size, measured that way)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def sampling(rounds: int, steps: int, views_n: int, width: int, overrides: list[str]) -> None:
    import torch

    from agent.data.loaders import load_views
    from agent.data.capture import estimate_scene_box
    from agent.data.ros.intake import Keyframe
    from agent.data.stream import StreamConfig, ViewStream
    from agent.defaults import Capture
    from agent.geometry import box_from_center
    from agent.swarm import SwarmTrainingConfig, build_robot, own_holdout_split
    from cli.options import load_train_config

    torch.set_num_threads(2)
    views = load_views(f"procedural:views={views_n},width={width}")
    train_views, test = own_holdout_split(views, 8)
    centre, half, _ = estimate_scene_box(views, True, cameras_elsewhere=True)
    box = box_from_center(centre, half)  # from config: the box is not what is compared here
    tcfg = load_train_config(None, overrides, rounds * steps, capture=Capture(unbounded=True, width=width))
    training = SwarmTrainingConfig(rounds=rounds, steps_per_round=steps, own_holdout_every=0, train=tcfg)
    per_round = -(-len(train_views) // rounds)
    n_test_recent = max(1, len(test) // rounds)

    def keyframe(i: int) -> Keyframe:
        return Keyframe(f"frame_{i:06d}", train_views.images[i].numpy(), train_views.c2w[i].double().numpy(),
                        tuple(float(x) for x in train_views.intrinsics[i]), i, time.time_ns())

    def psnr(trainer, sel) -> float:
        return statistics.mean(trainer.evaluate(test.subset(sel), with_ssim=False)["psnr"])

    results = {}
    for mode in ("recency", "uniform", "offline"):
        t0 = time.monotonic()
        curve = []
        if mode == "offline":
            setup = build_robot(0, train_views, box, training)
        with tempfile.TemporaryDirectory() as tmp:
            if mode != "offline":
                stream = ViewStream(StreamConfig(sampling=mode, working_set=64), _NoIntake(), Path(tmp) / "kf",
                                    None, 0, len(train_views))
                stream._admit([keyframe(i) for i in range(per_round)])
                setup = build_robot(0, stream.initial_views(), box, training, stream=stream)
            for k in range(rounds):
                if mode != "offline" and k:
                    stream._admit([keyframe(i) for i in range(k * per_round, min((k + 1) * per_round,
                                                                                  len(train_views)))])
                setup.trainer.train(steps)
                seen = min((k + 1) * per_round, len(train_views)) / len(train_views)  # fraction of the path so far
                last = int(seen * len(test))
                curve.append(psnr(setup.trainer, list(range(max(0, last - n_test_recent), max(last, 1)))))
            results[mode] = (psnr(setup.trainer, list(range(len(test)))), curve, time.monotonic() - t0)
    print(f"sampling on a growing set: procedural {views_n} views at {width} px, {len(train_views)} training "
          f"keyframes arriving {per_round} per round, {rounds} rounds x {steps} steps, {len(test)} held out")
    for mode, (final, curve, secs) in results.items():
        print(f"  {mode:8s} final PSNR on all held-out {final:5.2f} dB; after each round, on the newest places: "
              + " ".join(f"{x:.1f}" for x in curve) + f"  ({secs:.0f} s)")


class _NoIntake:
    """Keyframes are admitted directly: the memory benchmark measures the store, not the decoding."""

    images, skipped, camera, dropped = 0, {}, None, 0

    def take(self) -> list:
        return []

    def finish(self) -> list:
        return []


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=100, help="images published for the latency (10 Hz; 0: skip it)")
    p.add_argument("--sizes", default="100,300,1000", help="keyframe counts for the memory")
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)
    p.add_argument("--sampling", action="store_true", help="only the sampling comparison (recency, uniform, offline)")
    p.add_argument("--rounds", type=int, default=8)
    p.add_argument("--steps", type=int, default=50)
    p.add_argument("--set", action="append", default=[], help="--sampling: a TrainConfig setting, e.g. "
                   "occupancy.warmup_steps=100000 (the grid never prunes)")
    a = p.parse_args()
    if a.sampling:
        sampling(a.rounds, a.steps, 64, 48, a.set)
        return
    if a.child:
        n, mode = a.child.split(":")
        print(json.dumps(memory_child(int(n), mode, 160, 120, 50)))
        return
    print("live camera over Zenoh, loopback, 10 Hz (median / p95 ms):")
    for w, h in ((320, 240), (640, 480)) if a.frames else ():
        r = latency(a.frames, w, h)
        print(f"  {r['size']}: {r['received']}/{r['frames']} images received, publish -> decoded "
              f"{r['transport_median_ms']:.1f} / {r['transport_p95_ms']:.1f}, -> posed keyframe ready "
              f"{r['ready_median_ms']:.1f} / {r['ready_p95_ms']:.1f}, -> admitted by the trainer "
              f"{r['to_trainer_median_ms']:.1f} / {r['to_trainer_p95_ms']:.1f} ({r['keyframes']} keyframes; "
              f"training meanwhile at {r['step_ms']:.0f} ms a step)")
    print("peak RSS as keyframes grow (160x120, training meanwhile):")
    for n in [int(x) for x in a.sizes.split(",")]:
        row = {}
        for mode in ("stream", "stream-all", "in-memory"):
            out = subprocess.run([sys.executable, __file__, "--child", f"{n}:{mode}"], capture_output=True, text=True,
                                 timeout=3600)
            if out.returncode != 0:
                raise SystemExit(out.stderr)
            row[mode] = json.loads(out.stdout.strip().splitlines()[-1])
        print(f"  {n:5d} keyframes: stream {row['stream']['peak_rss_mb']:.0f} MB ({row['stream']['seconds']:.0f} s; "
              f"summarising every keyframe instead of a pool: {row['stream-all']['peak_rss_mb']:.0f} MB), "
              f"all in memory {row['in-memory']['peak_rss_mb']:.0f} MB ({row['in-memory']['seconds']:.0f} s); samples "
              f"a ray at the end {row['stream']['samples_per_ray']:.0f} / {row['in-memory']['samples_per_ray']:.0f}")


if __name__ == "__main__":
    main()
