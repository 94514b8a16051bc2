"""``dinerf-agent up``: run one robot's daemon until the swarm's rounds are done."""

from __future__ import annotations

import signal
import sys
from pathlib import Path

import typer

from cli.errors import UserError, friendly_errors
from cli.logs import LOGGER
from cli.main import app

_log = LOGGER.info
_EXIT_ON = {signal.SIGINT: 130, signal.SIGTERM: 143}  # 128 + the signal, as shells report it


@app.command()
@friendly_errors
def up(
    robot_id: int = typer.Option(..., "--id", help="This robot's id (one of the robots listed in the swarm file)."),
    data: Path = typer.Option(..., "--data", help="This robot's recording: a folder (transforms.json, COLMAP, LLFF, "
                              "images only, or one from `split`) or a ROS 2 bag (rosbag2 folder, .mcap, .db3)."),
    swarm: Path = typer.Option(None, "--swarm", help="Swarm TOML (default: swarm.toml beside or inside --data)."),
    tls: Path = typer.Option(None, "--tls", help="This robot's certificate folder (default: tls/ inside a data "
                             "folder, else beside the data)."),
    run_dir: Path = typer.Option(None, "--run-dir", help="Checkpoints and telemetry (default: runs/<swarm>/robot<id>)."),
    listen: list[str] = typer.Option([], "--listen", help="Zenoh endpoint to listen on (repeatable)."),
    connect: list[str] = typer.Option([], "--connect", help="Zenoh endpoint to connect to (repeatable)."),
    overrides: list[str] = typer.Option([], "--set", help="Override a swarm-file setting, e.g. --set training.rounds=5 (repeatable)."),
    replay: float = typer.Option(None, "--replay", help="Train while the bag --data plays at this multiple of its "
                                 "recorded pace (1.0: real time): its keyframes join as they arrive ([data.stream])."),
    live: list[str] = typer.Option([], "--live", help="Train while this robot's camera streams over Zenoh: its "
                                   "local router (rmw_zenoh, e.g. tcp/localhost:7447); --data holds its swarm file."),
) -> None:
    """Join the swarm and train: one robot's daemon (resumes from --run-dir if it holds a checkpoint)."""
    from agent.checkpoint import RunFolder
    from cli.config import to_dict
    from cli.scenario.tomlout import dumps
    from cli.swarm_file import find_swarm_file, load_swarm_file, robot_tls_dir
    from cli.options import check_output_folder

    _check_data(data, replay, live)
    swarm_path = swarm or find_swarm_file(data)
    if swarm_path is None:
        raise UserError(f"no --swarm given and no swarm.toml beside or inside {data}")
    cfg, base_dir = load_swarm_file(swarm_path, overrides)
    if robot_id not in cfg.swarm.robots:
        raise UserError(f"--id {robot_id} is not one of the swarm's robots {cfg.swarm.robots} ({swarm_path})")
    box = _field_box(cfg, base_dir, swarm_path)
    run_dir = run_dir or Path("runs") / cfg.swarm.name / f"robot{robot_id}"
    check_output_folder(run_dir, "--run-dir")
    tls_dir = tls if tls is not None else robot_tls_dir(data, cfg.security.tls_dir)
    transport_cfg = cfg.transport_for(robot_id, listen, connect, tls_dir=tls_dir)  # checks the certificate first
    folder = RunFolder(run_dir, create=False)  # made once the data loaded: bad data leaves no run folder
    source, views, summary_views = _load_views(robot_id, cfg, data, folder, replay, live)
    run_folder = RunFolder(run_dir)
    # render/eval/export find the views through it (a stream's: the keyframes it kept, not its source)
    run_folder.write_data_record(data if source is None else folder.keyframe_cache, swarm_path)
    run_folder.write_config(dumps(to_dict(cfg), show_unset=True))  # what it runs with, agent.defaults fitted
    if views.meta.get("bag_settings_changed"):
        LOGGER.warning(f"[robot {robot_id}] {views.meta['notes'][-1]}")
    try:
        _run_daemon(robot_id, cfg, transport_cfg, views, summary_views, box, run_dir, source)
    finally:
        if source is not None:
            source.close()


def _check_data(data: Path, replay: float | None, live: list[str]) -> None:
    from agent.data.ros import is_bag

    if not data.exists():
        raise UserError(f"--data {data}: no such file or folder (expected the robot's recording: a data folder or a "
                        "ROS 2 bag)")
    if data.is_file() and not is_bag(data):
        raise UserError(f"--data {data}: not a folder or a ROS 2 bag file (.mcap, .db3)")
    if replay is not None and (live or not is_bag(data)):
        raise UserError("--replay plays the ROS 2 bag given as --data; it does not go with --live" if live else
                        f"--replay: --data {data} is not a ROS 2 bag (rosbag2 folder, .mcap, .db3)")


def _field_box(cfg, base_dir: Path, swarm_path: Path):
    """The swarm's field box [4, 4], or None without a scene file (`init`: robots with their own
    recordings), where the reference derives it from its own views."""
    from agent.data.folder import read_scene

    box = read_scene(base_dir / cfg.swarm.scene).box_from_shared if cfg.swarm.scene else None
    if box is None and cfg.daemon.initial_pose != "coarse":
        raise UserError(f"{swarm_path}: the swarm has no field box (no scene file, or robots with images only): set "
                        "daemon.initial_pose = 'coarse' so that the reference shares the box of its own frame")
    return box


def _load_views(robot_id: int, cfg, data: Path, folder, replay: float | None, live: list[str]):
    """(stream source or None, the views to start with, the views of the keyframe summary or None).

    Images only: SfM on the full-size images (cached); a bag: its keyframes (cached); then
    downscaled. A stream: its first keyframes make the box and the summary."""
    from cli.options import progress_listener
    from cli.view_source import start_stream

    if replay is not None or live:
        started = start_stream(cfg, data, folder.keyframe_cache, replay, live, lambda t: _log(f"[robot {robot_id}] {t}"))
        return started
    with progress_listener():
        views = folder.load_views(data, cfg.training.image_width, sfm=cfg.sfm, ros=cfg.data.ros)
        summary_views = None  # the keyframe summary's features come from the sharper images when there are any
        if cfg.daemon.initial_pose == "coarse" and cfg.daemon.summary_width != cfg.training.image_width:
            full = folder.load_views(data, cfg.daemon.summary_width, sfm=cfg.sfm, ros=cfg.data.ros)
            summary_views = full if full.width != views.width else None
    return None, views, summary_views


def _run_daemon(robot_id: int, cfg, transport_cfg, views, summary_views, box, run_dir: Path, source) -> None:
    """Open the session, run the daemon to its last round; Ctrl-C / SIGTERM exit 130 / 143."""
    from agent.daemon import Daemon
    from protocol.keys import Keys
    from protocol.transport import TransportError, ZenohTransport

    try:
        transport = ZenohTransport(transport_cfg, Keys(cfg.swarm.name), robot_id).open()
    except TransportError as e:
        raise UserError(f"cannot open the Zenoh session: {e}") from None
    daemon = None
    stopped_by: list[int] = []

    def stop(signum: int, _frame) -> None:
        stopped_by.append(signum)
        daemon.stop()

    try:
        daemon = Daemon(robot_id, views, box, cfg.identity(), cfg.training, cfg.daemon,
                        transport, run_dir, log=_log, summary_views=summary_views, align=cfg.align,
                        warn=LOGGER.warning, stream=source.stream if source is not None else None)
        for sig in _EXIT_ON:
            signal.signal(sig, stop)
        (LOGGER.warning if cfg.security.insecure else _log)(_security_line(robot_id, cfg, transport_cfg))
        _log(f"[robot {robot_id}] up: swarm '{cfg.swarm.name}' ({cfg.topology.kind}: "
             f"neighbours {sorted(cfg.graph().neighbours(robot_id))}), "
             f"{source.stream.describe() if source else f'{len(views)} views'}, "
             f"listen {transport_cfg.listen}, connect {transport_cfg.connect}, run dir {run_dir}")
        daemon.run()
    except RuntimeError as e:  # e.g. an unusable checkpoint
        raise UserError(str(e)) from None
    finally:
        transport.close()
    sys.stdout.flush()
    if stopped_by:
        _log(f"[robot {robot_id}] stopped by {signal.Signals(stopped_by[0]).name}: the checkpoint of the last "
             f"completed round is kept in {run_dir}")
        raise typer.Exit(_EXIT_ON[stopped_by[0]])


def _security_line(robot_id: int, cfg, transport_cfg) -> str:
    """How this robot's links are protected, said first: an insecure swarm must not look like a secure one."""
    if cfg.security.insecure:
        return (f"[robot {robot_id}] WARNING: INSECURE SWARM ([security] insecure = true): no certificates, no access "
                "control; anyone who reaches a port can join, read every snapshot and speak as any robot")
    revoked = f", revoked {cfg.security.revoked}" if cfg.security.revoked else ""
    return (f"[robot {robot_id}] secure: mutual TLS as robot-{robot_id} ({transport_cfg.tls_cert}), access control: "
            f"each of robots {cfg.swarm.robots} may say only its own keys{revoked}")
