"""The ``scenario.toml`` schema as typed dataclasses.

A scenario file is read with :func:`cli.config.from_dict`, so an unknown or misspelt key is an
error that names it. Example (every table but ``[scenario]`` is optional)::

    [scenario]
    name = "quickstart"
    dataset = "procedural:views=60,width=48"   # or a path, e.g. "../shared/data/nerf_synthetic/lego"
    width = 48                                 # downscale images to this width
    robots = 3                                 # ids 1..N; robot 1 is the reference
    # credit = "Photography: ..."              # the data's attribution, printed in the report

    [split]                                    # agent.data.split.SplitConfig, see there
    overlap = 0.1
    frame = "offset"
    test_every = 8                             # test views 0, 8, 16 ... seen by no robot
    # by = "trajectory"                        # segments of the capture order instead of azimuth sectors
    # images_only = true                       # robots get no poses (own SfM); robot_image_width = 400
    # calibrated_cameras = true                # ... but each knows its camera's focal length (camera.json)

    # the sections of the swarm file (cli.swarm_file), which every robot gets:
    [topology]                                 # protocol.membership.TopologyConfig
    kind = "ring"                              # full | ring | star | line | edges (+ edges = [[1, 2]], hub = 1)
    [training]                                 # agent.swarm.SwarmTrainingConfig: rounds, steps_per_round,
    rounds = 8                                 # [training.consensus] rho0 ..., [training.train.*]
    [daemon]                                   # agent.daemon.DaemonConfig (round_timeout_s, threads ...)
    [network]                                  # protocol.transport.TransportConfig (lease_ms, ...)
    [align]                                    # agent.align.AlignConfig
    [sfm]                                      # agent.data.sfm.SfmConfig
    [data.ros]                                 # agent.data.ros.RosBagConfig (robots recording bags)
    [security]                                 # protocol.pki.SecurityConfig: mutual TLS + access
    # insecure = true                          # control unless this says plain TCP (announced by `up`)

    [faults]                                   # rounds count from 0
    kill = [{ robot = 3, round = 2 }]          # SIGKILL robot 3 when the swarm reaches round 2
    restart = [{ robot = 3, round = 4 }]       # start it again on the same run dir (it resumes)
    freeze = [{ robot = 2, round = 3, seconds = 5 }]  # SIGSTOP robot 2 for 5 s (or `rounds = 3`), then SIGCONT
    cut = [{ link = [1, 2], from_round = 2, to_round = 4 }]                  # netns only
    netem = [{ link = [2, 3], from_round = 1, delay_ms = 100, loss = 0.1 }]  # netns only

    [baseline]
    enabled = true                             # also train the centralised model and each robot alone
    [record]                                   # robots run from ROS 2 bags of their views (RecordSpec)
    # enabled = true; reverse = [2]            # ... robot 2's bag walks its views last to first
    # replay = true                            # ... and they train while the bags play (up --replay)
    [report]
    eval_every = 1                             # evaluate rounds/<k>.safetensors every k-th round
    orbit_frames = 36                          # orbit.gif of the reference's final model (0 = none)
    # orbit_all_robots = true                  # ... and of every other robot's, side by side
    [run]
    mode = "local"                             # or netns, compose (root); timeout_s = 600 ...

"Round k" in the timeline means: as soon as every running robot has completed k rounds
(rounds count from 0; the slowest sets the pace). ``to_round`` is when the fault ends (the link is healed or made clean
again); without it the fault lasts until the end.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from agent.align import AlignConfig
from agent.daemon import DaemonConfig
from agent.frames import frames_of_split, resolve_pose_settings
from agent.data.config import DataConfig
from agent.data.sfm import SfmConfig
from agent.data.split import SplitConfig
from agent.swarm import SwarmTrainingConfig
from cli.config import ConfigError, from_dict, load_toml
from protocol.membership import Topology, TopologyConfig
from protocol.pki import SecurityConfig
from protocol.transport import TransportConfig

__all__ = [
    "KillFault",
    "RestartFault",
    "CutFault",
    "NetemFault",
    "FaultsSpec",
    "BaselineSpec",
    "ReportSpec",
    "RunSpec",
    "ScenarioSpec",
    "load_scenario",
    "find_scenario",
    "list_scenarios",
    "repo_root",
    "scenarios_dir",
    "resolve_dataset",
]

Mode = Literal["local", "netns", "compose"]


def repo_root() -> Path:
    """The checkout this package runs from (scenario datasets are relative to it)."""
    return Path(__file__).resolve().parents[2]


def scenarios_dir() -> Path:
    """The named scenarios: package data of ``scenarios`` (a checkout's folder, or the installed copy)."""
    import scenarios

    return Path(scenarios.__file__).resolve().parent


@dataclass
class KillFault:
    """SIGKILL ``robot`` when the swarm reaches ``round`` (no goodbye: a crash or power loss)."""

    robot: int
    round: int


@dataclass
class RestartFault:
    """Start ``robot`` again on its run dir when the swarm reaches ``round`` (it resumes)."""

    robot: int
    round: int


@dataclass
class FreezeFault:
    """SIGSTOP ``robot`` at ``round`` and SIGCONT it ``seconds`` later, or once every other running
    robot is ``rounds`` rounds past it, whichever comes first: a robot that hangs (no goodbye; its
    lease expires) and then comes back, rounds behind, with its old state. ``rounds`` makes "how
    far behind" the same on a fast machine and a slow one."""

    robot: int
    round: int
    seconds: float = 0.0  # 0: no time limit (then rounds must be set)
    rounds: int = 0  # 0: no round limit (then seconds must be set)

    def __post_init__(self) -> None:
        if self.seconds < 0 or self.rounds < 0 or not (self.seconds > 0 or self.rounds > 0):
            raise ValueError(f"faults.freeze of robot {self.robot}: set seconds > 0 and/or rounds > 0")

    def describe(self) -> str:
        limits = [f"{self.seconds:g} s"] * (self.seconds > 0) + [f"{self.rounds} rounds of the others"] * (self.rounds > 0)
        return f"freeze robot {self.robot} for {' or '.join(limits)}"


@dataclass
class CutFault:
    """Link a-b down (``ip link set down`` on both ends) from ``from_round`` until ``to_round``."""

    link: tuple[int, int]
    from_round: int
    to_round: int | None = None


@dataclass
class NetemFault:
    """Delay/jitter/loss and a rate cap on link a-b (both directions) from ``from_round`` until ``to_round``.

    ``delay_ms`` is one-way (a round trip gets twice), ``loss`` a fraction in [0, 1) per packet,
    ``rate_mbit`` the link's capacity in each direction (0: none; a robots' wireless mesh has a
    few to a few tens of Mbit/s, from round 0 it is the link itself).
    """

    link: tuple[int, int]
    from_round: int
    to_round: int | None = None
    delay_ms: float = 0.0
    jitter_ms: float = 0.0
    loss: float = 0.0
    rate_mbit: float = 0.0

    def __post_init__(self) -> None:
        if self.delay_ms < 0 or self.jitter_ms < 0:
            raise ValueError(f"netem on link {list(self.link)}: delay_ms and jitter_ms must be >= 0")
        if self.jitter_ms > self.delay_ms:
            raise ValueError(f"netem on link {list(self.link)}: jitter_ms ({self.jitter_ms}) must not exceed delay_ms")
        if not 0.0 <= self.loss < 1.0:
            raise ValueError(f"netem on link {list(self.link)}: loss is a fraction in [0, 1), got {self.loss}")
        if self.rate_mbit < 0:
            raise ValueError(f"netem on link {list(self.link)}: rate_mbit must be >= 0 (0: no cap)")
        if self.delay_ms == 0 and self.loss == 0 and self.rate_mbit == 0:
            raise ValueError(f"netem on link {list(self.link)}: set delay_ms, loss and/or rate_mbit")


@dataclass
class FaultsSpec:
    kill: list[KillFault] = field(default_factory=list)
    restart: list[RestartFault] = field(default_factory=list)
    freeze: list[FreezeFault] = field(default_factory=list)
    cut: list[CutFault] = field(default_factory=list)
    netem: list[NetemFault] = field(default_factory=list)

    @property
    def needs_netns(self) -> bool:
        return bool(self.cut or self.netem)

    def counts(self) -> dict[str, int]:
        """Faults per kind, in timeline order of the fields (only the kinds present)."""
        return {f.name: len(getattr(self, f.name)) for f in dataclasses.fields(self) if getattr(self, f.name)}

    @property
    def empty(self) -> bool:
        return not self.counts()


@dataclass
class BaselineSpec:
    """The report's points of comparison, trained in-process after the swarm has finished."""

    enabled: bool = False  # the centralised model on every robot's views, true poses
    alone: bool = True  # with enabled: also each robot alone on its own views (true pose, no consensus)
    steps: int | None = None  # default: the swarm's total_steps (rounds * steps_per_round)
    # reuse baselines trained before on the same data, settings and code (agent.evaluation.baseline_cache)
    reuse: bool = True


@dataclass
class ReportSpec:
    eval_every: int = 1  # evaluate the snapshot of every k-th round (and always the last)
    ssim: bool = True
    render_views: int = 3  # held-out views on the render sheet
    threads: int = 1  # torch threads for the evaluation (1 beats 2 on a busy 2-core machine)
    workers: int = 2  # processes scoring the rounds' snapshots, one thread each (the same scores; 1 = here);
    # the baselines' robots alone as many, or the centralised model's threads when they are off
    # Also score each robot's final model with every held-out view's pose fitted to its image
    # (agent.evaluation.fit_view_pose), as pose-free NeRF is evaluated; 0 = off. For SfM frames.
    fit_heldout_poses_steps: int = 0
    # Also score each robot's final field on every k-th of its own training views, through its own
    # (refined) cameras: well below what the robot reaches alone, the shared field cannot hold its
    # views (cameras that disagree, a box that clips the scene). 0 = off.
    own_views_every: int = 4
    # orbit.gif: the reference's final model along an orbit of this many frames at the held-out
    # views' width (~3 s of CPU for 36 frames at 48 px), or every robot's side by side. 0 = none.
    orbit_frames: int = 36
    orbit_all_robots: bool = False

    def __post_init__(self) -> None:
        if (self.eval_every < 1 or self.render_views < 0 or self.threads < 1 or self.workers < 1
                or self.fit_heldout_poses_steps < 0 or self.own_views_every < 0 or self.orbit_frames < 0):
            raise ValueError("report: eval_every >= 1, render_views >= 0, threads >= 1, workers >= 1, "
                             "fit_heldout_poses_steps >= 0, own_views_every >= 0, orbit_frames >= 0")


@dataclass
class RecordSpec:
    """Robots that record ROS 2 bags of their views and run from them (cli.scenario.recordings): each
    in its own odometry frame, with ``init``'s swarm file (local frames, no scene file)."""

    enabled: bool = False
    storage: list[Literal["mcap", "sqlite3"]] = field(default_factory=lambda: ["mcap", "sqlite3"])  # per robot, in turn
    image_rate_hz: float = 10.0
    tf_rate_factor: int = 20  # /tf at this multiple of the image rate
    encoding: Literal["rgb8", "bgr8", "rgba8", "bgra8", "mono8", "mono16", "jpeg", "png"] = "rgb8"  # png/rgba8: masks
    k1: float = 0.04  # a pincushion lens put into the pixels and declared in CameraInfo
    mount_tilt_deg: float = 15.0
    offset_translation: float = 1.0  # each odometry frame: a random rotation and a shift this long
    seed: int = 0
    reverse: list[int] = field(default_factory=list)  # robots that record their views last to first (paths that meet late)
    replay: bool = False  # robots train while their bag plays (`up --replay`), not from all of it at start
    replay_pace: float = 1.0  # --replay: this multiple of the recorded pace

    def __post_init__(self) -> None:
        if not self.storage or self.image_rate_hz <= 0 or self.tf_rate_factor < 2 or self.k1 < 0:
            raise ValueError("record: storage must list mcap/sqlite3, image_rate_hz > 0, tf_rate_factor >= 2, k1 >= 0")
        if self.replay_pace <= 0:
            raise ValueError("record: replay_pace must be > 0 (1.0: as recorded)")


@dataclass
class RunSpec:
    mode: Mode = "local"  # local: loopback processes; netns: a network namespace per robot; compose: a container (root)
    timeout_s: float = 900.0  # the whole swarm run, start to done
    impair: Literal["auto", "netem", "relay"] = "auto"  # how [[faults.netem]] is done, see cli.scenario.netns

    def __post_init__(self) -> None:
        if self.timeout_s <= 0:
            raise ValueError("run: timeout_s must be > 0")


@dataclass
class ScenarioSpec:
    name: str
    dataset: str = "procedural"
    width: int | None = None
    robots: int = 3  # ids 1..robots (the split's robots)
    description: str = ""
    credit: str = ""  # the data's attribution (a CC BY capture's), printed at the top of the report
    split: SplitConfig = field(default_factory=SplitConfig)
    # the sections every robot's swarm file gets (cli.swarm_file.SwarmFile), under the same names
    topology: TopologyConfig = field(default_factory=TopologyConfig)
    network: TransportConfig = field(default_factory=TransportConfig)
    training: SwarmTrainingConfig = field(default_factory=SwarmTrainingConfig)
    daemon: DaemonConfig = field(default_factory=DaemonConfig)
    align: AlignConfig = field(default_factory=AlignConfig)
    sfm: SfmConfig = field(default_factory=SfmConfig)
    data: DataConfig = field(default_factory=DataConfig)
    security: SecurityConfig = field(default_factory=SecurityConfig)
    faults: FaultsSpec = field(default_factory=FaultsSpec)
    baseline: BaselineSpec = field(default_factory=BaselineSpec)
    report: ReportSpec = field(default_factory=ReportSpec)
    record: RecordSpec = field(default_factory=RecordSpec)
    run: RunSpec = field(default_factory=RunSpec)
    path: Path | None = None  # the scenario.toml it came from (not a TOML key)
    # [training.train] as the file (and --set) gave it: what agent.defaults fills once the capture is
    # known (after the split) leaves these alone (not a TOML key)
    given_train: dict[str, Any] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        if self.robots < 1:
            raise ValueError(f"robots must be >= 1, got {self.robots}")
        if self.width is not None and self.width < 8:
            raise ValueError(f"width must be >= 8, got {self.width}")
        if self.split.robots != self.robots or self.split.ids is not None:
            self.split = dataclasses.replace(self.split, robots=self.robots, ids=None)  # ids 1..robots
        self._check_images()
        self.training, self.daemon = resolve_pose_settings(self.frames, self.training, self.daemon)
        self.graph()  # validates kind/edges/hub against the ids
        self.network.validate()
        self.align.for_pose_mode(self.training.train.pose.mode)
        self._check_faults()

    # --- derived ------------------------------------------------------------------------------
    @property
    def ids(self) -> list[int]:
        return list(range(1, self.robots + 1))

    @property
    def frames(self) -> str:
        """The frames the robots' poses are in (agent.frames): the split's, or their bags' odometry frames."""
        if self.record.enabled:
            return "local"
        return frames_of_split(self.split.frame, self.split.images_only)

    @property
    def reference_id(self) -> int:
        return min(self.ids)

    @property
    def rounds(self) -> int:
        return int(self.training.rounds)

    def graph(self) -> Topology:
        return self.topology.build(self.ids)

    @property
    def links(self) -> list[tuple[int, int]]:
        return list(self.graph().edges)

    # --- validation -------------------------------------------------------------------------------
    def _check_images(self) -> None:
        """Robot image width and images-only robots: what they need, said rather than overridden."""
        if self.record.enabled and self.split.images_only:
            raise ValueError("record.enabled: the robots record bags with their poses; split.images_only must be false")
        if (self.record.replay or self.record.reverse) and not self.record.enabled:
            raise ValueError("record.replay and record.reverse are about the robots' bags: they need record.enabled")
        if not set(self.record.reverse) <= set(self.ids):
            raise ValueError(f"record.reverse: {sorted(set(self.record.reverse) - set(self.ids))} not among the robots")
        w = self.split.robot_image_width
        if w is not None:
            if self.width is None:
                raise ValueError("split.robot_image_width needs scenario.width (the width of the held-out views "
                                 "and of the centralised baseline)")
            if w < self.width:
                raise ValueError(f"split.robot_image_width ({w}) must be >= scenario.width ({self.width}): it is "
                                 "for giving the robots more pixels than the evaluation, not fewer")

    def _check_faults(self) -> None:
        ids, rounds = set(self.ids), self.rounds
        links = set(self.links)

        def link_of(link: tuple[int, int], what: str) -> tuple[int, int]:
            a, b = link
            for r in (a, b):
                if r not in ids:
                    raise ValueError(f"{what}: robot {r} is not one of the robots {sorted(ids)}")
            key = (min(a, b), max(a, b))
            if key not in links:
                raise ValueError(f"{what}: link {a}-{b} is not in the {self.topology.kind} topology (links: "
                                 f"{', '.join(f'{x}-{y}' for x, y in sorted(links))})")
            return key

        def window(frm: int, to: int | None, what: str) -> None:
            if not 0 <= frm < rounds:
                raise ValueError(f"{what}: from_round {frm} is outside the run's rounds 0..{rounds - 1}")
            if to is not None and not frm < to <= rounds:
                raise ValueError(f"{what}: to_round {to} must be after from_round {frm} and <= rounds ({rounds})")

        for kind in ("kill", "restart", "freeze"):  # the faults of one robot at one round
            for f in getattr(self.faults, kind):
                if f.robot not in ids:
                    raise ValueError(f"faults.{kind}: robot {f.robot} is not one of the robots {sorted(ids)}")
                if not 0 <= f.round < rounds:
                    raise ValueError(f"faults.{kind}: round {f.round} of robot {f.robot} is outside 0..{rounds - 1}")
        for r in ids:  # kills and restarts of one robot must alternate, starting with a kill
            events = sorted([(f.round, 1, "kill") for f in self.faults.kill if f.robot == r]
                            + [(f.round, 0, "restart") for f in self.faults.restart if f.robot == r])
            alive = True
            for rnd, _, kind in events:
                if (kind == "kill") != alive:
                    raise ValueError(f"faults: robot {r} gets a {kind} at round {rnd} while it is "
                                     f"{'alive' if alive else 'already dead'}; kills and restarts must alternate")
                alive = kind == "restart"
        for f in self.faults.cut:
            link_of(f.link, "faults.cut")
            window(f.from_round, f.to_round, f"faults.cut {f.link[0]}-{f.link[1]}")
        for f in self.faults.netem:
            link_of(f.link, "faults.netem")
            window(f.from_round, f.to_round, f"faults.netem {f.link[0]}-{f.link[1]}")
        for kind, items in (("cut", self.faults.cut), ("netem", self.faults.netem)):
            by_link: dict[tuple[int, int], list] = {}
            for f in items:
                by_link.setdefault((min(f.link), max(f.link)), []).append(f)
            for key, fs in by_link.items():
                fs.sort(key=lambda f: f.from_round)
                for x, y in zip(fs, fs[1:]):
                    if x.to_round is None or x.to_round > y.from_round:
                        raise ValueError(f"faults.{kind}: two windows on link {key[0]}-{key[1]} overlap")

    def check_mode(self, mode: str) -> None:
        """Link faults need real links: a clear error instead of a run that silently ignores them."""
        if mode not in ("local", "netns", "compose"):
            raise ConfigError(f"mode must be local, netns or compose, got {mode!r}")
        if mode == "local" and self.faults.needs_netns:
            kinds = [k for k in ("cut", "netem") if getattr(self.faults, k)]
            raise ConfigError(f"scenario {self.name!r} has link faults ({', '.join(kinds)}): they need --mode netns "
                              "or compose (as root)")

    def resolved_dataset(self) -> str:
        return resolve_dataset(self.dataset, self.path.parent if self.path else None)

    def needs_files(self) -> bool:
        return not self.dataset.startswith("procedural")


def resolve_dataset(dataset: str, scenario_dir: Path | None = None) -> str:
    """``procedural[:...]`` as is; a relative path against the repo, then the scenario folder, then cwd.

    Raises FileNotFoundError naming every place looked at.
    """
    if dataset == "procedural" or dataset.startswith("procedural:"):
        return dataset
    p = Path(dataset).expanduser()
    candidates = [p] if p.is_absolute() else [repo_root() / p] + ([scenario_dir / p] if scenario_dir else []) + [Path.cwd() / p]
    for c in candidates:
        if c.exists():
            return str(c.resolve())
    raise FileNotFoundError(f"dataset {dataset!r} not found (looked at {', '.join(str(c) for c in candidates)})")


def load_scenario(path: str | Path) -> ScenarioSpec:
    """Read and validate one ``scenario.toml`` (a file, or a folder holding one)."""
    path = Path(path)
    if path.is_dir():
        path = path / "scenario.toml"
    data = load_toml(path)
    top = data.pop("scenario", None)
    if not isinstance(top, dict):
        raise ConfigError(f"{path}: needs a [scenario] table with at least name and dataset")
    overlap = sorted(set(top) & set(data))
    if overlap:
        raise ConfigError(f"{path}: {overlap} given both in [scenario] and as a table")
    _refuse_owned_keys(path, data)
    try:
        spec = from_dict(ScenarioSpec, {**top, **data})
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from None
    spec.path = path.resolve()
    spec.given_train = dict((data.get("training") or {}).get("train") or {})
    return spec


def _refuse_owned_keys(path: Path, data: dict[str, Any]) -> None:
    """Keys a scenario may not set, since the runner sets them per robot: said, not overridden."""
    for key in ("listen", "connect", "endpoints"):
        if key in (data.get("network") or {}):
            raise ConfigError(f"{path}: network.{key} is set by the scenario runner (one endpoint per robot "
                              "and link); remove it")
    for key in ("robots", "ids"):
        if key in (data.get("split") or {}):
            raise ConfigError(f"{path}: split.{key}: the robots are [scenario] robots = N (ids 1..N)")


def list_scenarios(root: Path | None = None) -> list[Path]:
    root = root or scenarios_dir()
    return sorted(p.parent for p in root.glob("*/scenario.toml"))


def find_scenario(name_or_path: str) -> Path:
    """A scenario by name (a folder of ``scenarios/``) or by path (folder or toml file)."""
    p = Path(name_or_path)
    if p.suffix == ".toml" and p.is_file():
        return p
    if (p / "scenario.toml").is_file():
        return p / "scenario.toml"
    q = scenarios_dir() / name_or_path / "scenario.toml"
    if q.is_file():
        return q
    known = ", ".join(d.name for d in list_scenarios()) or "none"
    raise FileNotFoundError(f"no scenario {name_or_path!r} (neither a path nor a folder of {scenarios_dir()}; known: {known})")


def spec_to_dict(spec: ScenarioSpec) -> dict[str, Any]:
    """The spec as plain data (for report.json)."""
    from cli.config import to_dict

    d = {f.name: to_dict(getattr(spec, f.name)) for f in dataclasses.fields(spec) if f.name not in ("path", "given_train")}
    d["path"] = str(spec.path) if spec.path else None
    return d
