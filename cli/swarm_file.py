"""The swarm TOML: what every robot of a swarm shares, in one typed object.

::

    [swarm]                      # who: name, robots, topology, the shared field box
    name = "demo"
    robots = [1, 2, 3]
    topology = "line"            # full | ring | star | line | edges
    edges = []                   # for "edges": [[1, 2], [2, 3]]
    scene = "scene.json"         # relative to this file (written by `dinerf-agent split`)

    [network]                    # protocol.transport.TransportConfig, plus endpoints
    lease_ms = 2000
    [network.endpoints]          # robot id -> where it listens; robots connect to their neighbours'
    "1" = "tcp/127.0.0.1:7501"

    [training]                   # agent.swarm.SwarmTrainingConfig (rounds, steps, rho, model ...)
    [daemon]                     # agent.daemon.DaemonConfig (timeouts, threads, wire dtype ...)
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from agent.daemon import DaemonConfig, SwarmIdentity
from agent.swarm import SwarmTrainingConfig
from cli.config import ConfigError, apply_overrides, from_dict, load_toml
from protocol.keys import validate_swarm
from protocol.membership import Topology, TopologyError
from protocol.transport import TransportConfig

SWARM_FILE = "swarm.toml"


@dataclass
class SwarmSection:
    name: str
    robots: list[int]
    topology: str = "full"
    edges: list[list[int]] = field(default_factory=list)
    hub: int | None = None
    scene: str = "scene.json"


@dataclass
class NetworkSection(TransportConfig):
    endpoints: dict[str, str] = field(default_factory=dict)  # robot id -> listen endpoint


@dataclass
class SwarmFile:
    swarm: SwarmSection
    network: NetworkSection = field(default_factory=NetworkSection)
    training: SwarmTrainingConfig = field(default_factory=SwarmTrainingConfig)
    daemon: DaemonConfig = field(default_factory=DaemonConfig)

    def topology(self) -> Topology:
        s = self.swarm
        try:
            return Topology.from_spec(s.topology, s.robots, edges=s.edges or None, hub=s.hub)
        except TopologyError as e:
            raise ConfigError(f"swarm.topology: {e}") from None

    def identity(self) -> SwarmIdentity:
        return SwarmIdentity(self.swarm.name, self.topology())

    def endpoint(self, robot_id: int) -> str | None:
        return self.network.endpoints.get(str(robot_id))

    def transport_for(self, robot_id: int, listen: list[str], connect: list[str]) -> TransportConfig:
        """The robot's transport: flags win; else listen on its endpoint, connect to its neighbours'."""
        from dataclasses import fields

        base = {f.name: getattr(self.network, f.name) for f in fields(TransportConfig)}
        own = self.endpoint(robot_id)
        if listen or own:
            base["listen"] = list(listen) if listen else [own]
        neighbours = [e for j in sorted(self.topology().neighbours(robot_id)) if (e := self.endpoint(j))]
        if connect or neighbours:
            base["connect"] = list(connect) if connect else neighbours
        cfg = TransportConfig(**base)
        try:
            cfg.validate()
        except ValueError as e:
            raise ConfigError(f"network: {e}") from None
        return cfg


def load_swarm_file(path: Path, overrides: list[str] = ()) -> tuple[SwarmFile, Path]:
    """Load and validate; returns the config and the folder relative paths are resolved against."""
    data = load_toml(path)
    if "swarm" not in data:
        raise ConfigError(f"{path}: missing the [swarm] table (name, robots, topology)")
    cfg = from_dict(SwarmFile, data, "")
    cfg = apply_overrides(cfg, list(overrides))
    try:
        validate_swarm(cfg.swarm.name)
    except ValueError as e:
        raise ConfigError(f"swarm.name: {e}") from None
    cfg.topology()  # validates robots/edges
    return cfg, path.resolve().parent


def find_swarm_file(data_dir: Path) -> Path | None:
    """Where `split` puts it: beside the robot folders, or inside the robot folder."""
    for candidate in (data_dir.parent / SWARM_FILE, data_dir / SWARM_FILE):
        if candidate.is_file():
            return candidate
    return None


def write_swarm_file(
    path: Path,
    name: str,
    robots: list[int],
    topology: str = "full",
    *,
    edges: list[list[int]] | None = None,
    hub: int | None = None,
    scene: str = "scene.json",
    network: dict | None = None,
    training: dict | None = None,
    daemon: dict | None = None,
    header: str = "",
) -> Path:
    """Write a swarm TOML that :func:`load_swarm_file` reads back (validated before writing)."""
    from cli.scenario.tomlout import dumps

    doc = {
        "swarm": {"name": name, "robots": list(robots), "topology": topology, "edges": edges, "hub": hub,
                  "scene": scene},
        "network": network or {},
        "training": training or {},
        "daemon": daemon or {},
    }
    text = (f"# {header}\n" if header else "") + dumps(doc)
    try:
        validate_swarm(name)
        from_dict(SwarmFile, tomllib.loads(text), "").topology()
    except (ValueError, ConfigError) as e:
        raise ConfigError(f"refusing to write an invalid swarm file {path}: {e}") from None
    path.write_text(text)
    return path


def loopback_endpoints(robots: list[int], port_base: int) -> dict[str, str]:
    """One TCP port per robot on 127.0.0.1 (local runs: every robot on this machine)."""
    return {str(i): f"tcp/127.0.0.1:{port_base + i}" for i in robots}
