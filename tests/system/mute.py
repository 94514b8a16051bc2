"""A robot that holds its liveliness token but never sends a thing: the stand-in for a neighbour
behind a dead link whose token Zenoh has not dropped yet (it took 11-21 s in one CI run).

Run as ``python tests/system/mute.py SWARM_TOML ID DURATION_S``. It takes robot ID's place in the
swarm (its endpoint, its token), prints ``ready`` and stays silent until DURATION_S is over.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))


def main(swarm_toml: str, robot_id: int, duration: float) -> None:
    from cli.swarm_file import load_swarm_file
    from protocol.keys import Keys
    from protocol.transport import ZenohTransport

    cfg, _ = load_swarm_file(Path(swarm_toml))
    net = ZenohTransport(cfg.transport_for(robot_id, [], []), Keys(cfg.swarm.name), robot_id).open()
    net.declare_alive()
    print("ready", flush=True)
    time.sleep(duration)
    net.close()


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]), float(sys.argv[3]))
