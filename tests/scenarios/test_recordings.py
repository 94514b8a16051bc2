"""A recording scenario's robots get bags of their views in odometry frames of their own, and the
truth follows: carried back through the rewritten truth, every camera read from a bag is where
the split put it in the world."""

from __future__ import annotations

import json

import torch

from agent.data.loaders import load_views
from agent.data.split import SplitConfig, split_dataset
from cli.scenario.recordings import record_robots, recording_of
from cli.scenario.runner import prepare_split
from cli.scenario.spec import RecordSpec, ScenarioSpec


def test_bags_in_their_own_frames_and_a_truth_that_maps_them_back_to_the_world(tmp_path):
    spec = ScenarioSpec(name="rec", dataset="procedural:views=16,width=32", robots=2,
                        split=SplitConfig(overlap=0.2, frame="world", test_every=4),
                        record=RecordSpec(enabled=True, k1=0.0, storage=["mcap", "sqlite3"], reverse=[2]))
    data = tmp_path / "data"
    prepare_split(spec, data)
    _, split = split_dataset(spec.dataset, spec.split, None)
    summary = record_robots(spec, data, echo=lambda _: None)
    assert [summary[i]["storage"] for i in (1, 2)] == ["mcap", "sqlite3"]
    names = {i: split.robots[i].views.names for i in (1, 2)}
    assert summary[1]["views"] == names[1] and summary[2]["views"] == names[2][::-1]  # robot 2 walks back
    assert len(summary[2]["stamps_s"]) == len(names[2]) and summary[2]["stamps_s"] == sorted(summary[2]["stamps_s"])
    assert recording_of(data / "robot1").suffix == ".mcap" and recording_of(data / "robot2").name == "bag"
    assert sorted(p.name for p in (data / "robot1").iterdir()) == ["robot1.mcap", "tls"]  # no images left beside
    truth = json.loads((data / "truth.json").read_text())["robots"]
    for i in (1, 2):
        views = load_views(recording_of(data / f"robot{i}"))  # the camera in its odometry frame, from the bag
        world = torch.tensor(truth[str(i)]["T_world_from_local"], dtype=torch.float64) @ views.c2w.double()
        index = [int(n.split("_")[1]) for n in views.names]  # keyframe names: the image's index in the bag
        if i == 2:  # recorded last view first
            index = [len(names[2]) - 1 - k for k in index]
        expected = split.robots[i].views.c2w.double()[index]  # frame "world": the split's cameras are the truth
        assert torch.allclose(world, expected, atol=1e-4), i
        assert float((views.c2w[:, :3, 3] - split.robots[i].views.c2w[index, :3, 3]).norm(dim=-1).min()) > 0.1  # moved
