"""Publish a ROS 2 bag over Zenoh as rmw_zenoh would: a robot's camera and tf, without ROS.

    python tools/rmw_zenoh_publish.py robot.mcap --connect tcp/localhost:7447 [--rate 1.0] [--skip N] [--count M]

The stand-in for a camera driver and robot_state_publisher in tests and benchmarks (no ROS
runtime is installable here); the keys and the attachment are :mod:`protocol.rmw_format`'s.
Prints one line when done: how many messages it published.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from protocol.ros_camera import RosTopicPublisher, replay_bag  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("bag", type=Path)
    p.add_argument("--connect", action="append", default=[], help="Zenoh endpoint (the robot's router)")
    p.add_argument("--listen", action="append", default=[], help="Zenoh endpoint to listen on (peer mode)")
    p.add_argument("--mode", default="peer", choices=("peer", "client"))
    p.add_argument("--domain", type=int, default=0)
    p.add_argument("--rate", type=float, default=1.0, help="x the recorded pace (0: as fast as possible)")
    p.add_argument("--skip", type=int, default=0, help="start at this message")
    p.add_argument("--count", type=int, default=None, help="publish this many messages")
    p.add_argument("--match-timeout", type=float, default=0.0, help="wait this long for a subscriber per topic")
    p.add_argument("--linger", type=float, default=0.5, help="seconds to keep the session after the last message")
    a = p.parse_args(argv)
    if not a.bag.exists():
        print(f"{a.bag}: no such bag", file=sys.stderr)
        return 2
    pub = RosTopicPublisher(a.connect, a.listen, a.domain, a.mode, a.match_timeout)
    try:
        n = replay_bag(a.bag, pub, a.rate, skip=a.skip, count=a.count)
        time.sleep(a.linger)  # what is queued must leave before the session closes
    finally:
        pub.close()
    print(f"published {n} messages", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
