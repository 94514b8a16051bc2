"""`dinerf-agent render | eval | export` on a real finished run, as a user runs them.

The run is a tiny scenario (2 robots, 24x24 procedural scene) run by the real `scenario run`,
which starts one real `dinerf-agent up` per robot over Zenoh on loopback. The commands run as
subprocesses; their files are then read back with other tools: imageio for the PNGs, GIF and
MP4, our own transforms.json loader for the cameras, plyfile for the point cloud and mesh, and
safetensors alone (plus a numpy re-implementation of the field, from field.json's description)
for the weights.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.agent_cli import agent as run_agent

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]

TINY = """
[scenario]
name = "outputs-tiny"
dataset = "procedural:views=24,width=24"
robots = 2
[split]
overlap = 0.1
frame = "world"
test_every = 6
[topology]
kind = "full"
[training]
rounds = 3
steps_per_round = 30
own_holdout_every = 0
[training.train]
rays_per_step = 512
[training.train.field]
density_hidden = 32
color_hidden = 32
[training.train.field.grid]
log2_hashmap_size = 14  # level 0 (16^3) is indexed densely, the finer levels hashed: both in field.json
num_levels = 8
max_resolution = 128
[training.train.occupancy]
resolution = 32
warmup_steps = 16
update_every = 8
[daemon]
round_timeout_s = 20
eval_every = 0
keep_rounds = true
[report]
ssim = false
render_views = 0
eval_every = 100
"""


def agent(*args: str, cwd: Path = ROOT, timeout: float = 240) -> subprocess.CompletedProcess:
    return run_agent(*args, cwd=cwd, timeout=timeout, env={"OMP_NUM_THREADS": "1", "COLUMNS": "200"})


def ok(p: subprocess.CompletedProcess) -> str:
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    return p.stdout


def invoke(*args: str):
    """The same command in this process (typer's runner): for the variants, to spare a torch import each."""
    from typer.testing import CliRunner

    from cli.main import _register, app

    _register()
    return CliRunner().invoke(app, [*args, "--threads", "1"])


def ok_here(*args: str) -> str:
    res = invoke(*args)
    assert res.exit_code == 0, (res.exit_code, res.output, res.exception)
    return res.output


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("outputs")
    (tmp / "scenario.toml").write_text(TINY)
    ok(agent("scenario", "run", str(tmp / "scenario.toml"), "--out", str(tmp / "run")))
    return tmp / "run"


def test_render_an_orbit_as_pngs_and_mp4_and_given_cameras_as_gif(run, tmp_path):
    import imageio.v3 as iio

    out = tmp_path / "orbit"
    ok(agent("render", str(run), "--orbit", "6", "--spiral", "10", "--width", "32", "--video", "mp4",
             "--out", str(out), "--threads", "1"))
    for kind in ("rgb", "depth"):
        pngs = sorted((out / kind).glob("*.png"))
        assert len(pngs) == 6
        imgs = np.stack([iio.imread(p) for p in pngs])
        assert imgs.shape == (6, 32, 32, 3) and imgs.std() > 5, kind  # not a constant image
        assert np.abs(imgs[0].astype(int) - imgs[3].astype(int)).mean() > 1, "the orbit does not move"
    video = iio.imread(out / "video.mp4", plugin="FFMPEG")
    assert video.shape[0] == 6 and video.shape[1:3] == (32, 64)  # colour | depth
    assert np.load(out / "depth.npy").shape == (6, 32, 32)

    held = tmp_path / "held"
    ok_here("render", str(run / "robots" / "2"), "--cameras", str(run / "data" / "eval" / "transforms.json"),
            "--out", str(held))  # a robot's run dir: its data folder is recorded
    gif = iio.imread(held / "video.gif", index=None)
    assert gif.shape[0] == 4 == len(list((held / "rgb").glob("*.png")))
    # the frame of the split is "world", so the held-out cameras are in the shared frame: the render
    # is the field's view of the held-out image
    from agent.runs import open_run
    from agent.data.loaders import load_views

    trainer = open_run(run).load(2)
    views = load_views(run / "data" / "eval")
    mine = trainer.render(views.c2w[1], views.intrinsics[1], views.width, views.height)["rgb"].numpy()
    png = iio.imread(held / "rgb" / "0001.png")[..., :3] / 255.0
    assert np.abs(png - mine).max() <= 1 / 255 + 1e-6


def test_eval_matches_agent_evaluation(run, tmp_path):
    from agent.evaluation import EvalSet, evaluate_robot
    from agent.runs import open_run

    out = ok(agent("eval", str(run), "--json", str(tmp_path / "scores.json"), "--threads", "1"))
    assert "PSNR all" in out and "view_006" in out
    doc = json.loads((tmp_path / "scores.json").read_text())
    evalset = EvalSet.from_dir(run / "data")
    opened = open_run(run)
    for i in (1, 2):
        ev = evaluate_robot(opened.load(i), evalset, i)
        got = doc["robots"][str(i)]
        assert got["psnr"] == pytest.approx(ev.psnr_all, abs=1e-9) and got["ssim"] == pytest.approx(ev.ssim_all, abs=1e-9)
        assert [v["psnr"] for v in got["per_view"]] == pytest.approx(ev.psnr, abs=1e-9)
        assert [v["others_only"] for v in got["per_view"]] == [k in ev.others_only for k in range(len(ev.psnr))]
        assert got["psnr"] > 12  # it learnt something
    # the same robot through its own run dir, at an earlier round kept under rounds/
    one = ok_here("eval", str(run / "robots" / "1"), "--round", "2", "--no-ssim", "--json", str(tmp_path / "r2.json"))
    r2 = json.loads((tmp_path / "r2.json").read_text())
    assert set(r2["robots"]) == {"1"} and r2["round"] == 2 and "view_000" in one
    assert r2["robots"]["1"]["psnr"] == pytest.approx(evaluate_robot(opened.load(1, round=2), evalset, 1).psnr_all)
    # a swarm run by hand: runs/<swarm>/robot<id>/, as `up` lays them out by default
    hand = tmp_path / "swarm1"
    for i in (1, 2):
        shutil.copytree(run / "robots" / str(i), hand / f"robot{i}")
    ok_here("eval", str(hand), "--no-ssim", "--json", str(tmp_path / "hand.json"))
    by_hand = json.loads((tmp_path / "hand.json").read_text())
    assert {i: r["psnr"] for i, r in by_hand["robots"].items()} == {i: r["psnr"] for i, r in doc["robots"].items()}


def _mlp(layers: list[dict], t: dict[str, np.ndarray], h: np.ndarray) -> np.ndarray:
    for layer in layers:
        h = h @ t[layer["weight"]].T + t[layer["bias"]]
        h = np.maximum(h, 0) if layer["activation"] == "relu" else h
    return h


def _sh4(d: np.ndarray) -> np.ndarray:
    """docs/export.md's real SH basis of degree 4, in its order.  [N, 3] unit -> [N, 16]."""
    x, y, z = d.T
    xx, yy, zz = x * x, y * y, z * z
    return np.stack([np.full_like(x, 0.28209479177387814), -0.4886025119029199 * y, 0.4886025119029199 * z,
                     -0.4886025119029199 * x, 1.0925484305920792 * x * y, -1.0925484305920792 * y * z,
                     0.31539156525252005 * (2 * zz - xx - yy), -1.0925484305920792 * x * z,
                     0.5462742152960396 * (xx - yy), -0.5900435899266435 * y * (3 * xx - yy),
                     2.890611442640554 * x * y * z, -0.4570457994644658 * y * (4 * zz - xx - yy),
                     0.3731763325901154 * z * (2 * zz - 3 * xx - 3 * yy), -0.4570457994644658 * x * (4 * zz - xx - yy),
                     1.445305721320277 * z * (xx - yy), -0.5900435899266435 * x * (xx - 3 * yy)], -1)


def _field_numpy(cfg: dict, t: dict[str, np.ndarray], x_shared: np.ndarray, d_shared: np.ndarray):
    """The field's density and colour from field.json + field.safetensors alone (docs/export.md)."""
    b = np.array(cfg["frame"]["box_from_shared"])
    x = (x_shared @ b[:3, :3].T + b[:3, 3]).astype(np.float32)
    assert not cfg["frame"]["unbounded"]  # RGBA procedural images: a bounded field
    unit = (x + 1) * np.float32(0.5)
    inside = ((unit >= 0) & (unit <= 1)).all(-1)
    unit = np.clip(unit, 0, 1)
    hg = cfg["hash_grid"]
    size, table = hg["table_size"], t[hg["table"]]
    primes = np.array(hg["primes"], dtype=np.uint32)
    feats = []
    for level, (res, dense) in enumerate(zip(hg["resolutions"], hg["dense"])):
        pos = unit * np.float32(res)
        base = np.floor(pos)
        frac = pos - base
        f = np.zeros((len(x), hg["features_per_level"]), np.float64)
        for corner in range(8):
            bits = np.array([(corner >> a) & 1 for a in range(3)])
            c = (base + bits).astype(np.uint32)  # [N, 3]
            if dense:
                idx = c[:, 0] + c[:, 1] * np.uint32(res + 1) + c[:, 2] * np.uint32((res + 1) ** 2)
            else:
                idx = (c[:, 0] * primes[0]) ^ (c[:, 1] * primes[1]) ^ (c[:, 2] * primes[2])
            w = np.prod(np.where(bits == 1, frac, 1 - frac), axis=1)
            f += w[:, None] * table[(idx & np.uint32(size - 1)).astype(np.int64) + level * size]
        lw = hg["level_weights"]
        feats.append(f * (1.0 if lw is None else lw[level]))
    out = _mlp(cfg["density_mlp"]["layers"], t, np.concatenate(feats, axis=1))
    sigma = np.exp(out[:, 0] + cfg["density_mlp"]["density_bias"]) * inside
    rot = b[:3, :3] / np.cbrt(np.linalg.det(b[:3, :3]))
    d = d_shared @ rot.T
    assert cfg["color_mlp"]["sh_degree"] == 4 and cfg["color_mlp"]["output"] == "sigmoid"
    rgb = 1 / (1 + np.exp(-_mlp(cfg["color_mlp"]["layers"], t, np.concatenate([out[:, 1:], _sh4(d)], axis=1))))
    return sigma, rgb


def test_export_cameras_geometry_and_weights(run, tmp_path):
    from plyfile import PlyData
    from safetensors.numpy import load_file

    from agent.data.loaders import load_views
    from agent.geometry import transform_points
    from agent.runs import open_run

    out = tmp_path / "export"
    said = ok(agent("export", str(run), "--out", str(out), "--resolution", "48", "--density", "3", "--threads", "1"))
    assert "note:" not in said, said
    opened = open_run(run)
    trainers = {i: opened.load(i) for i in (1, 2)}

    # cameras: our own loader reads them back, the same cameras in the shared frame
    views = load_views(out)
    expect = torch.cat([t.cameras_shared().detach() for t in trainers.values()])
    assert len(views) == len(expect) == sum(len(t.views) for t in trainers.values())
    assert torch.allclose(views.c2w, expect, atol=1e-6)
    assert torch.allclose(views.intrinsics, torch.cat([t.camera_intrinsics() for t in trainers.values()]))
    top = json.loads((out / "transforms.json").read_text())
    assert top["camera_model"] == "PINHOLE" and {"fl_x", "fl_y", "cx", "cy", "w", "h"} <= set(top)
    assert {f["robot"] for f in top["frames"]} == {1, 2}

    # geometry: points and a mesh inside the field's box, read by plyfile
    box = trainers[1].box_from_shared.double()
    pts = PlyData.read(str(out / "points.ply"))["vertex"]
    xyz = np.stack([pts["x"], pts["y"], pts["z"]], -1).astype(np.float64)
    in_box = transform_points(box, torch.from_numpy(xyz)).abs().max(-1).values <= 1 + 1e-5
    assert len(xyz) > 20 and bool(in_box.all())
    assert np.ptp(np.stack([pts["red"], pts["green"], pts["blue"]]), axis=1).max() > 0  # coloured by the field
    mesh = PlyData.read(str(out / "mesh.ply"))
    assert mesh["face"].count > 20 and mesh["vertex"].count > 20

    # weights: safetensors alone + field.json describe the field; numpy gives our field's density
    cfg = json.loads((out / "field.json").read_text())
    tensors = load_file(str(out / "field.safetensors"))
    assert cfg["format"] == "dinerf-field" and any(cfg["hash_grid"]["dense"]) and not all(cfg["hash_grid"]["dense"])
    rng = np.random.default_rng(0)
    shared_from_box = np.linalg.inv(box.numpy())
    probe_box = np.concatenate([rng.uniform(-1, 1, (64, 3)), transform_points(box, torch.from_numpy(xyz[:64])).numpy()])
    probe = probe_box @ shared_from_box[:3, :3].T + shared_from_box[:3, 3]
    dirs = rng.normal(size=probe.shape)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    sigma, rgb = _field_numpy(cfg, tensors, probe, dirs)
    f, r = trainers[1].field, box[:3, :3] / torch.linalg.det(box[:3, :3]).abs() ** (1 / 3)
    with torch.no_grad():  # our field, at the same points and directions in the box
        ours_sigma, ours_rgb = f(torch.from_numpy(probe_box).float(), (torch.from_numpy(dirs) @ r.T).float(),
                                 trainers[1].level_weights())
    assert ours_sigma.max() > 3  # the probe reaches the dense part, where the numbers are not just exp(bias)
    np.testing.assert_allclose(sigma, ours_sigma.double().numpy(), rtol=2e-4, atol=1e-6)
    np.testing.assert_allclose(rgb, ours_rgb.double().numpy(), atol=1e-5)


def test_bad_input_is_one_line(run, tmp_path):
    def fails(*args: str) -> str:
        res = invoke(*args)
        lines = [line for line in res.stderr.splitlines() if line.strip()]
        assert res.exit_code == 2 and len(lines) == 1 and lines[0].startswith("error: "), (res.exit_code, res.output)
        assert res.exception is None or isinstance(res.exception, SystemExit)
        return lines[0]

    assert "no such folder" in fails("render", str(tmp_path / "nope"))
    (tmp_path / "empty").mkdir()
    assert "not a run folder" in fails("eval", str(tmp_path / "empty"))
    assert "no snapshot of round 99" in fails("render", str(run), "--round", "99", "--orbit", "2")
    assert "no robot 7" in fails("export", str(run), "--out", str(tmp_path / "x"), "--robot", "7")
    assert "--device" in fails("render", str(run), "--device", "no-such-device", "--orbit", "2")
    assert "not both" in fails("render", str(run), "--orbit", "2", "--cameras", str(run / "data" / "eval"))
    starting = tmp_path / "starting" / "robot1"  # a swarm run by hand that is still starting: no checkpoint yet
    starting.mkdir(parents=True)
    shutil.copy(run / "robots" / "1" / "data.json", starting)
    assert "has a checkpoint.safetensors yet" in fails("eval", str(starting.parent))
    old = tmp_path / "old"  # a run dir of a dinerf that did not record its data folder
    shutil.copytree(run / "robots" / "1", old)
    (old / "data.json").unlink()
    assert "pass --data" in fails("eval", str(old))
    lonely = tmp_path / "lonely" / "robot1"  # a robot folder that is not part of a split
    shutil.copytree(run / "data" / "robot1", lonely)
    assert "no held-out views" in fails("eval", str(old), "--data", str(lonely))
    ok_here("eval", str(old), "--data", str(run / "data" / "robot1"), "--no-per-view", "--no-ssim")
    raw = bytearray((old / "checkpoint.safetensors").read_bytes())
    raw[-100] ^= 0xFF
    (old / "checkpoint.safetensors").write_bytes(bytes(raw))
    assert "checksum" in fails("export", str(old), "--out", str(tmp_path / "y"), "--data", str(run / "data" / "robot1"))


def test_the_scenario_report_has_an_orbit_and_no_pose_panels_for_known_poses(run):
    """The run's own report (frames "world", the pose fixed): orbit.gif of both robots, no pose panels."""
    from tests.scenarios.report_checks import check_figures

    report = json.loads((run / "report.json").read_text())
    check_figures(run, report, orbit_frames=36, pose_panels=False, all_robots=False)  # the defaults
    assert [int(k) for k in report["figures"]["convergence"]["points"]["psnr"]["1"]] == [3]  # eval_every = 100: the last
