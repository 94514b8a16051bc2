"""The swarm TOML: what every robot of a swarm shares, in one typed object.

::

    [swarm]                      # who: name, robots, the shared field box
    name = "demo"
    robots = [1, 2, 3]
    scene = "scene.json"         # relative to this file (written by `dinerf-agent split`)

    [topology]                   # protocol.membership.TopologyConfig
    kind = "line"                # full | ring | star | line | edges (+ edges = [[1, 2]], hub = 1)

    [network]                    # protocol.transport.TransportConfig, plus endpoints
    lease_ms = 2000
    [network.endpoints]          # robot id -> where it listens; robots connect to their neighbours'
    "1" = "tcp/127.0.0.1:7501"

    [training]                   # agent.swarm.SwarmTrainingConfig (rounds, steps, rho, model ...)
    [daemon]                     # agent.daemon.DaemonConfig (timeouts, threads, wire dtype ...)
    [align]                      # agent.align.AlignConfig (keyframe summaries, matching)
    [sfm]                        # agent.data.sfm.SfmConfig (robots with images only)
    [data.ros]                   # agent.data.ros.RosBagConfig (robots with ROS 2 bags)
    [data.stream]                # agent.data.stream.StreamConfig (up --replay / --live: views that arrive)
    [security]                   # protocol.pki.SecurityConfig: mutual TLS + access control, or insecure

Unless ``[security] insecure = true``, every endpoint is ``tls/``, each robot presents the
certificate in ``<its data folder>/tls/`` (CN ``robot-<id>``, checked before the session opens)
and loads the access control of ``protocol.acl`` built from ``swarm.robots`` minus
``security.revoked``: robot i may say only its own keys.

A scenario.toml has the same sections (cli.scenario.spec), so one setting has one name.
"""

from __future__ import annotations

import dataclasses
import random
import socket
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from agent.align import AlignConfig
from agent.daemon import DaemonConfig, SwarmIdentity
from agent.data.config import DataConfig
from agent.data.folder import read_scene
from agent.defaults import Capture, fit_train
from agent.data.sfm import SfmConfig
from agent.frames import resolve_pose_settings
from agent.swarm import SwarmTrainingConfig
from agent.trainer import TrainConfig
from cli.config import ConfigError, apply_overrides, from_dict, load_toml, merge_tables, overrides_table, to_dict
from protocol.acl import access_control
from protocol.keys import Keys, validate_swarm
from protocol.membership import Topology, TopologyConfig, TopologyError
from protocol.pki import MONITOR_NAME, PkiError, SecurityConfig, check_identity, robot_name
from protocol.transport import TransportConfig

SWARM_FILE = "swarm.toml"


@dataclass
class SwarmSection:
    name: str
    robots: list[int]
    # which frames the robots' poses are in: shared | local | sfm (agent.frames); required
    frames: Literal["shared", "local", "sfm"] | None = None
    # the field box every robot shares (written by `split`); "": none, the reference derives it
    # from its own views and sends it with its keyframe summary (`init`: robots' own recordings)
    scene: str = "scene.json"


@dataclass
class NetworkSection(TransportConfig):
    endpoints: dict[str, str] = field(default_factory=dict)  # robot id -> listen endpoint


@dataclass
class SwarmFile:
    swarm: SwarmSection
    topology: TopologyConfig = field(default_factory=TopologyConfig)
    network: NetworkSection = field(default_factory=NetworkSection)
    training: SwarmTrainingConfig = field(default_factory=SwarmTrainingConfig)
    daemon: DaemonConfig = field(default_factory=DaemonConfig)
    align: AlignConfig = field(default_factory=AlignConfig)
    sfm: SfmConfig = field(default_factory=SfmConfig)
    data: DataConfig = field(default_factory=DataConfig)
    security: SecurityConfig = field(default_factory=SecurityConfig)

    def graph(self) -> Topology:
        try:
            return self.topology.build(self.swarm.robots)
        except TopologyError as e:
            raise ConfigError(f"topology: {e}") from None

    def identity(self) -> SwarmIdentity:
        return SwarmIdentity(self.swarm.name, self.graph())

    def endpoint(self, robot_id: int) -> str | None:
        return self.network.endpoints.get(str(robot_id))

    def transport_for(self, robot_id: int, listen: list[str], connect: list[str],
                      tls_dir: Path | None = None) -> TransportConfig:
        """The robot's transport: flags win; else listen on its endpoint, connect to its neighbours'.
        In a secure swarm, with the certificate in ``tls_dir`` and the swarm's access control."""
        from dataclasses import fields

        base = {f.name: getattr(self.network, f.name) for f in fields(TransportConfig)}
        own = self.endpoint(robot_id)
        if listen or own:
            base["listen"] = list(listen) if listen else [own]
        neighbours = [e for j in sorted(self.graph().neighbours(robot_id)) if (e := self.endpoint(j))]
        if connect or neighbours:
            base["connect"] = list(connect) if connect else neighbours
        if not self.security.insecure:
            if robot_name(robot_id) in self.security.revoked:
                raise ConfigError(f"security.revoked: robot {robot_id} is revoked in this swarm file")
            if tls_dir is None:
                raise ConfigError("a secure swarm needs the robot's certificate folder (tls/)")
            base.update(self._tls(Path(tls_dir), robot_name(robot_id)))
        return self._checked(TransportConfig(**base), base["listen"] + base["connect"])

    def monitor_transport(self, base_dir: Path, connect: list[str]) -> TransportConfig:
        """What `dinerf-agent status` joins with: listens nowhere, presents the monitor certificate."""
        base: dict = dict(listen=[], connect=list(connect), multicast_scouting=self.network.multicast_scouting,
                          lease_ms=self.network.lease_ms, tls_verify_name_on_connect=self.network.tls_verify_name_on_connect)
        if not self.security.insecure:
            base.update(self._tls(Path(base_dir) / self.security.monitor_dir, MONITOR_NAME))
        return self._checked(TransportConfig(**base), base["connect"])

    def _tls(self, tls_dir: Path, name: str) -> dict:
        try:
            check_identity(tls_dir, name)
        except PkiError as e:
            raise ConfigError(f"security: {e}") from None
        acl = access_control(Keys(self.swarm.name), self.swarm.robots, self.security.revoked)
        return dict(tls_root_ca=str(tls_dir / "ca.pem"), tls_cert=str(tls_dir / "cert.pem"),
                    tls_key=str(tls_dir / "key.pem"), enable_mtls=True, access_control=acl)

    def _checked(self, cfg: TransportConfig, endpoints: list[str]) -> TransportConfig:
        if not self.security.insecure:
            plain = [e for e in endpoints if not e.startswith("tls/")]
            if plain:
                raise ConfigError(f"network: endpoint {plain[0]!r} is not tls/: a secure swarm authenticates every "
                                  "link (use tls/host:port, or set [security] insecure = true for plain TCP)")
        try:
            cfg.validate()
        except ValueError as e:
            raise ConfigError(f"network: {e}") from None
        return cfg


def load_swarm_file(path: Path, overrides: list[str] = ()) -> tuple[SwarmFile, Path]:
    """Load and validate; returns the config and the folder relative paths are resolved against."""
    data = load_toml(path)
    if not isinstance(data.get("swarm"), dict):
        raise ConfigError(f"{path}: missing the [swarm] table (name, robots)")
    moved = sorted({"topology", "edges", "hub"} & set(data["swarm"]))
    if moved:
        raise ConfigError(f"{path}: swarm.{moved[0]} now lives in its own [topology] table "
                          "(kind = \"ring\", edges = [[1, 2]], hub = 1), as in scenario.toml")
    cfg = from_dict(SwarmFile, data, "")
    cfg = apply_overrides(cfg, list(overrides))
    base = path.resolve().parent
    given = merge_tables(((data.get("training") or {}).get("train") or {}),
                         overrides_table(list(overrides)).get("training", {}).get("train", {}))
    return _validate(fit_to_capture(cfg, given, swarm_capture(cfg, base))), base


def swarm_capture(cfg: SwarmFile, base_dir: Path) -> Capture:
    """What the swarm's images are: its scene file's capture (a split's), the training width and the
    field kind the swarm file sets (robots with their own recordings: `init` writes both)."""
    scene = base_dir / cfg.swarm.scene if cfg.swarm.scene else None
    return capture_of(read_scene(scene).capture if scene is not None and scene.is_file() else None, cfg.training)


def capture_of(scene_capture: dict | None, training: SwarmTrainingConfig) -> Capture:
    """A capture from a scene file's (or None) and the training settings, which win where they are set."""
    known = scene_capture or {}
    unbounded = training.train.field.unbounded
    return Capture(unbounded=unbounded if unbounded is not None else known.get("unbounded"),
                   width=training.image_width or known.get("width"))


def fit_to_capture(cfg, given: dict, capture: Capture):
    """``cfg`` (a swarm file or a scenario) with ``[training.train]`` as ``given`` over what ``capture``
    calls for (agent.defaults)."""
    train = from_dict(TrainConfig, fit_train(given, capture), "training.train")
    return dataclasses.replace(cfg, training=dataclasses.replace(cfg.training, train=train))


def _validate(cfg: SwarmFile) -> SwarmFile:
    """Check the file as a whole; returns it with the pose settings its frames call for."""
    try:
        validate_swarm(cfg.swarm.name)
    except ValueError as e:
        raise ConfigError(f"swarm.name: {e}") from None
    cfg.graph()  # validates robots/edges
    if not cfg.security.insecure:
        plain = sorted(e for e in cfg.network.endpoints.values() if not e.startswith("tls/"))
        if plain:
            raise ConfigError(f"network.endpoints: {plain[0]!r} is plain TCP, but the swarm is secure by default: "
                              "use tls/ endpoints with the certificates of `dinerf-agent split`, or set "
                              "[security] insecure = true (anyone who reaches a port can then join)")
    if cfg.swarm.frames is None:
        raise ConfigError(f"swarm.frames: say which frames the robots' poses are in: {FRAMES_HELP}")
    try:
        training, daemon = resolve_pose_settings(cfg.swarm.frames, cfg.training, cfg.daemon)  # type: ignore[arg-type]
        cfg.align.for_pose_mode(training.train.pose.mode)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    return dataclasses.replace(cfg, training=training, daemon=daemon)


FRAMES_HELP = ("'shared' (one frame for all, e.g. a split with --frame world), 'local' (each robot its own; "
               "poses are learnt from a coarse start) or 'sfm' (images only: each robot's own SfM)")


def robot_tls_dir(data: Path, tls_dir: str = "tls") -> Path:
    """A robot's certificates: ``tls/`` inside its data folder (a split's), else beside its recording
    (``robot3.mcap`` with ``tls/`` next to it); the first is named in the error when neither exists."""
    candidates = ([data / tls_dir] if data.is_dir() else []) + [data.parent / tls_dir]
    return next((c for c in candidates if c.is_dir()), candidates[0])


def find_swarm_file(data_dir: Path) -> Path | None:
    """Where `split` puts it: beside the robot folders, or inside the robot folder."""
    for candidate in (data_dir.parent / SWARM_FILE, data_dir / SWARM_FILE):
        if candidate.is_file():
            return candidate
    return None


def write_swarm_file(path: Path, doc: dict, header: str = "") -> Path:
    """Write a swarm TOML (its sections as plain data) that :func:`load_swarm_file` reads back;
    validated before writing."""
    from cli.scenario.tomlout import dumps

    text = (f"# {header}\n" if header else "") + dumps(doc)
    try:
        _validate(from_dict(SwarmFile, tomllib.loads(text), ""))
    except (ValueError, ConfigError) as e:
        raise ConfigError(f"refusing to write an invalid swarm file {path}: {e}") from None
    path.write_text(text)
    return path


def swarm_doc(name: str, robots: list[int], frames: str, topology: TopologyConfig | str = "full",
              scene: str = "scene.json", **sections: dict) -> dict:
    """A swarm file's sections as plain data: [swarm], [topology] and any of network, training,
    daemon, align, sfm, data, security (dicts of the settings that differ from the defaults, or everything)."""
    topo = TopologyConfig(topology) if isinstance(topology, str) else topology
    unknown = sorted(set(sections) - {"network", "training", "daemon", "align", "sfm", "data", "security"})
    if unknown:
        raise ValueError(f"not swarm-file sections: {unknown}")
    return {"swarm": {"name": name, "robots": list(robots), "frames": frames, "scene": scene}, "topology": to_dict(topo),
            **{k: v for k, v in sections.items() if v}}


def loopback_endpoints(robots: list[int], port_base: int, tls: bool = True) -> dict[str, str]:
    """One port per robot on 127.0.0.1 (local runs: every robot on this machine); tls/ unless insecure."""
    return {str(i): f"{'tls' if tls else 'tcp'}/127.0.0.1:{port_base + i}" for i in robots}


def free_loopback_port_base(count: int) -> int:
    """A base such that base+1 .. base+count are free TCP ports on 127.0.0.1 now (best effort).

    Below the kernel's ephemeral range: a listener port inside it can be taken, before its robot
    binds it, as the local port of another robot's outgoing connection (it happened with 32 robots)."""
    low = _ephemeral_low()
    rng = random.Random()
    for _ in range(200):
        base = rng.randrange(10000, max(low - count - 1, 10001))
        if all(_bindable(base + i) for i in range(1, count + 1)):
            return base
    raise RuntimeError(f"no {count} consecutive free ports on 127.0.0.1 below {low}")


def _ephemeral_low() -> int:
    try:
        return int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768  # Linux's default


def _bindable(port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def security_sections(insecure: bool, monitor_dir: str = "monitor") -> dict[str, dict]:
    """The [security] and [network] settings a generated swarm file gets: mutual TLS with the
    split's certificates (names are not checked against addresses: the CN is the identity), or
    plain TCP when asked for explicitly."""
    if insecure:
        return {"security": {"insecure": True}, "network": {}}
    return {"security": {"monitor_dir": monitor_dir}, "network": {"tls_verify_name_on_connect": False}}


def parse_robot_endpoint(text: str, port_base: int) -> tuple[int, str]:
    """``--robot 3=HOST[:PORT]`` -> (3, "HOST:PORT"); the port defaults to ``port_base + id``."""
    rid, eq, where = text.partition("=")
    try:
        robot_id = int(rid)
    except ValueError:
        robot_id = -1
    if not eq or robot_id < 1 or not where or where.startswith(":"):
        raise ConfigError(f"--robot {text!r}: expected ID=HOST or ID=HOST:PORT, e.g. 3=192.168.1.13:7503")
    host, colon, port = where.rpartition(":") if where.count(":") == 1 else (where, "", "")
    if colon and not (port.isdigit() and 0 < int(port) < 65536):
        raise ConfigError(f"--robot {text!r}: port {port!r} is not a port number")
    return robot_id, f"{host}:{port}" if colon else f"{where}:{port_base + robot_id}"


def init_swarm(out: Path, name: str, endpoints: dict[int, str], *, frames: str = "local", topology: str = "full",
               insecure: bool = False, training: dict | None = None) -> Path:
    """A swarm for robots that already have their own recordings (no split): ``swarm.toml`` with
    no scene file (the reference derives the field box), and unless insecure the swarm CA in
    ``<out>/ca/`` (never in a robot folder), ``<out>/robot<i>/tls/`` and ``<out>/monitor/``.

    endpoints: robot id -> "HOST:PORT" it listens on (its certificate names HOST too)."""
    from protocol.pki import MONITOR_NAME, create_ca, issue, robot_name

    ids = sorted(endpoints)
    out.mkdir(parents=True, exist_ok=True)
    if not insecure:
        ca = create_ca(out / "ca", name, overwrite=True)
        for i in ids:
            issue(ca, robot_name(i), out / f"robot{i}" / "tls", hosts=(endpoints[i].rsplit(":", 1)[0],))
        issue(ca, MONITOR_NAME, out / "monitor")
    sec = security_sections(insecure)
    scheme = "tcp" if insecure else "tls"
    network = {**sec["network"], "endpoints": {str(i): f"{scheme}/{endpoints[i]}" for i in ids}}
    doc = swarm_doc(name, ids, frames, topology, scene="", network=network, training=training or {},
                    security=sec["security"])
    return write_swarm_file(out / SWARM_FILE, doc, header="written by `dinerf-agent init`; edit freely (see cli/swarm_file.py)")


def add_robot(path: Path, robot_id: int, endpoint: str) -> None:
    """Add ``robot_id`` listening on ``endpoint`` (tls/ or tcp/ HOST:PORT) to a swarm file's roster."""
    data = load_toml(path)
    robots = data.setdefault("swarm", {}).setdefault("robots", [])
    if robot_id in robots:
        raise ConfigError(f"{path}: robot {robot_id} is already in the swarm's robots {robots}")
    data["swarm"]["robots"] = sorted(robots + [robot_id])
    data.setdefault("network", {}).setdefault("endpoints", {})[str(robot_id)] = endpoint
    header = " ".join(line.lstrip("# ").strip() for line in path.read_text().splitlines()[:1] if line.startswith("#"))
    write_swarm_file(path, data, header=header)


def next_endpoint(cfg: SwarmFile, robot_id: int, host: str | None, port: int | None) -> str:
    """The endpoint of a robot added to ``cfg``: HOST:PORT as given, else on the pattern of the
    others (loopback ``base + id``), else a clear error asking for them."""
    scheme = "tcp" if cfg.security.insecure else "tls"
    bases = {int(e.rsplit(":", 1)[1]) - int(i) for i, e in cfg.network.endpoints.items() if e.rsplit(":", 1)[-1].isdigit()}
    hosts = {e.split("/", 1)[-1].rsplit(":", 1)[0] for e in cfg.network.endpoints.values()}
    if port is None and len(bases) == 1:
        port = bases.pop() + robot_id
    if host is None and len(hosts) == 1 and hosts <= {"127.0.0.1", "localhost"}:
        host = hosts.pop()
    if host is None or port is None:
        raise ConfigError(f"where does robot {robot_id} listen? give --host HOST and --port PORT (the other robots' "
                          f"endpoints follow no single pattern: {sorted(cfg.network.endpoints.values())})")
    return f"{scheme}/{host}:{port}"
