"""``dinerf-agent render | eval | export``: what a finished run gives its user (the logic is in agent.outputs)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import typer

from cli.errors import UserError, friendly_errors
from cli.main import app
from cli.options import RUN_DATA_HELP, RUN_HELP, check_output_folder, progress_bar, set_threads

ROBOT_HELP = "Which robot's field (default: the lowest id, the usual reference)."
ROUND_HELP = "Use the snapshot kept after this round (rounds/<k>) instead of the last checkpoint."
DEVICE_HELP = "Torch device to rebuild the field on (default: the one it trained on), e.g. cpu."


def _open(run_dir: Path, data: Path | None, threads: int):
    from agent.runs import open_run

    set_threads(threads)
    return open_run(run_dir, data)


def _checked(make, what: str):
    """A config dataclass built from options; its check failing is the user's to fix, in one line."""
    try:
        return make()
    except ValueError as e:
        raise UserError(f"{what}: {e}") from None


@app.command()
@friendly_errors
def render(
    run_dir: Path = typer.Argument(..., help=RUN_HELP),
    out: Path = typer.Option(None, "--out", help="Output folder (default: <RUN_DIR>/renders)."),
    robot: int = typer.Option(None, "--robot", help=ROBOT_HELP),
    cameras: Path = typer.Option(None, "--cameras", help="Render these views: a transforms.json or any dataset folder (its images must be there)."),
    frame: str = typer.Option("shared", "--frame", help="--cameras are in the shared frame, or the robot's local one."),
    orbit: int = typer.Option(None, "--orbit", help="Render N views on an orbit around the field's box (default 60)."),
    spiral: float = typer.Option(0.0, "--spiral", help="Orbit: the elevation swings +- this many degrees per turn."),
    elevation: float = typer.Option(None, "--elevation", help="Orbit: degrees (default: the robot's cameras' median)."),
    radius: float = typer.Option(None, "--radius", help="Orbit: shared-frame units (default: the cameras' median)."),
    width: int = typer.Option(None, "--width", help="Image width (default: the robot's images')."),
    video: str = typer.Option("gif", "--video", help="gif, mp4 or none."),
    fps: float = typer.Option(15.0, "--fps", help="Video frames per second."),
    round: int = typer.Option(None, "--round", help=ROUND_HELP),
    data: Path = typer.Option(None, "--data", help=RUN_DATA_HELP),
    device: str = typer.Option(None, "--device", help=DEVICE_HELP),
    threads: int = typer.Option(2, help="CPU threads for torch."),
) -> None:
    """Render colour and depth along an orbit/spiral or given cameras: PNGs and a GIF/MP4."""
    from agent.outputs.paths import OrbitConfig, trainer_orbit
    from agent.outputs.render import VIDEO_FORMATS, render_views, write_renders

    if cameras is not None and orbit is not None:
        raise UserError("give --cameras or --orbit, not both")
    if video not in VIDEO_FORMATS or not (math.isfinite(fps) and fps > 0) or frame not in ("shared", "local"):
        raise UserError(f"--video must be one of {', '.join(VIDEO_FORMATS)}, --fps > 0, --frame shared or local")
    if width is not None and width < 1:
        raise UserError(f"--width must be >= 1, got {width}")
    out = out or run_dir / "renders"
    check_output_folder(out, "--out")
    run = _open(run_dir, data, threads)
    rid = run.pick(robot)
    trainer = run.load(rid, round=round, device=device)
    if cameras is not None:
        c2w, k, w, h = _file_cameras(trainer, cameras, frame, width)
    else:
        cfg = _checked(lambda: OrbitConfig(frames=60 if orbit is None else orbit, elevation_deg=elevation,
                                           radius=radius, spiral_deg=spiral), "orbit")
        c2w, k, w, h = trainer_orbit(trainer, cfg, width)
    with progress_bar() as bar:
        task = bar.add_task(f"robot {rid}: rendering", total=len(c2w))
        views = render_views(trainer, c2w, k, w, h, on_view=lambda n: bar.update(task, completed=n))
    written = write_renders(out, views, video, fps)
    typer.echo(f"robot {rid}: {len(views)} views at {w}x{h} -> {out}/rgb, {out}/depth"
               + (f", {written['video']}" if "video" in written else ""))


def _file_cameras(trainer, cameras: Path, frame: str, width: int | None):
    """The views of a transforms.json (or any dataset) as shared-frame cameras: (c2w, intrinsics, w, h)."""
    from agent.data.loaders import load_views
    from agent.geometry import transform_c2w

    views = load_views(cameras, width=width)
    c2w = views.c2w
    if frame == "local":
        c2w = transform_c2w(trainer.pose.matrix().detach().cpu(), c2w.to(trainer.pose.matrix().dtype))
    return c2w.float(), views.intrinsics, views.width, views.height


@app.command("eval")
@friendly_errors
def eval_(
    run_dir: Path = typer.Argument(..., help=RUN_HELP),
    robot: int = typer.Option(None, "--robot", help="Score only this robot (default: every robot of the run)."),
    round: int = typer.Option(None, "--round", help=ROUND_HELP),
    ssim: bool = typer.Option(True, "--ssim/--no-ssim", help="Also compute SSIM."),
    json_out: Path = typer.Option(None, "--json", help="Also write the scores to this JSON file."),
    per_view: bool = typer.Option(True, "--per-view/--no-per-view", help="Print the per-view table."),
    data: Path = typer.Option(None, "--data", help=RUN_DATA_HELP),
    device: str = typer.Option(None, "--device", help=DEVICE_HELP),
    threads: int = typer.Option(2, help="CPU threads for torch."),
) -> None:
    """PSNR and SSIM of every robot's field: on a split's held-out views (against its truth), and on every robot's
    own held-out frames through the estimated poses (no truth needed: robots with their own recordings)."""
    from rich.console import Console

    from agent.outputs.scoring import score_heldout, score_own_frames

    if json_out is not None and json_out.is_dir():
        raise UserError(f"--json {json_out}: is a folder, expected a file name")
    run = _open(run_dir, data, threads)
    robots = run.ids if robot is None else [run.pick(robot)]
    console = Console()
    doc: dict = {"views": [], "notes": [], "round": round, "robots": {}}
    if run.split_dir is not None:
        doc = score_heldout(run, robots, round=round, with_ssim=ssim, device=device, echo=typer.echo)
        for note in doc["notes"]:
            console.print(f"note: {note}", markup=False)
        console.print(_robot_table(doc))
        if per_view:
            console.print(_view_table(doc))
    cross = score_own_frames(run, run.ids, round=round, with_ssim=ssim, device=device, echo=typer.echo)
    if cross is None and run.split_dir is None:
        raise UserError(f"{run_dir}: no held-out views to score against: no split's (eval/, truth.json), and no robot "
                        "kept frames of its own out of training (training.own_holdout_every = 0)")
    if cross is not None:
        doc["cross"] = cross
        console.print(_cross_table(cross, robots))
        console.print(_frames_table(cross))
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps({**doc, "robots": {str(i): r for i, r in doc["robots"].items()}}, indent=2) + "\n")
        typer.echo(f"wrote {json_out}")


def _fmt(x, digits: int = 2) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}f}"


def _robot_table(doc: dict):
    from rich.table import Table

    t = Table(title=f"held-out views ({len(doc['views'])})" + (f", round {doc['round']}" if doc["round"] is not None else ""))
    for col in ("robot", "PSNR all", "SSIM all", "PSNR others only", "SSIM others only", "pose err deg"):
        t.add_column(col, justify="right")
    for i, r in doc["robots"].items():
        t.add_row(str(i), _fmt(r["psnr"]), _fmt(r.get("ssim"), 3), _fmt(r["psnr_others_only"]),
                  _fmt(r.get("ssim_others_only"), 3), _fmt(r.get("pose_rotation_deg"), 3))
    return t


def _cross_table(cross: dict, robots: list[int]):
    """PSNR of each robot's field (rows) on each robot's own held-out frames (columns)."""
    from rich.table import Table

    owners = sorted(cross["frames"], key=int)
    t = Table(title="each robot's field (row) on each robot's own held-out frames (column), through the estimated "
                    "poses: PSNR dB / SSIM")
    t.add_column("field of")
    for j in owners:
        t.add_column(f"robot {j} ({cross['frames'][j]} frames)", justify="right")
    t.add_column("mean on others'", justify="right")
    for i in map(str, robots):
        cells = [_fmt(cross["psnr"][i][j]) + (f" / {_fmt(cross['ssim'][i][j], 3)}" if cross["ssim"].get(i) else "")
                 for j in owners]
        t.add_row(f"robot {i}", *cells, _fmt(cross["mean_others"][i]))
    return t


def _frames_table(cross: dict):
    """Where each robot's frame was placed, how sure the coarse step was, and its state."""
    from rich.table import Table

    t = Table(title="relative poses found (robot's frame -> shared frame)")
    for col in ("robot", "state", "rotation deg", "|t|", "scale", "coarse step: sigma deg", "via", "inliers"):
        t.add_column(col, justify="right")
    for i, r in sorted(cross["robots"].items(), key=lambda kv: int(kv[0])):
        t.add_row(i, r["alignment"], _fmt(r["rotation_deg"], 2), _fmt(r["translation"], 3), _fmt(r["scale"], 3),
                  _fmt(r["rotation_sigma_deg"], 3), "-" if r["via"] is None else str(r["via"]),
                  "-" if r["inliers"] is None else str(r["inliers"]))
    return t


def _view_table(doc: dict):
    from rich.table import Table

    t = Table(title="per view: PSNR dB / SSIM (* = only other robots saw it)")
    t.add_column("view")
    for i in doc["robots"]:
        t.add_column(f"robot {i}", justify="right")
    for k, name in enumerate(doc["views"]):
        cells = []
        for r in doc["robots"].values():
            v = r["per_view"][k]
            cells.append(f"{_fmt(v['psnr'])}" + (f" / {_fmt(v['ssim'], 3)}" if v["ssim"] is not None else "")
                         + (" *" if v["others_only"] else ""))
        t.add_row(name, *cells)
    return t


@app.command()
@friendly_errors
def export(
    run_dir: Path = typer.Argument(..., help=RUN_HELP),
    out: Path = typer.Option(..., "--out", help="Output folder."),
    robot: int = typer.Option(None, "--robot", help="Whose field to export (default: the lowest id)."),
    round: int = typer.Option(None, "--round", help=ROUND_HELP),
    resolution: int = typer.Option(128, "--resolution", help="Lattice points per axis for the point cloud and mesh."),
    density: float = typer.Option(10.0, "--density", help="Density threshold (per box unit) of points and surface."),
    data: Path = typer.Option(None, "--data", help=RUN_DATA_HELP),
    device: str = typer.Option(None, "--device", help=DEVICE_HELP),
    threads: int = typer.Option(2, help="CPU threads for torch."),
) -> None:
    """Every robot's cameras as one transforms.json, the field as a PLY point cloud and mesh, and its weights."""
    from agent.outputs.export import GeometryConfig, export_cameras, export_geometry
    from agent.outputs.weights import export_weights

    cfg = _checked(lambda: GeometryConfig(resolution=resolution, density_threshold=density), "export")
    check_output_folder(out, "--out")
    run = _open(run_dir, data, threads)
    rid = run.pick(robot)
    trainers = {i: run.load(i, round=round, device=device) for i in run.ids}
    out.mkdir(parents=True, exist_ok=True)
    try:
        tj = export_cameras(trainers, out)
    except ValueError as e:
        raise UserError(str(e)) from None
    trainer = trainers[rid]
    geo = export_geometry(trainer, out, cfg)
    export_weights(trainer, out, about={"robot": rid, "round": round, "run": str(run.path.resolve())})
    typer.echo(f"{len(tj['frames'])} cameras of robots {run.ids} -> {out}/transforms.json; robot {rid}'s field: "
               f"{geo.points} points -> points.ply, {geo.vertices} vertices / {geo.faces} faces -> mesh.ply, "
               f"weights -> field.safetensors + field.json")
    if geo.points == 0:
        typer.echo(f"note: no point of the field is denser than --density {density} (its densest: "
                   f"{geo.max_density:.3g}): lower --density")
