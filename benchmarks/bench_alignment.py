"""Coarse initial alignment on lego: success rate and error of the coarse step alone.

Two robots get lego's training views (every 8th view held out, as in evaluation) by the project's
own sector split (``agent.data.split.split_views``): two azimuth sectors widened until 20% of each
robot's views are also held by the other (``--overlap``). Each robot's local frame is random
(``frame="random"``): rotation about a uniform axis by an angle uniform in [0, 180] deg,
translation uniform in a ball of 3 scene radii (scene radius = radius of lego's camera sphere,
~4.0 units), and with ``--scale`` a scale log-uniform in [1/2, 2]. The sector start is random per
trial too, so the 20 trials see 20 different pairs of sectors. Robot 1 is the reference.

Printed per trial and overall: whether the coarse step succeeded, rotation/translation/scale
error of T_a_from_b against the truth (in lego units), the mean error of B's camera centres mapped
into the world (what the NeRF actually sees), and the summary bytes next to the robot's image
bytes. With ``--refine-rounds R`` each trial also runs the joint optimisation (the in-process
C-ADMM swarm of ``agent.swarm``: NeRF and relative pose, R rounds of ``--refine-steps`` steps per
robot at the feature resolution) once from each start in ``--refine-starts``: ``coarse`` (the
coarse estimate; the identity when the coarse step found nothing) and ``identity`` (the paper's
start). Success = final error <= 1 deg and <= 0.02 lego units, for the translation of T_a_from_b
and, separately, for the mean error of B's camera centres mapped into the world. The first
carries a lever arm: B's origin lies up to 12 units from the scene, so 0.1 deg about the scene
centre moves it by 0.02; the second measures where B's content lands.

Modes: ``--feature-width`` is the resolution the features are computed at (100 = the training
resolution; 400 = the originals in ../shared/data). ``--disjoint`` drops the shared views from
B (no image in common, only a shared region). ``--sfm`` gives each robot images only: it runs its
own SfM (agent.data.sfm, cached under --cache), so its local frame and scale are SfM's, and the
truth is the SfM->world similarity of each robot (trimmed Umeyama on its camera centres).

    .venv/bin/python benchmarks/bench_alignment.py --feature-width 100
    .venv/bin/python benchmarks/bench_alignment.py --feature-width 400
    .venv/bin/python benchmarks/bench_alignment.py --feature-width 100 --disjoint
    .venv/bin/python benchmarks/bench_alignment.py --feature-width 100 --sfm --trials 5
    .venv/bin/python benchmarks/bench_alignment.py --feature-width 100 --refine-rounds 20
    .venv/bin/python benchmarks/bench_alignment.py --feature-width 400 --refine-rounds 10 --refine-starts coarse

``--feature-width`` and ``--train-width`` (default 100) are separate: a robot computes its summary
from its own image files (the daemon's default, ``daemon.summary_width``) while it trains smaller.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent import geometry as G  # noqa: E402
from agent.align import AlignConfig, estimate_relative, summarise  # noqa: E402
from agent.data.split import SplitConfig, split_views  # noqa: E402
from agent.data.views import Views  # noqa: E402
from agent.pose import PoseConfig  # noqa: E402


def file_bytes(data: Path, names: list[str]) -> int:
    return sum((data / "train" / f"{n}.png").stat().st_size for n in names)


def sfm_robot(data: Path, names: list[str], cache: Path, feature_width: int) -> tuple[Views, torch.Tensor]:
    """Images-only robot: own SfM on its original files -> (views in SfM frame, T_world_from_sfm)."""
    from agent.data.loaders import load_views
    from agent.data.sfm import run_sfm

    key = f"{len(names)}_{hashlib.sha1(','.join(names).encode()).hexdigest()[:10]}"  # stable across runs
    folder = cache / "images" / key
    folder.mkdir(parents=True, exist_ok=True)
    for n in names:
        dst = folder / f"{n}.png"
        if not dst.exists():
            dst.symlink_to(data / "train" / f"{n}.png")
    views = run_sfm(folder, cache / "sfm" / key, width=feature_width)
    truth = load_views(data)
    true_c2w = truth.c2w[[truth.names.index(n) for n in views.names]].double()
    # Trimmed Umeyama: a few cameras SfM got badly wrong (see the note on mirrored clusters in
    # the report) must not corrupt the reference transform; they are counted instead.
    keep = torch.ones(len(views), dtype=torch.bool)
    for _ in range(10):
        t_world_from_sfm = G.umeyama(views.c2w[keep, :3, 3].double(), true_c2w[keep, :3, 3])
        aligned = G.transform_c2w(t_world_from_sfm, views.c2w.double())
        err = (aligned[:, :3, 3] - true_c2w[:, :3, 3]).norm(dim=1)
        new_keep = err < max(3.0 * float(err[keep].median()), 0.05)
        if torch.equal(new_keep, keep):
            break
        keep = new_keep
    rot = torch.tensor([float(G.rotation_angle_deg(aligned[i, :3, :3], true_c2w[i, :3, :3])) for i in range(len(views))])
    views.meta["bench_bad_cameras"] = int((rot > 5.0).sum())
    views.meta["bench_median_rot_deg"] = float(rot.median())
    return views, t_world_from_sfm


def at_width(local: Views, images: Views) -> Views:
    """``local`` (a robot's views in its frame) with the images and intrinsics of ``images`` (same views)."""
    assert local.names == images.names
    return Views(images.images, local.c2w, images.intrinsics, list(local.names), None, dict(local.meta))


def refine(robots: dict[int, Views], box_from_shared: torch.Tensor, args, initial: torch.Tensor | None,
           sigma_deg: float = float("nan")) -> torch.Tensor:
    """Joint NeRF + pose optimisation of the two robots from ``initial`` (T_a_from_b; None = identity)
    with the estimate's rotation 1-sigma, as the daemon does. Returns robot 2's final T_a_from_b, float64."""
    from agent.swarm import Simulation, SwarmTrainingConfig
    from agent.trainer import TrainConfig

    train = TrainConfig()
    train = dataclasses.replace(train, pose=dataclasses.replace(train.pose, mode="sim3" if args.scale else "se3",
                                                                start_step=args.refine_pose_start,
                                                                lr_factor_from_estimate=args.refine_pose_lr_factor,
                                                                travel_sigmas=args.refine_travel_sigmas))
    cfg = SwarmTrainingConfig(rounds=args.refine_rounds, steps_per_round=args.refine_steps, seed=args.seed,
                              own_holdout_every=0, train=train)
    sim = Simulation(robots, {1: {2}, 2: {1}}, box_from_shared, cfg, reference_id=1)
    if initial is not None:
        sim.trainers[2].pose.set_initial(initial, sigma_deg=sigma_deg if args.refine_use_sigma else float("nan"))
    print(f"      joint optimisation: pose learning rates x {sim.trainers[2].pose_lr_scale():.3f}", flush=True)
    sim.run(lambda rec: None)
    return sim.trainers[2].pose.matrix().detach().double().cpu()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared/data/nerf_synthetic/lego")
    ap.add_argument("--feature-width", type=int, default=100, help="resolution of the images features come from")
    ap.add_argument("--train-width", type=int, default=100, help="resolution the joint optimisation trains at")
    ap.add_argument("--trials", type=int, default=20)
    ap.add_argument("--overlap", type=float, default=0.2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scale", action=argparse.BooleanOptionalAction, default=True, help="random scale (Sim(3))")
    ap.add_argument("--disjoint", action="store_true", help="B keeps none of A's views")
    ap.add_argument("--sfm", action="store_true", help="images-only robots with their own SfM")
    ap.add_argument("--cache", type=Path, default=ROOT / "runs/bench_alignment")
    ap.add_argument("--keyframes", type=int, default=AlignConfig.num_keyframes)
    ap.add_argument("--min-inliers", type=int, default=AlignConfig.min_inliers)
    ap.add_argument("--refine-rounds", type=int, default=0, help="joint optimisation after the coarse step (0: none)")
    ap.add_argument("--refine-steps", type=int, default=25, help="steps per round of the joint optimisation")
    ap.add_argument("--refine-starts", default="coarse,identity")
    ap.add_argument("--refine-pose-start", type=int, default=100,
                    help="steps the pose waits for the field to form (a pose learnt against an empty "
                         "field drifts: 0.1 -> 0.6 deg in the first 10 steps, measured)")
    ap.add_argument("--refine-pose-lr-factor", type=float, default=PoseConfig.lr_factor_from_estimate,
                    help="pose learning rates x this when the joint optimisation starts from the coarse estimate")
    ap.add_argument("--refine-use-sigma", action=argparse.BooleanOptionalAction, default=True,
                    help="the pose learns at a rate set by the coarse estimate's rotation sigma (pose.travel_sigmas); "
                         "without it, at --refine-pose-lr-factor")
    ap.add_argument("--refine-travel-sigmas", type=float, default=PoseConfig.travel_sigmas)
    ap.add_argument("--first-trial", type=int, default=0, help="skip the trials before this one (same offsets)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    if args.refine_rounds and args.sfm:
        sys.exit("--refine-rounds works with true local poses only (not with --sfm)")
    starts = [x for x in args.refine_starts.split(",") if x] if args.refine_rounds else []
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)

    if not args.data.is_dir():
        sys.exit(f"{args.data} is absent: this benchmark needs lego from ../shared/data")
    from agent.data.loaders import load_views

    t0 = time.perf_counter()
    views = load_views(args.data, width=args.train_width)
    feature_views = views if args.feature_width == args.train_width else load_views(args.data, width=args.feature_width)
    print(f"lego: {len(views)} views, features at {feature_views.width}x{feature_views.height}, joint optimisation "
          f"at {views.width}x{views.height} (loaded in {time.perf_counter() - t0:.1f}s); overlap {args.overlap:.0%} of each sector; "
          f"{'Sim(3)' if args.scale or args.sfm else 'SE(3)'}; {'disjoint images' if args.disjoint else 'shared views in the overlap'}"
          f"{'; per-robot SfM' if args.sfm else '; true local poses'}; views 0, 8, 16 ... held out")
    centres = views.c2w[:, :3, 3].double()
    radius = float(centres.norm(dim=1).median())
    print(f"scene radius (camera sphere) {radius:.3f}; offsets: rotation U[0,180] deg, translation U[0,{3 * radius:.1f}]")
    cfg = AlignConfig(num_keyframes=args.keyframes, min_inliers=args.min_inliers, with_scale=args.scale or args.sfm, seed=args.seed)

    kept = [i for i in range(len(views)) if i % 8 != 0]  # views 0, 8, 16 ... held out for evaluation
    views, feature_views = views.subset(kept), feature_views.subset(kept)
    g = torch.Generator().manual_seed(args.seed)
    rows = []
    header = ("trial  nA  nB shared  ok  inl/match  rot_deg   t_err  scale%  cam_err  init_rot init_t  "
              "sumA_KB sumB_KB  imgB_KB(png) imgB_KB(raw@100)  t_sum  t_est  reason")
    print(header)
    for trial in range(args.trials):
        start = float(torch.rand((), generator=g)) * 360.0 - 180.0
        if trial < args.first_trial:
            continue
        split = split_views(views, SplitConfig(
            robots=2, overlap=args.overlap, frame="random", random_max_angle_deg=180.0,
            random_max_translation=3.0 * radius, random_max_scale=2.0 if args.scale else 1.0,
            sector_start_deg=start, seed=args.seed * 1000 + trial))
        ra, rb = split.robots[1], split.robots[2]
        ia, ib = list(ra.indices), list(rb.indices)
        shared = len(set(ia) & set(ib))
        vb_local = rb.views
        if args.disjoint:
            keep = [k for k, i in enumerate(ib) if i not in set(ia)]
            ib = [ib[k] for k in keep]
            vb_local = vb_local.subset(keep)
        names_b = [views.names[i] for i in ib]
        if args.sfm:
            va, w_from_a = sfm_robot(args.data, [views.names[i] for i in ia], args.cache, args.feature_width)
            vb, w_from_b = sfm_robot(args.data, names_b, args.cache, args.feature_width)
            true_b_centres = G.transform_points(w_from_b, vb.c2w[:, :3, 3].double())  # B's SfM, ideally placed
            print(f"      SfM A: {len(va)}/{len(ia)} registered, {va.meta['bench_bad_cameras']} off by > 5 deg, "
                  f"median {va.meta['bench_median_rot_deg']:.2f} deg, {va.meta['sfm_seconds']:.0f} s; "
                  f"SfM B: {len(vb)}/{len(ib)}, {vb.meta['bench_bad_cameras']} off, median "
                  f"{vb.meta['bench_median_rot_deg']:.2f} deg, {vb.meta['sfm_seconds']:.0f} s", flush=True)
        else:
            va, w_from_a = ra.views, ra.T_world_from_local
            vb, w_from_b = vb_local, rb.T_world_from_local
            true_b_centres = views.c2w[ib, :3, 3].double()
        # What each robot computes its summary from: its images at the feature width, in its local frame.
        fa, fb = (va, vb) if args.sfm else (at_width(va, feature_views.subset(ia)), at_width(vb, feature_views.subset(ib)))
        truth = G.sim3_inverse(w_from_a) @ w_from_b  # T_a_from_b
        a_from_world = G.sim3_inverse(w_from_a)
        t1 = time.perf_counter()
        sa, sb = summarise(fa, "triangulate", cfg), summarise(fb, "triangulate", cfg)
        t2 = time.perf_counter()
        res = estimate_relative(sa, sb, cfg)
        t3 = time.perf_counter()
        res_3d = estimate_relative(sa, sb, dataclasses.replace(cfg, reproj_refine=False))  # baseline: no pixels
        init = G.pose_error(torch.eye(4, dtype=torch.float64), truth)  # the paper's identity start
        row = {"ok": res.success, "init_rot": init["rotation_deg"], "init_t": init["translation"],
               "sum_a": sa.nbytes, "sum_b": sb.nbytes, "png_b": file_bytes(args.data, names_b),
               "raw_b": len(names_b) * 100 * 100 * 4, "t_sum": (t2 - t1) / 2, "t_est": t3 - t2}
        def errors(t_a_from_b: np.ndarray) -> dict:
            # Errors in lego units: A's frame is the world up to a_from_world (identity unless SfM).
            to_world = G.sim3_inverse(a_from_world)
            est = to_world @ torch.from_numpy(t_a_from_b)
            err = G.pose_error(est, to_world @ truth)
            # B's cameras mapped into the world with the estimate vs where they truly are.
            cam = (G.transform_points(est, vb.c2w[:, :3, 3].double()) - true_b_centres).norm(dim=1).mean()
            return dict(rot=err["rotation_deg"], t=err["translation"], scale=100 * err["scale_rel"], cam=float(cam))

        if res.success:
            row.update(errors(res.T_a_from_b), reason=res.reason, sigma=res.rotation_sigma_deg)
        if res_3d.success:
            row["fit_3d"] = errors(res_3d.T_a_from_b)
        for start in starts:
            initial = torch.from_numpy(res.T_a_from_b).float() if start == "coarse" and res.success else None
            t4 = time.perf_counter()
            est = refine({1: va, 2: vb}, split.box_from_shared, args, initial, res.rotation_sigma_deg)
            to_world = G.sim3_inverse(a_from_world)
            err = G.pose_error(to_world @ est, to_world @ truth)
            cam = float((G.transform_points(to_world @ est, vb.c2w[:, :3, 3].double()) - true_b_centres).norm(dim=1).mean())
            row[f"refined_{start}"] = {"rot": err["rotation_deg"], "t": err["translation"], "cam": cam,
                                       "ok": err["rotation_deg"] <= 1.0 and err["translation"] <= 0.02,
                                       "ok_cam": err["rotation_deg"] <= 1.0 and cam <= 0.02,
                                       "from": "identity" if initial is None else "coarse",
                                       "T_a_from_b": est.tolist(), "seconds": time.perf_counter() - t4}
        rows.append(row)
        fmt = (lambda k, f: f.format(row[k]) if k in row else "-".rjust(len(f.format(0.0))))
        print(f"{trial:5d} {len(ia):3d} {len(ib):3d} {shared:6d} {'yes' if res.success else ' no'} "
              f"{res.inliers:4d}/{res.matches:<5d} {fmt('rot', '{:7.3f}')} {fmt('t', '{:7.4f}')} "
              f"{fmt('scale', '{:6.3f}')} {fmt('cam', '{:8.4f}')} "
              f"{row['init_rot']:8.1f} {row['init_t']:6.2f} {row['sum_a'] / 1e3:8.1f} {row['sum_b'] / 1e3:7.1f} "
              f"{row['png_b'] / 1e3:13.1f} {row['raw_b'] / 1e3:16.1f} {row['t_sum']:6.2f} {row['t_est']:6.2f}  "
              f"{'' if res.success else res.reason}", flush=True)
        if res.success:
            print(f"      rotation sigma (the estimate's own) {row['sigma']:.3f} deg; error / sigma "
                  f"{row['rot'] / row['sigma']:.2f}", flush=True)
        if "fit_3d" in row:
            f3 = row["fit_3d"]
            print(f"      3-D fit only: {f3['rot']:.3f} deg, t {f3['t']:.4f}, cameras {f3['cam']:.4f}", flush=True)
        for start in starts:
            r = row[f"refined_{start}"]
            print(f"      refined from {start} ({r['from']} start): {r['rot']:.3f} deg, t {r['t']:.4f} units, "
                  f"cameras {r['cam']:.4f} units -> {'success' if r['ok'] else 'failure'} "
                  f"({'success' if r['ok_cam'] else 'failure'} on cameras) ({r['seconds']:.0f} s)", flush=True)

    ok = [r for r in rows if r["ok"]]
    n = len(rows)
    print(f"\ncoarse step alone: success {len(ok)}/{n} ({100 * len(ok) / n:.0f}%)")
    if ok:
        for key, unit in (("rot", "deg"), ("t", "units"), ("scale", "%"), ("cam", "units")):
            vals = np.array([r[key] for r in ok])
            print(f"  {key:5s} error {unit:10s} median {np.median(vals):.4f}  mean {vals.mean():.4f}  max {vals.max():.4f}")
        for name, key in (("3-D fit only (baseline, same run)", "fit_3d"), ("with the reprojection refinement", None)):
            errs = [r[key] if key else r for r in rows if (key in r if key else r["ok"])]
            within = sum(e["rot"] <= 1.0 and e["t"] <= 0.02 for e in errs)
            within_cam = sum(e["rot"] <= 1.0 and e["cam"] <= 0.02 for e in errs)
            print(f"  {name}: within 1 deg / 0.02 units {within}/{n} on the transform's translation, "
                  f"{within_cam}/{n} on B's camera centres; median {np.median([e['rot'] for e in errs]):.3f} deg, "
                  f"t {np.median([e['t'] for e in errs]):.4f}, cameras {np.median([e['cam'] for e in errs]):.4f}")
    ratio = [r["rot"] / r["sigma"] for r in ok if np.isfinite(r.get("sigma", np.nan))]
    if ratio:
        print(f"  rotation error / the estimate's sigma: median {np.median(ratio):.2f}, max {max(ratio):.2f} "
              f"(1-sigma of a 3-D rotation: about 0.9 expected)")
    basin = sum(r["init_rot"] <= 45.0 and r["init_t"] <= 1.0 for r in rows)
    print(f"identity start within the paper's basin (<= 45 deg and <= 1 unit): {basin}/{n}")
    sums = np.array([r["sum_b"] for r in rows])
    print(f"summary bytes per robot: median {np.median(sums) / 1e3:.1f} KB, max {sums.max() / 1e3:.1f} KB; "
          f"robot images: median {np.median([r['png_b'] for r in rows]) / 1e6:.2f} MB as 400x400 PNG files, "
          f"{np.median([r['raw_b'] for r in rows]) / 1e6:.2f} MB raw RGBA at 100x100")
    for start in starts:
        done = [r[f"refined_{start}"] for r in rows]
        wins, wins_cam = sum(d["ok"] for d in done), sum(d["ok_cam"] for d in done)
        print(f"joint optimisation from the {start} start ({args.refine_rounds} x {args.refine_steps} steps): "
              f"success {wins}/{n} ({100 * wins / n:.0f}%) on the transform's translation, {wins_cam}/{n} "
              f"({100 * wins_cam / n:.0f}%) on B's camera centres; median final error "
              f"{np.median([d['rot'] for d in done]):.3f} deg, t {np.median([d['t'] for d in done]):.4f}, "
              f"cameras {np.median([d['cam'] for d in done]):.4f} units")
    if args.json:
        import json

        args.json.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, "trials": rows},
                                        indent=2, default=float) + "\n")
    print(f"time per robot summary {np.mean([r['t_sum'] for r in rows]):.2f} s, per estimate "
          f"{np.mean([r['t_est'] for r in rows]):.2f} s ({args.threads} threads)")


if __name__ == "__main__":
    main()
