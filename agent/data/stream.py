"""The views a robot has now: keyframes admitted while it trains, on disk, a bounded few in memory.

A robot that maps does not hand over a finished folder: its keyframes arrive while it moves
(:mod:`agent.data.ros.intake`: a bag replayed at its recorded pace, or the live camera over
Zenoh). :class:`ViewStream` owns them:

- **Admission**, before every training step (a keyframe is trained from the step after it
  arrives) and every round. Each keyframe is written to the run folder's ``keyframes/`` (a nerfstudio
  folder, as the bag loader writes, so evaluation, export and the viewer read it) and takes the
  trainer's next row (:meth:`agent.trainer.RobotTrainer.admit_views`, which opens the occupancy
  grid where it looks). Every ``own_holdout_every``-th keyframe is held out instead, by the rule
  of :func:`agent.swarm.own_holdout_split`, so the folder read later splits the same way. Past
  ``capacity`` training keyframes (the trainer's per-view state is allocated once, for
  checkpoints to keep their shapes) new ones are dropped and counted.
- **Memory.** Only a working set of ``working_set`` keyframes is held, at the training width:
  the newest ``recent_keyframes`` always, the rest drawn from the older ones and swapped a few at
  a time every ``refresh_every`` steps, so every keyframe comes back in turn.
- **Sampling** (:meth:`sample`, the trainer's pixel source): ``recency`` draws a
  ``recent_fraction`` of each step's rays from the newest keyframes and the rest uniformly over
  the working set, meant to learn new places fast without forgetting old ones; ``uniform`` (the
  default: recency was below it in both runs measured) draws every ray alike.
- **The field box** is fixed before the first step (it is part of the model's signature): from
  the first keyframes, or from the scene file. A robot that drives out of it still trains: an
  unbounded field squeezes the outside into its shell (coarser there, ~|x|^2 per cell); a
  bounded field cannot see outside it at all. The round record's ``coverage`` says how far the
  cameras have gone, so an operator sees it happen.

A folder or bag loaded at start is not a stream: the trainer samples its views exactly as before.
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from agent.camera import spread_views
from agent.config_io import InvalidValue, check
from agent.data.folder import matrix_to_list, write_png
from agent.data.images import read_image, resize_image, target_size
from agent.data.ros.intake import FrameIntake, Keyframe
from agent.data.views import DataError, Views
from agent.files import atomic_write_text

__all__ = ["StreamConfig", "ViewStream", "StreamRound"]


@dataclass
class StreamConfig:
    """``[data.stream]``: a robot's views as they arrive (``up --replay`` or ``--live``)."""

    capacity: int = 0  # training keyframes the trainer holds state for; 0: data.ros.keyframes.max_keyframes
    start_keyframes: int = 3  # the first round waits for this many keyframes (the box and summary come from them)
    start_timeout_s: float = 300.0  # ... at most this long
    sampling: Literal["recency", "uniform"] = "uniform"  # recency was below uniform in both runs measured (results.md)
    recent_keyframes: int = 8  # the newest this many keyframes ...
    recent_fraction: float = 0.5  # ... get this fraction of each step's rays (recency)
    working_set: int = 64  # keyframes held in memory at the training width
    refresh_every: int = 16  # steps between swaps of part of the working set's older keyframes
    tf_wait_s: float = 1.0  # an image waits this long for /tf to cover its stamp
    domain_id: int = 0  # ROS_DOMAIN_ID of the live topics
    eval_views: int = 8  # held-out keyframes scored when the round is evaluated (evenly spread)

    def __post_init__(self) -> None:
        check(self, capacity=">= 0", start_keyframes=">= 1", start_timeout_s="> 0", recent_keyframes=">= 1",
              recent_fraction="in [0, 1]", working_set=">= 2", refresh_every=">= 1", tf_wait_s=">= 0",
              domain_id="in [0, 232]", eval_views=">= 1")
        if self.recent_keyframes >= self.working_set:
            raise InvalidValue("recent_keyframes", f"must be below working_set ({self.working_set}), got "
                               f"{self.recent_keyframes}")


@dataclass
class StreamRound:
    """What one round saw of the stream (the round's record, log line and status)."""

    admitted: int  # keyframes admitted for training this round
    held_out: int  # ... held out this round
    dropped: int  # frames that became no keyframe this round: no pose, or over capacity
    keyframes: int  # training keyframes so far
    held_out_total: int
    dropped_total: int
    newest_age_s: float | None  # since the newest keyframe reached the robot
    coverage: list[float] | None  # extent of the camera centres so far, per axis (local frame units)


class _Store:
    """``keyframes/`` on disk: images/<name>.png at the camera's size and transforms.json."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        (folder / "images").mkdir(parents=True, exist_ok=True)
        self.frames: list[dict] = []
        self.camera: dict = {}
        path = folder / "transforms.json"
        if (folder / "bag.json").is_file():
            raise DataError(f"{folder}: keyframes of a bag loaded at start, not of a stream (use another --run-dir, "
                            "or move keyframes/ away)")
        if path.is_file():  # a restart: the keyframes of this run stay its keyframes
            try:
                doc = json.loads(path.read_text())
                self.frames, self.camera = list(doc["frames"]), {k: doc[k] for k in ("w", "h", "fl_x", "fl_y", "cx", "cy")}
            except (ValueError, KeyError, TypeError):
                raise DataError(f"{path}: not a keyframe index this robot wrote (move keyframes/ away to start over)") from None

    def add(self, kf: Keyframe, held_out: bool) -> None:
        write_png(self.folder / "images" / f"{kf.name}.png", kf.image)
        if not self.camera:
            fx, fy, cx, cy = kf.intrinsics
            self.camera = {"w": int(kf.image.shape[1]), "h": int(kf.image.shape[0]), "fl_x": fx, "fl_y": fy,
                           "cx": cx, "cy": cy}
        self.frames.append({"file_path": f"images/{kf.name}.png", "transform_matrix": matrix_to_list(kf.c2w),
                            "stamp_ns": kf.stamp_ns, "received_ns": kf.received_ns, "ready_ns": kf.ready_ns,
                            "admitted_ns": time.time_ns(),
                            "held_out": held_out})
        atomic_write_text(self.folder / "transforms.json", json.dumps(
            {"camera_model": "PINHOLE", **self.camera, "dinerf": {"source": "stream"}, "frames": self.frames}))

    def image(self, frame: dict, width: int, height: int) -> np.ndarray:
        img = read_image(self.folder / frame["file_path"])
        return resize_image(img, width, height)


class ViewStream:
    """A robot's growing set of keyframes, the trainer's pixel source (module docstring)."""

    def __init__(self, cfg: StreamConfig, intake: FrameIntake, folder: Path, width: int | None,
                 holdout_every: int, capacity: int) -> None:
        if capacity < 1:
            raise DataError("a stream needs a keyframe budget: set data.stream.capacity or "
                            "data.ros.keyframes.max_keyframes")
        self.cfg, self.intake, self.width, self.every, self.capacity = cfg, intake, width, holdout_every, capacity
        self.store = _Store(folder)
        self.ended = threading.Event()
        self.error: BaseException | None = None
        self.trainer = None
        self._rows: list[dict] = []  # per trainer row, its frame
        self._held: list[dict] = []
        self._size: tuple[int, int] | None = None  # (width, height) at training size
        self._buffer: Tensor | None = None  # [working_set, H, W, C]
        self._slot_row = torch.full((cfg.working_set,), -1, dtype=torch.long)  # trainer row of each slot
        self._steps = 0
        self._counts = {"admitted": 0, "held_out": 0}
        self._dropped_before = 0
        self._over_capacity = 0
        self._newest_received: float | None = None
        self._lo = self._hi = None
        self._thread: threading.Thread | None = None
        self._pending: list[Keyframe] = []  # the intake's last keyframes, once its source ended
        self._newest_stamp = max((f["stamp_ns"] for f in self.store.frames), default=-1)
        for frame in self.store.frames:  # a restart: what this run already had
            self._place(frame)

    # ------------------------------------------------------------------ sources
    def run_in_background(self, feed) -> None:
        """Run ``feed(stop_event)`` (a replay) in a thread; the stream ends when it returns."""
        def target() -> None:
            try:
                feed(self.ended)
            except BaseException as e:  # a damaged bag: said by the daemon's next admission
                self.error = e
            finally:
                self._pending = self.intake.finish()
                self.ended.set()

        self._thread = threading.Thread(target=target, name="view-stream", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self.ended.set()
        if self._thread is not None:
            self._thread.join(timeout=5)

    def _arrived(self) -> list[Keyframe]:
        if self.error is not None:
            raise DataError(str(self.error)) if not isinstance(self.error, DataError) else self.error
        out = self.intake.take()
        if self.ended.is_set():
            out, self._pending = out + self._pending, []
        return [k for k in out if k.stamp_ns > self._newest_stamp]  # a replay after a restart: none added twice

    def wait_for_start(self, log=lambda text: None) -> None:
        """Until ``start_keyframes`` keyframes are in (or the source ended, or the timeout)."""
        deadline = time.monotonic() + self.cfg.start_timeout_s
        while len(self._rows) < self.cfg.start_keyframes and time.monotonic() < deadline:
            ended = self.ended.is_set()
            self._admit(self._arrived())
            if ended:
                break
            time.sleep(0.05)
        if not self._rows:
            raise DataError(f"no keyframe arrived within {self.cfg.start_timeout_s:.0f} s (images {self.intake.images}, "
                            f"without a pose {dict(self.intake.skipped)}; camera info "
                            f"{'seen' if self.intake.camera else 'not seen'})")
        log(f"{len(self._rows)} keyframes to start from ({len(self._held)} held out)")

    # ------------------------------------------------------------------ admission
    def _place(self, frame: dict) -> None:
        """A stored keyframe takes a trainer row (or the held-out list)."""
        if frame.get("held_out"):
            self._held.append(frame)
            return
        if len(self._rows) >= self.capacity:
            self._over_capacity += 1
            return
        self._rows.append(frame)
        centre = np.asarray(frame["transform_matrix"])[:3, 3]
        self._lo = centre if self._lo is None else np.minimum(self._lo, centre)
        self._hi = centre if self._hi is None else np.maximum(self._hi, centre)
        if self.trainer is not None:
            self._to_trainer(len(self._rows) - 1)

    def _admit(self, keyframes: list[Keyframe]) -> None:
        for kf in keyframes:
            n = len(self.store.frames)
            held = self.every > 0 and n % self.every == self.every - 1
            self.store.add(kf, held)
            self._counts["held_out" if held else "admitted"] += 1
            self._newest_received = kf.received_ns * 1e-9
            self._newest_stamp = max(self._newest_stamp, kf.stamp_ns)
            self._place(self.store.frames[-1])

    def admit(self) -> None:
        """Take in what arrived since the last call (the daemon calls it before each round)."""
        self._admit(self._arrived())

    def attach(self, trainer) -> None:
        """The trainer built from :meth:`initial_views` gets every admitted row and samples from us."""
        self.trainer = trainer
        first_loaded = len(self._rows) - self.cfg.working_set  # a restart: only the newest are read back
        for row in range(len(self._rows)):
            self._to_trainer(row, load=row >= first_loaded)

    def _camera(self, frame: dict, size: tuple[int, int] | None = None) -> tuple[Tensor, Tensor]:
        cam = self.store.camera
        s = (size or self.size)[0] / cam["w"]
        k = torch.tensor([cam["fl_x"] * s, cam["fl_y"] * s, cam["cx"] * s, cam["cy"] * s])
        return torch.tensor(frame["transform_matrix"], dtype=torch.float32), k

    @property
    def training_keyframes(self) -> int:
        return len(self._rows)

    @property
    def size(self) -> tuple[int, int]:
        if self._size is None:
            cam = self.store.camera
            self._size = target_size(int(cam["w"]), int(cam["h"]), self.width, "data.stream")
        return self._size

    def _to_trainer(self, row: int, load: bool = True) -> None:
        c2w, k = self._camera(self._rows[row])
        self.trainer.admit_views(row, c2w, k, *self.size)
        if load:
            self._load_into_working_set(row)

    # ------------------------------------------------------------------ the working set
    def _image(self, frame: dict, size: tuple[int, int] | None = None) -> Tensor:
        return torch.from_numpy(np.ascontiguousarray(self.store.image(frame, *(size or self.size))))

    def _load_into_working_set(self, row: int, slot: int | None = None) -> None:
        img = self._image(self._rows[row])
        if self._buffer is None:
            w, h = self.size
            self._buffer = torch.zeros(self.cfg.working_set, h, w, img.shape[-1])
        if slot is None:
            free = (self._slot_row < 0).nonzero()
            slot = int(free[0]) if len(free) else self._old_slots()[row % len(self._old_slots())]
        self._buffer[slot] = img
        self._slot_row[slot] = row

    def _old_slots(self) -> list[int]:
        """Slots that do not hold one of the newest ``recent_keyframes`` rows."""
        newest = len(self._rows) - self.cfg.recent_keyframes
        return [s for s in range(self.cfg.working_set) if int(self._slot_row[s]) < newest]

    def _refresh(self, generator: torch.Generator) -> None:
        """Swap a few old keyframes of the working set for others not in it: each comes back in turn."""
        rows, ws = len(self._rows), self.cfg.working_set
        old = self._old_slots()
        if rows <= ws or not old:
            return
        held = set(int(r) for r in self._slot_row)
        outside = [r for r in range(rows - self.cfg.recent_keyframes) if r not in held]
        swaps = min(max(1, len(old) // 8), len(outside))
        pick = torch.randperm(len(outside), generator=generator)[:swaps]
        slots = torch.randperm(len(old), generator=generator)[:swaps]
        for r, s in zip(pick.tolist(), slots.tolist()):
            self._load_into_working_set(outside[r], old[s])

    def sample(self, n: int, generator: torch.Generator, device: torch.device) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """n pixels: trainer row, pixel row, column [n] each and colour [n, C] (the trainer's source).
        What arrived since the last step is admitted first: a keyframe is trained from the next step on."""
        self._admit(self._arrived())
        if self._steps % self.cfg.refresh_every == 0:
            self._refresh(generator)
        self._steps += 1
        filled = (self._slot_row >= 0).nonzero().squeeze(-1)  # [K]
        rows = self._slot_row[filled]
        k = len(filled)
        recent = rows >= len(self._rows) - self.cfg.recent_keyframes
        if self.cfg.sampling == "recency" and 0 < int(recent.sum()) < k:
            f = self.cfg.recent_fraction
            weights = (1 - f) / k + f * recent.float() / float(recent.sum())
            pos = torch.multinomial(weights, n, replacement=True, generator=generator)
        else:
            pos = torch.randint(0, k, (n,), generator=generator)
        w, h = self.size
        px = torch.randint(0, h * w, (n,), generator=generator)
        row, col = px // w, px % w
        pixels = self._buffer[filled[pos], row, col]
        return rows[pos].to(device), row.to(device), col.to(device), pixels.to(device)

    # ------------------------------------------------------------------ views for who needs pixels
    def _views(self, frames: list[dict], size: tuple[int, int] | None = None) -> Views:
        cams = [self._camera(f, size) for f in frames]
        return Views(torch.stack([self._image(f, size) for f in frames]), torch.stack([c for c, _ in cams]),
                     torch.stack([k for _, k in cams]), [Path(f["file_path"]).stem for f in frames],
                     meta={"format": "stream", "source": str(self.store.folder)})

    def initial_views(self, width: int | None = 0) -> Views:
        """The training keyframes admitted so far, in memory: the box, the first summary, the first rows.
        ``width``: 0 the training width, None the camera's own (the keyframe summary's sharper copy)."""
        return self._views(self._rows, self._size_for(width))

    def spread_views(self, limit: int, width: int | None = 0) -> Views:
        """At most ``limit`` training keyframes, spread over positions and viewing directions: the
        summary of a robot that keeps mapping reads a bounded few however many it has."""
        c2w = np.array([f["transform_matrix"] for f in self._rows], dtype=np.float64).reshape(-1, 4, 4)
        return self._views([self._rows[i] for i in spread_views(c2w, limit)], self._size_for(width))

    def _size_for(self, width: int | None) -> tuple[int, int] | None:
        """0: None (the training size); None: the camera's own; else that width."""
        cam = self.store.camera
        return None if width == 0 else target_size(int(cam["w"]), int(cam["h"]), width, "daemon.summary_width")

    def holdout_views(self) -> Views | None:
        """Up to ``eval_views`` held-out keyframes spread over all of them (the log line's PSNR)."""
        if not self._held:
            return None
        n = min(self.cfg.eval_views, len(self._held))
        pick = sorted({round(i * (len(self._held) - 1) / max(n - 1, 1)) for i in range(n)})
        return self._views([self._held[i] for i in pick])

    # ------------------------------------------------------------------ telemetry
    def round_stats(self) -> StreamRound:
        dropped = self.intake.dropped + self._over_capacity
        out = StreamRound(
            admitted=self._counts["admitted"], held_out=self._counts["held_out"],
            dropped=dropped - self._dropped_before, keyframes=len(self._rows), held_out_total=len(self._held),
            dropped_total=dropped,
            newest_age_s=None if self._newest_received is None else max(time.time() - self._newest_received, 0.0),
            coverage=None if self._lo is None else [float(x) for x in self._hi - self._lo])
        self._counts = {"admitted": 0, "held_out": 0}
        self._dropped_before = dropped
        return out

    def describe(self) -> str:
        return (f"{len(self._rows)} keyframes ({len(self._held)} held out), working set {self.cfg.working_set}, "
                f"sampling {self.cfg.sampling}" + (f" ({self.cfg.recent_fraction:.0%} of rays on the newest "
                                                   f"{self.cfg.recent_keyframes})" if self.cfg.sampling == "recency"
                                                   else ""))
