"""``dinerf-agent cert``: certificates of a secure swarm (issue one for a new robot, revoke one, show one)."""

from __future__ import annotations

from pathlib import Path

import typer

from cli.errors import UserError, friendly_errors
from cli.main import app

cert_app = typer.Typer(help="Certificates of a secure swarm: issue, revoke, show.", no_args_is_help=True)
app.add_typer(cert_app, name="cert")


@cert_app.command("issue")
@friendly_errors
def issue_cmd(
    ca: Path = typer.Option(None, "--ca", help="The swarm's CA folder (ca.pem, ca.key; default: ca/ beside --swarm)."),
    out: Path = typer.Option(None, "--out", help="Where the certificate goes: the robot's tls/ (ca.pem, cert.pem, "
                             "key.pem; default: robot<id>/tls/ beside --swarm)."),
    robot_id: int = typer.Option(None, "--id", help="The new robot's id (its certificate names robot-<id>)."),
    monitor: bool = typer.Option(False, "--monitor", help="A monitor certificate instead (for `dinerf-agent status`)."),
    swarm: Path = typer.Option(None, "--swarm", help="The swarm TOML: refuse an identity it revokes, and add a new "
                               "robot to its roster (robots and endpoint)."),
    host: list[str] = typer.Option([], "--host", help="A name or address the robot is reached at (repeatable); the "
                                   "first is its endpoint's host in --swarm."),
    port: int = typer.Option(None, "--port", help="The port the new robot listens on (default: on the pattern of the "
                             "other robots' endpoints)."),
    force: bool = typer.Option(False, help="Replace a certificate already in --out."),
) -> None:
    """Issue a certificate from the swarm CA, for a new robot (--id) or a monitor (--monitor); with --swarm, a new
    robot also joins the roster."""
    from cli.config import ConfigError
    from cli.swarm_file import add_robot, next_endpoint
    from protocol.pki import CERT, MONITOR_NAME, PkiError, describe, issue, robot_name

    if (robot_id is None) == (not monitor):
        raise UserError("give either --id <robot id> or --monitor")
    if ca is None or out is None:
        if swarm is None:
            raise UserError("give --ca and --out, or --swarm (the CA and the robot's tls/ beside the swarm file)")
        ca = ca or swarm.resolve().parent / "ca"
        out = out or swarm.resolve().parent / ("monitor" if monitor else f"robot{robot_id}/tls")
    try:
        name = MONITOR_NAME if monitor else robot_name(robot_id)
    except ValueError as e:
        raise UserError(f"--id: {e}") from None
    cfg = None
    if swarm is not None:
        cfg = _swarm(swarm)
        if name in cfg.security.revoked:
            raise UserError(f"{name} is revoked in {swarm}: a revoked identity stays revoked; give the robot a new id")
        if not monitor and robot_id not in cfg.swarm.robots:
            try:  # before anything is written: the endpoint must be known
                endpoint = next_endpoint(cfg, robot_id, host[0] if host else None, port)
            except ConfigError as e:
                raise UserError(str(e)) from None
    if (out / CERT).exists() and not force:
        raise UserError(f"{out / CERT} exists (pass --force to replace it)")
    try:
        info = describe(issue(ca, name, out, hosts=tuple(host)) / CERT)
    except PkiError as e:
        raise UserError(str(e)) from None
    typer.echo(f"issued {info.common_name} (serial {info.serial:x}, valid until {info.not_after[:10]}) in {out}")
    if monitor:
        return
    if cfg is not None and robot_id not in cfg.swarm.robots:
        add_robot(swarm, robot_id, endpoint)
        typer.echo(f"robot {robot_id} added to {swarm} (listens on {endpoint}): give every robot the new file and "
                   "restart them: a robot loads the roster and its access control when it starts")
    elif cfg is None:
        typer.echo(f"next: add {robot_id} to [swarm] robots (and its endpoint) in swarm.toml, give every robot the new "
                   "file and restart them: a robot loads the roster and its access control when it starts")


@cert_app.command("revoke")
@friendly_errors
def revoke_cmd(
    swarm: Path = typer.Option(..., "--swarm", help="The swarm TOML to add the identity to ([security] revoked)."),
    robot_id: int = typer.Option(None, "--id", help="The robot to revoke."),
    monitor: bool = typer.Option(False, "--monitor", help="Revoke the monitor certificate instead."),
) -> None:
    """Deny an identity in the swarm's access control (every robot must load the new swarm.toml)."""
    from cli.config import load_toml
    from cli.swarm_file import write_swarm_file
    from protocol.pki import MONITOR_NAME, robot_name

    if (robot_id is None) == (not monitor):
        raise UserError("give either --id <robot id> or --monitor")
    cfg = _swarm(swarm)
    if cfg.security.insecure:
        raise UserError(f"{swarm} is an insecure swarm ([security] insecure = true): there is nothing to revoke; "
                        "anyone who reaches a port is admitted")
    name = MONITOR_NAME if monitor else robot_name(robot_id)
    data = load_toml(swarm)
    security = data.setdefault("security", {})
    revoked = sorted(set(security.get("revoked", [])) | {name})
    security["revoked"] = revoked
    header = " ".join(line.lstrip("# ").strip() for line in swarm.read_text().splitlines()[:1] if line.startswith("#"))
    write_swarm_file(swarm, data, header=header)
    typer.echo(f"{name} is revoked in {swarm} (revoked: {', '.join(revoked)}).\n"
               "Give every robot the new swarm.toml and restart it: Zenoh's access control is fixed when a session "
               f"opens. {name} can still complete a TLS handshake (Zenoh's TLS checks no revocation list), but the "
               "robots that loaded the new file accept nothing it says or asks and send it nothing.")


@cert_app.command("show")
@friendly_errors
def show_cmd(path: Path = typer.Argument(..., help="A certificate (cert.pem) or a certificate folder.")) -> None:
    """Who a certificate names, who signed it, until when, and its fingerprint."""
    from protocol.pki import CERT, PkiError, describe

    try:
        info = describe(path / CERT if path.is_dir() else path)
    except PkiError as e:
        raise UserError(str(e)) from None
    typer.echo(f"{info.common_name}: issued by {info.issuer}, serial {info.serial:x}, valid until {info.not_after}, "
               f"sha256 {info.fingerprint}")


def _swarm(path: Path):
    from cli.swarm_file import load_swarm_file

    cfg, _ = load_swarm_file(path)
    return cfg
