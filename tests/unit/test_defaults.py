"""Defaults that fit the data (agent.defaults): what the capture calls for fills what was left unset."""

from __future__ import annotations

import json

from typer.testing import CliRunner

import cli.main
from agent.defaults import Capture, defaults_for, fit_train
from cli.swarm_file import load_swarm_file

cli.main._register()
runner = CliRunner()


def test_the_table_follows_the_capture_and_what_was_given_wins():
    room = defaults_for(Capture(unbounded=True, width=100))
    assert room["field"]["unbounded"] is True and room["occupancy"]["resolution"] == 96
    assert room["occupancy"]["decay"] < 0.95  # a short run must forget the young field's fog
    assert room["occupancy"]["density_threshold"] > 1  # and close the fog a room field holds near density 1
    assert room["march"]["skip_visibility_above"] == 1.0 and room["rays_per_step"] == 1024
    # a sample budget that shrinks the batch while the young field's fog holds ~100 samples a ray
    assert 0 < room["target_samples_per_step"] < 1024 * 100
    assert defaults_for(Capture(unbounded=False, width=48))["field"]["grid"]["log2_hashmap_size"] == 14
    assert defaults_for(Capture(unbounded=False, width=100))["field"]["grid"]["log2_hashmap_size"] == 17
    assert defaults_for(Capture()) == {}  # nothing known: the dataclasses' defaults
    given = {"rays_per_step": 300, "field": {"grid": {"num_levels": 6}}}
    fitted = fit_train(given, Capture(unbounded=True, width=48))
    assert fitted["rays_per_step"] == 300 and fitted["field"]["grid"] == {"log2_hashmap_size": 14, "num_levels": 6,
                                                                           "max_resolution": 256}
    # an explicit field kind decides the table, whatever the scene said
    assert "march" not in fit_train({"field": {"unbounded": False}}, Capture(unbounded=True, width=48))


def test_a_split_swarm_gets_what_its_images_call_for_and_a_set_still_wins(tmp_path):
    out = tmp_path / "room"
    res = runner.invoke(cli.main.app, ["split", "--data", "procedural:views=12,width=40,room=1", "-n", "2",
                                       "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert json.loads((out / "scene.json").read_text())["capture"] == {"unbounded": True, "width": 40}
    cfg, _ = load_swarm_file(out / "swarm.toml")
    t = cfg.training.train
    assert (t.field.unbounded, t.field.density_hidden, t.occupancy.resolution, t.rays_per_step) == (True, 32, 96, 1024)
    cfg, _ = load_swarm_file(out / "swarm.toml", ["training.train.occupancy.resolution=40", "training.image_width=200"])
    assert cfg.training.train.occupancy.resolution == 40 and cfg.training.train.field.density_hidden == 32
    shown = runner.invoke(cli.main.app, ["config", "show", "--swarm", str(out / "swarm.toml")])
    assert "skip_visibility_above = 1.0" in shown.stdout and "resolution = 96" in shown.stdout


def test_room_2_arc_keeps_its_measured_settings_without_writing_them():
    shown = runner.invoke(cli.main.app, ["config", "show", "--scenario", "room-2-arc"]).stdout
    for line in ("rays_per_step = 1024", "density_hidden = 32", "log2_hashmap_size = 14", "num_levels = 12",
                 "max_resolution = 256", "resolution = 96", "unbounded = true"):
        assert f"\n{line}\n" in shown, line
    assert "given_train" not in shown
