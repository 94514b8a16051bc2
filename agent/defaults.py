"""The training settings a capture calls for: the field, the occupancy grid, the sampler and the batch.

One table, decided by what the images are (:class:`Capture`): an object with alpha or masks in a
bounded box, or RGB that shows its surroundings (an unbounded, contracted field), and how wide
the training images are. A setting written in a swarm file, a scenario or ``--set`` always wins:
the table only fills what was left unset (:func:`fit_train`). ``config show`` prints the result,
and each robot's run folder keeps it (its checkpoint's training settings).

A swarm's robots must build the same field (it is part of the model signature), so the capture
is the swarm's, never one robot's own images: ``split`` writes it to ``scene.json``; a swarm of
robots with their own recordings (``init``) states it in its swarm file (``training.image_width``
and ``training.train.field.unbounded``). The figures behind the table are in docs/results.md
("Defaults that fit the data").

| capture | field (MLP width, table, levels to) | occupancy grid | rays / step | sampler |
|---|---|---|---|---|
| bounded, images up to 64 px | 32, 2^14, 12 to 256 | 48, warm-up 64 steps | 1024 | termination once it prunes 40% |
| bounded, wider | 64, 2^17, 16 to 1024 | 64, warm-up 256 | 2048 | as above |
| unbounded, any width | 32, 2^14, 12 to 256 | 96, warm-up 64, decay 0.6, threshold 3 | up to 1024, 32k samples | termination always; rays end at 64 |

Why: a lego-sized field on 48 px images cost 2.5 s a step in the room for nothing it could show;
the unbounded field's linear box fills only the grid's central half, so it wants twice the
bounded grid's cells; and in a contracted scene a ray has ~275 candidates out to ``march.far``,
of which a formed field keeps ~27 before the ray is opaque, so early termination pays from the
first steps (a step of the room's field: 4.0 s without it, 0.53 s with it, measured at 48 px).
Rays of an unbounded field end 64 box half-sizes out: past ~48 one cell of the 96^3 contracted
grid spans the rest of space, so candidates beyond it add cost, not detail (half the candidates
of a ray; at 100 px, 400 steps: 0.24 dB lower and a step 30% cheaper, one run each).
The unbounded grid forgets faster (its running max decays by 0.6 a visit, not nerfacc's 0.95): a
young room field is dense everywhere, and at 0.95 a cell visited every third update still held
a quarter of that after 1000 steps, so 70-100% of the grid stayed open and rays kept ~100
samples where the formed field needs ~35 (room at 100 px, 600 steps: 36.5 samples a ray and
30.33 dB against 93.7 and 29.94 dB). Its threshold is 3 (instant-ngp's opacity 0.01 over its
smallest step, in box units), not 1: a room field holds a fog near density 1 that the lower
threshold keeps open (room-2-arc at 100 px as a swarm: 372 s and 31.08 / 31.07 dB at 3, 549 s
and 31.11 / 30.81 dB at 1).
A step of an unbounded field marches at most 32k samples (instant-ngp's fixed sample budget: the
rays a step shrink while the young field's fog holds ~100 samples a ray, down to
``min_rays_per_step``, and are 1024 again once it holds ~30): the forming field cost a third of the
swarm's time for steps that teach it little (room-2-arc at 100 px as a swarm: 254 s and 30.91 dB
with it, 372 s and 31.07 dB without).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from agent.config_io import merge_tables

__all__ = ["Capture", "defaults_for", "fit_train", "SMALL_IMAGE_WIDTH"]

SMALL_IMAGE_WIDTH = 64  # training images up to this wide get the small field
UNBOUNDED_SAMPLE_BUDGET = 32 * 1024  # samples a step: 1024 rays of a formed room field (~30 samples each)

_SMALL_FIELD = {"density_hidden": 32, "color_hidden": 32,
                "grid": {"log2_hashmap_size": 14, "num_levels": 12, "max_resolution": 256}}
_LARGE_FIELD = {"density_hidden": 64, "color_hidden": 64,
                "grid": {"log2_hashmap_size": 17, "num_levels": 16, "max_resolution": 1024}}


@dataclass(frozen=True)
class Capture:
    """What a swarm's images are, as every robot of it knows them (None: not known)."""

    unbounded: bool | None = None  # RGB without alpha or masks: all of space is modelled
    width: int | None = None  # the training images' width in pixels

    def describe(self) -> str:
        kind = {None: "unknown scene", True: "unbounded (RGB, surroundings)", False: "bounded (alpha or masks)"}
        return f"{kind[self.unbounded]}, {'unknown width' if self.width is None else f'{self.width} px'}"


def defaults_for(capture: Capture) -> dict[str, Any]:
    """The ``[training.train]`` settings the capture calls for, as a (partial) table."""
    if capture.unbounded is None and capture.width is None:
        return {}  # nothing known: the dataclasses' own defaults
    small = capture.width is not None and capture.width <= SMALL_IMAGE_WIDTH
    if capture.unbounded:
        return {"rays_per_step": 1024, "target_samples_per_step": UNBOUNDED_SAMPLE_BUDGET,
                "field": {**_SMALL_FIELD, "unbounded": True},
                "occupancy": {"resolution": 96, "warmup_steps": 64, "decay": 0.6, "density_threshold": 3.0},
                "march": {"skip_visibility_above": 1.0, "far": 64.0}}
    table: dict[str, Any] = {"field": dict(_SMALL_FIELD if small else _LARGE_FIELD)}
    if capture.unbounded is False:
        table["field"]["unbounded"] = False
    if small:
        table.update(rays_per_step=1024, occupancy={"resolution": 48, "warmup_steps": 64})
    elif capture.width is not None:
        table.update(rays_per_step=2048, occupancy={"resolution": 64, "warmup_steps": 256})
    return table


def fit_train(given: dict[str, Any], capture: Capture) -> dict[str, Any]:
    """``[training.train]`` as given (a table, possibly partial) over what the capture calls for."""
    unbounded = given.get("field", {}).get("unbounded") if isinstance(given.get("field"), dict) else None
    if unbounded is not None and unbounded != capture.unbounded:  # an explicit field kind decides the table
        capture = Capture(unbounded=unbounded, width=capture.width)
    return merge_tables(defaults_for(capture), given)
