"""agent.progress: long local work reports to the listener a command installs, and to nobody otherwise."""

from __future__ import annotations

from agent.data.loaders import load_views
from agent.progress import listening, stage, track


class Recorder:
    def __init__(self) -> None:
        self.events: list[tuple] = []

    def begin(self, description, total):
        self.events.append(("begin", description, total))
        return len(self.events)

    def advance(self, task):
        self.events.append(("advance", task))

    def end(self, task):
        self.events.append(("end", task))


def test_without_a_listener_nothing_is_told_and_items_pass_through():
    assert list(track(iter(range(3)), "x")) == [0, 1, 2]
    with stage("y"):
        pass


def test_a_bar_per_loop_and_a_spinner_per_stage():
    rec = Recorder()
    with listening(rec):
        assert list(track([5, 6], "two")) == [5, 6]
        with stage("unknown"):
            pass
    assert rec.events == [("begin", "two", 2), ("advance", 1), ("advance", 1), ("end", 1),
                          ("begin", "unknown", None), ("end", 5)]


def test_loading_a_folder_advances_once_per_image(tmp_path):
    from typer.testing import CliRunner

    from cli.main import _register, app

    _register()
    res = CliRunner().invoke(app, ["split", "--data", "procedural:views=8,width=8", "-n", "2", "--out", str(tmp_path)])
    assert res.exit_code == 0, res.output
    rec = Recorder()
    with listening(rec):
        views = load_views(tmp_path / "robot1")
    begins = [e for e in rec.events if e[0] == "begin"]
    assert begins and begins[0][2] == len(views) and sum(e[0] == "advance" for e in rec.events) == len(views)
