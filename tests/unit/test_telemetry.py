"""agent.telemetry's files: what a robot writes while it shuts down."""

from __future__ import annotations

from agent.telemetry import EventLog, read_events


def test_an_event_after_close_is_dropped_not_an_error(tmp_path):
    """A liveliness callback may report a neighbour's departure after the robot closed its files
    ("error in liveliness callback ... I/O operation on closed file" in 5 of 37 logs)."""
    log = EventLog(tmp_path / "events.jsonl", robot_id=1)
    log.write("start", 0)
    log.close()
    log.write("membership", 3, alive=[1])
    assert [e["event"] for e in read_events(tmp_path / "events.jsonl")] == ["start"]
