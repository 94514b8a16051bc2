"""``dinerf-agent split`` and ``dinerf-agent inspect``: prepare robot folders, look at a dataset."""

from __future__ import annotations

import math
from pathlib import Path

import torch
import typer
from rich.console import Console
from rich.table import Table

from cli.errors import friendly_errors
from cli.main import app

from cli.options import DATA_HELP


def _write_split_swarm(out: Path, ids: list[int], cfg, topology: str, port_base: int, insecure: bool,
                       training: dict) -> None:
    """swarm.toml beside the robot folders, and (unless insecure) the swarm CA and certificates."""
    from agent.frames import frames_of_split
    from cli.swarm_file import SWARM_FILE, loopback_endpoints, security_sections, swarm_doc, write_swarm_file
    from protocol.pki import create_swarm_pki

    name = "".join(c if c.isalnum() or c in "-_" else "-" for c in out.resolve().name) or "swarm"
    if not insecure:
        create_swarm_pki(out, name, ids)
    sec = security_sections(insecure)
    network = {**sec["network"], "endpoints": loopback_endpoints(ids, port_base, tls=not insecure)}
    write_swarm_file(out / SWARM_FILE, swarm_doc(name, ids, frames_of_split(cfg.frame, cfg.images_only), topology,
                                                 network=network, training=training, security=sec["security"]),
                     header="written by `dinerf-agent split`; edit freely (see cli/swarm_file.py)")


@app.command()
@friendly_errors
def split(
    data: str = typer.Option(..., "--data", help=DATA_HELP),
    robots: int = typer.Option(2, "--robots", "-n", help="Number of robots (ids 1..N; the reference is 1)."),
    out: Path = typer.Option(..., "--out", help="Output folder (robot<id>/, eval/, truth.json, split.json, scene.json)."),
    by: str = typer.Option("sector", help="sector: sectors of azimuth (equal round a full circle, quantiles along an "
                           "arc) | trajectory: contiguous segments of the capture order."),
    overlap: float = typer.Option(0.0, help="Mean fraction of a robot's views shared with a neighbour, 0-0.4."),
    sector_start: float = typer.Option(0.0, "--sector-start", help="Azimuth (deg) where robot 1's sector begins, when "
                                       "the cameras surround the scene."),
    test_every: int = typer.Option(8, help="Every k-th view (0, k, 2k, ...) is a test view, seen by no robot; 0 = none."),
    frame: str = typer.Option("first_camera", help="Local frames: first_camera | offset | world | random."),
    width: int = typer.Option(None, help="Downscale images to this width (area interpolation)."),
    robot_image_width: int = typer.Option(None, help="Robot folders get images this wide instead (e.g. for their own "
                                          "SfM); the test views keep --width."),
    depth_prior: str = typer.Option("none", help="Depth written for robots: none | true | scaled (random a_m, b_m)."),
    max_scale: float = typer.Option(1.0, help="With --frame random: scale log-uniform in [1/x, x] (Sim(3)); 1 = SE(3)."),
    images_only: bool = typer.Option(False, help="Write robot images without poses (robots run their own SfM)."),
    calibrated_cameras: bool = typer.Option(False, help="With --images-only: also write each robot's camera focal "
                                            "length (camera.json), which its SfM then keeps fixed."),
    seed: int = typer.Option(0, help="Seed of the random frames and depth scale/shift."),
    sets: list[str] = typer.Option([], "--set", help="Any other field of [split] in scenario.toml (SplitConfig), TOML "
                                   "values, e.g. --set up=[0,0,1] --set offset_rotation_deg=[0,0,90] (repeatable)."),
    force: bool = typer.Option(False, help="Replace a previous split in --out."),
    topology: str = typer.Option("full", help="Topology written to swarm.toml: full | ring | star | line."),
    port_base: int = typer.Option(7500, help="swarm.toml endpoints: robot i listens on tls/127.0.0.1:<base+i>."),
    insecure: bool = typer.Option(False, "--insecure", help="Plain TCP, no certificates: anyone who reaches a port "
                                  "can join and speak as any robot. Default: a swarm CA in <out>/ca, a certificate "
                                  "per robot, mutual TLS and access control."),
    rounds: int = typer.Option(None, help="swarm.toml [training] rounds (default: agent.swarm.SwarmTrainingConfig's)."),
    steps: int = typer.Option(None, help="swarm.toml [training] steps_per_round (default: SwarmTrainingConfig's)."),
) -> None:
    """Split a dataset into N robot folders by sectors of view direction (Di-NeRF's setting) or by trajectory."""
    from agent.data.split import SplitConfig, split_dataset, write_split
    from cli.config import apply_overrides

    cfg = SplitConfig(
        robots=robots,
        by=by,  # type: ignore[arg-type]  # validated by SplitConfig
        overlap=overlap,
        sector_start_deg=sector_start,
        test_every=test_every,
        frame=frame,  # type: ignore[arg-type]
        depth_prior=depth_prior,  # type: ignore[arg-type]
        random_max_scale=max_scale,
        images_only=images_only,
        calibrated_cameras=calibrated_cameras,
        robot_image_width=robot_image_width,
        seed=seed,
    )
    cfg = apply_overrides(cfg, sets)
    views, result = split_dataset(data, cfg, width)
    write_split(result, out, overwrite=force)
    ids = sorted(result.robots)
    training = {k: v for k, v in (("rounds", rounds), ("steps_per_round", steps)) if v is not None}
    _write_split_swarm(Path(out), ids, cfg, topology, port_base, insecure, training)
    _print_split(result, f"{len(views)} views of {data} -> {out}")
    console = Console()
    console.print(f"scene box: {result.box_source}; depth prior: {cfg.depth_prior}; truth.json is for evaluation only")
    from agent.data.capture import capture_warnings

    for warning in capture_warnings(views, result.box_source):
        console.print(f"[yellow]warning:[/yellow] {warning}")
    console.print(f"swarm.toml: {topology} topology, loopback ports {port_base + ids[0]}..{port_base + ids[-1]}; "
                  f"start each robot with: dinerf-agent up --id <id> --data {out}/robot<id>")
    if insecure:
        console.print("[bold red]insecure swarm:[/bold red] plain TCP, no certificates (--insecure)")
    else:
        console.print(f"mutual TLS: robot<id>/tls/ holds each robot's certificate, monitor/ the one of `status`; "
                      f"{out}/ca/ holds the swarm CA's key: keep it private, never copy it to a robot")


_LAYOUTS = {
    "circle": "sectors of equal width round the scene",
    "arc": "the cameras cover an arc: sectors cut at quantiles of their azimuths",
    "trajectory": "contiguous segments of the capture order",
}


def _print_split(result, title: str) -> None:
    """The robots of a split (views, sector or azimuth span, overlap, local frame) and its test views."""
    from agent.geometry import sim3_decompose, so3_log

    cfg = result.config
    console = Console()
    table = Table(title=title)
    span = "azimuths (deg)" if result.layout == "trajectory" else "sector (deg)"
    for col in ("robot", "views", span, "overlap", "local frame (vs world)"):
        table.add_column(col)
    for rid, rob in result.robots.items():
        s, rot, t = sim3_decompose(rob.T_world_from_local)
        angle = math.degrees(float(so3_log(rot).norm()))
        desc = f"{cfg.frame}: {angle:.1f} deg, |t| {float(t.norm()):.2f}" + (f", s {float(s):.2f}" if abs(float(s) - 1) > 1e-4 else "")
        a, b = rob.sector_deg
        table.add_row(
            f"{rid}" + (" (ref)" if rid == result.reference_id else ""),
            str(len(rob.indices)),
            "all" if len(result.robots) == 1 and result.layout != "trajectory" else f"{a % 360:.0f} .. {b % 360:.0f}",
            f"{100 * rob.overlap:.0f}%",
            desc,
        )
    console.print(table)
    margin = (f"segments share {result.margin_views} views at each border" if result.layout == "trajectory"
              else f"sector margin {result.margin_deg:.1f} deg")
    n_eval = len(result.eval_indices)
    console.print(
        f"split by {cfg.by}: {_LAYOUTS[result.layout]}; overlap: mean {100 * result.mean_overlap:.1f}% "
        f"(asked {100 * cfg.overlap:.0f}%, {margin}); test views: {n_eval} (every {cfg.test_every}th from 0)"
        + (f", {sum(1 for s in result.seen_by if len(s) == 0)} seen by no robot" if n_eval else "")
    )


@app.command()
@friendly_errors
def inspect(
    data: str = typer.Option(..., "--data", help=DATA_HELP),
    width: int = typer.Option(None, help="Load at this width (as training would)."),
    undistort: bool = typer.Option(True, help="Undo lens distortion at load (--no-undistort: ignore it, as before)."),
) -> None:
    """Show what a dataset holds: views, size, masks, lens, intrinsics, depth, camera layout, bounds, scene box."""
    from agent.data.capture import capture_warnings, estimate_scene_box, mean_up, scene_center
    from agent.data.loaders import load_views

    from cli.options import progress_listener

    with progress_listener():
        v = load_views(data, width=width, undistort=undistort)
    console = Console()
    table = Table(title=str(data), show_header=False)
    table.add_column("what", style="bold")
    table.add_column("value")
    fmt = str(v.meta.get("format", "?"))
    table.add_row("format", fmt.upper() if fmt in ("llff", "colmap") else fmt)
    if isinstance(v.meta.get("bag"), dict):  # a ROS 2 bag: its streams, tf chain, what was kept and why
        from agent.data.ros import BagReport

        for what, value in BagReport(**v.meta["bag"]).lines():
            table.add_row(what, value)
    table.add_row("views", f"{len(v)} ({', '.join(v.names[:3])}{', ...' if len(v) > 3 else ''})")
    table.add_row("size", f"{v.width} x {v.height}, {'RGBA' if v.has_alpha else 'RGB'}")
    for what, value in _pixel_rows(v):
        table.add_row(what, value)
    if v.depth is None:
        table.add_row("depth", "none")
    else:
        known = v.depth > 0
        kind = v.meta.get("depth_kind", "sparse" if v.meta.get("depth_sparse") else "dense")
        rng = f", {float(v.depth[known].min()):.3f}-{float(v.depth[known].max()):.3f}" if bool(known.any()) else ""
        table.add_row("depth", f"{kind}: {100 * float(known.float().mean()):.2f}% of pixels known{rng}")
    centre = scene_center(v.c2w)
    dist = (v.c2w[:, :3, 3].to(torch.float64) - centre).norm(dim=-1)
    table.add_row(
        "cameras",
        f"centre of the optical axes {_fmt(centre)}, distance {float(dist.min()):.3f}-{float(dist.max()):.3f}, up {_fmt(mean_up(v.c2w))}",
    )
    table.add_row("near/far", _bounds_row(v))
    box_c, box_h, src = estimate_scene_box(v)
    table.add_row("scene box", f"centre {_fmt(box_c)}, half-size {box_h:.3f} (from the {_BOX_SOURCES.get(src, src)})")
    for note in v.meta.get("notes", []):
        table.add_row("note", note)
    for warning in capture_warnings(v, src):
        table.add_row("[yellow]warning[/yellow]", warning)
    console.print(table)


_BOX_SOURCES = {"dataset": "dataset", "depth": "depth maps", "bounds": "near/far bounds", "cameras": "cameras only"}


def _pixel_rows(v) -> list[tuple[str, str]]:
    """The rows of what the pixels are: alpha, masks, lens distortion, intrinsics."""
    from agent.camera import fov_from_focal

    rows = []
    if v.has_alpha:
        rows.append(("alpha", f"mean {float(v.images[..., 3].mean()):.3f} (objects cover this fraction of pixels)"))
    masks = v.meta.get("masks")
    if isinstance(masks, dict):
        folders = ", ".join(Path(f).name + "/" for f in masks.get("folders", []))
        where = "mask_path of transforms.json" if masks.get("from") == "mask_path" else folders
        rows.append(("masks", f"yes: {masks.get('count')} from {where}, composited as alpha; mean coverage "
                              f"{float(v.images[..., 3].mean()):.3f}"))
    else:
        rows.append(("masks", "no"))
    lens = v.meta.get("lens")
    if isinstance(lens, dict):
        rows.append(("distortion", f"{', '.join(lens.get('models', []))}: {lens.get('done')}"))
    else:
        rows.append(("distortion", "none (pinhole cameras)"))
    k = v.intrinsics
    fov = torch.rad2deg(fov_from_focal(v.width, k[:, 0]))
    uniq = "shared by all views" if bool((k == k[0]).all()) else "per view"
    rows.append((
        "intrinsics",
        f"fx {float(k[:, 0].min()):.2f}-{float(k[:, 0].max()):.2f}, fy {float(k[:, 1].min()):.2f}-{float(k[:, 1].max()):.2f}, "
        f"cx {float(k[:, 2].mean()):.2f}, cy {float(k[:, 3].mean()):.2f} ({uniq}); horizontal fov {float(fov.mean()):.1f} deg",
    ))
    return rows


def _bounds_row(v) -> str:
    from agent.data.capture import view_bounds

    b = view_bounds(v)
    if b is None:
        return "none"
    return (f"near {float(b[:, 0].min()):.3f}-{float(b[:, 0].max()):.3f}, far {float(b[:, 1].min()):.3f}-"
            f"{float(b[:, 1].max()):.3f} (per view, scene units)")


def _fmt(t: torch.Tensor) -> str:
    return "(" + ", ".join(f"{float(x):.3f}" for x in t) + ")"
