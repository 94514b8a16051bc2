"""``dinerf-agent init``: a swarm for robots that already have their own recordings (no split)."""

from __future__ import annotations

from pathlib import Path

import typer

from cli.errors import UserError, friendly_errors
from cli.main import app


@app.command()
@friendly_errors
def init(
    out: Path = typer.Option(..., "--out", help="The swarm's folder: swarm.toml, ca/ (keep it private), "
                             "robot<id>/tls/ (one per robot, to copy to it), monitor/ (for `status`)."),
    robots: str = typer.Option(None, "--robots", help="Robot ids on this machine, e.g. 1,2,3 (loopback endpoints)."),
    robot: list[str] = typer.Option([], "--robot", help="ID=HOST[:PORT]: a robot on another machine and where it "
                                    "listens (repeatable; the port defaults to --port-base + ID)."),
    name: str = typer.Option(None, "--name", help="The swarm's name (default: --out's folder name)."),
    frames: str = typer.Option("local", "--frames", help="Where the robots' poses are: local (each robot's own "
                               "odometry frame; poses learnt), shared (one frame for all), sfm (images only)."),
    topology: str = typer.Option("full", "--topology", help="Who talks to whom: full | ring | star | line."),
    port_base: int = typer.Option(7500, "--port-base", help="Robot i listens on port base + i unless given."),
    width: int = typer.Option(100, "--width", help="The robots train on their images downscaled to this width "
                              "([training] image_width): it decides the field and sampler (agent.defaults)."),
    bounded: bool = typer.Option(False, "--bounded", help="The recordings show an object alone (alpha or masks): a "
                                 "bounded field. Default: cameras that see their surroundings, an unbounded field."),
    rounds: int = typer.Option(None, "--rounds", help="[training] rounds (default: SwarmTrainingConfig's)."),
    steps: int = typer.Option(None, "--steps", help="[training] steps_per_round (default: SwarmTrainingConfig's)."),
    insecure: bool = typer.Option(False, "--insecure", help="Plain TCP, no certificates: anyone who reaches a port "
                                  "can join and speak as any robot."),
    force: bool = typer.Option(False, "--force", help="Replace the swarm file and certificates already in --out."),
) -> None:
    """Make a swarm for robots with their own data (folders or ROS 2 bags): its CA, a certificate per robot
    and for the monitor, and swarm.toml; then say what to copy to each robot and what to run there."""
    from cli.config import ConfigError
    from cli.swarm_file import SWARM_FILE, init_swarm, parse_robot_endpoint

    endpoints: dict[int, str] = {}
    try:
        for text in robot:
            rid, where = parse_robot_endpoint(text, port_base)
            if rid in endpoints:
                raise ConfigError(f"--robot: robot {rid} given twice")
            endpoints[rid] = where
        for item in filter(None, (robots or "").split(",")):
            if not item.strip().isdigit() or int(item) < 1:
                raise ConfigError(f"--robots {robots!r}: expected ids >= 1 separated by commas, e.g. 1,2,3")
            endpoints.setdefault(int(item), f"127.0.0.1:{port_base + int(item)}")
    except ConfigError as e:
        raise UserError(str(e)) from None
    if not endpoints:
        raise UserError("give the robots: --robots 1,2,3 (this machine) and/or --robot ID=HOST[:PORT] (repeatable)")
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out}: exists and is not a folder")
    if (out / SWARM_FILE).exists() and not force:
        raise UserError(f"{out / SWARM_FILE} exists: a swarm is already there (pass --force to make a new one, with a "
                        "new CA: every robot then needs its new certificate)")
    name = name or "".join(c if c.isalnum() or c in "-_" else "-" for c in out.resolve().name) or "swarm"
    if width < 8:
        raise UserError(f"--width must be >= 8 pixels, got {width}")
    training = {k: v for k, v in (("rounds", rounds), ("steps_per_round", steps)) if v is not None}
    # every robot must build the same field: the swarm file says what the images are, not each robot's own
    training.update(image_width=width, train={"field": {"unbounded": not bounded}})
    path = init_swarm(out, name, endpoints, frames=frames, topology=topology, insecure=insecure, training=training)
    typer.echo(f"swarm '{name}': robots {sorted(endpoints)}, {topology} topology, frames {frames}, "
               f"{'bounded' if bounded else 'unbounded'} field at {width} px -> {path}")
    for i in sorted(endpoints):
        what = f"{out}/swarm.toml" + ("" if insecure else f" and {out}/robot{i}/tls/")
        tls = "" if insecure else " --tls tls"
        typer.echo(f"robot {i} (listens on {endpoints[i]}): copy {what} to it, then run there: dinerf-agent up "
                   f"--id {i} --data <its recording> --swarm swarm.toml{tls}")
    if not insecure:
        typer.echo(f"watch with: dinerf-agent status --swarm {out}/swarm.toml (its certificate: {out}/monitor/); "
                   f"{out}/ca/ holds the swarm CA's key: keep it here, never copy it to a robot; add a robot with "
                   f"dinerf-agent cert issue --swarm {out}/swarm.toml --id <id>")
