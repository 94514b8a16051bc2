"""The report of one scenario run: what each robot achieved, round by round, against the truth.

The evaluation is ``agent.evaluation``'s: every robot's kept snapshots scored round by round
(:func:`agent.evaluation.score_run`: PSNR/SSIM on the held-out views of the whole scene and on
those only *other* robots saw, the pose error against ``truth.json``, the consensus
disagreement), and with ``[baseline] enabled`` the points of comparison trained after the run
with the same steps as each robot (``rounds * steps_per_round`` unless ``baseline.steps``):
the centralised model, and each robot alone (:func:`agent.evaluation.run_baselines`). Robots
with images only have their SfM frames calibrated to the world first; the fit's residual is
reported with the results, since it bounds how exactly they can be measured.

This module adds what the run recorded (telemetry: loss, bytes per link, seconds per step and
waiting; ``run.json``: the faults applied and when) and writes ``report.json``, ``report.md``,
``convergence.png``, ``renders.png`` and ``orbit.gif`` into the run folder (``cli.scenario.figures``).
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any, Callable

from agent.data.views import DataError
from agent.evaluation import Baselines, RunScores, ScoringOptions, SwarmRun, run_baselines, score_run, summarise
from agent.files import read_json
from agent.metrics import finite_mean
from agent.telemetry import RoundRecord, read_telemetry
from cli.config import from_dict
from cli.scenario.figures import plot_convergence, poses_known, render_sheet, write_orbit
from cli.scenario.meeting import markdown as meeting_markdown
from cli.scenario.meeting import meetings
from cli.scenario.spec import ScenarioSpec

__all__ = ["build_report", "load_run_spec"]


def _nan_to_none(x: Any) -> Any:
    if isinstance(x, float) and (math.isnan(x) or math.isinf(x)):
        return None
    if isinstance(x, dict):
        return {k: _nan_to_none(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_nan_to_none(v) for v in x]
    return x


def _run_doc(out: Path) -> dict:
    doc = read_json(out / "run.json", DataError)
    if not isinstance(doc, dict) or not isinstance(doc.get("scenario"), dict):
        raise DataError(f"{out / 'run.json'}: not the run.json of `dinerf-agent scenario run` (no scenario table)")
    return doc


def load_run_spec(out: Path) -> ScenarioSpec:
    """The spec a run was made with (from its run.json)."""
    doc = _run_doc(out)
    data = dict(doc["scenario"])
    path = data.pop("path", None)
    spec = from_dict(ScenarioSpec, data)
    spec.path = Path(path) if path else None
    return spec


def swarm_run(out: Path, ids: list[int], recorded: bool = False) -> SwarmRun:
    """A scenario's output folder as the evaluation sees it: the split in data/, robot i's run in robots/<i>/
    (``recorded``: robot i's data is the bag in data/robot<i>/)."""
    from cli.scenario.recordings import recording_of

    data = {i: recording_of(out / "data" / f"robot{i}") for i in ids} if recorded else None
    return SwarmRun(out / "data", {i: out / "robots" / str(i) for i in ids}, data)


def build_report(out: Path, echo: Callable[[str], None] = print) -> dict:
    """Evaluate a finished (or stopped) run in ``out`` and write the report files. Returns report.json's dict.

    The settings are run.json's: the scenario as the robots ran it, ``[training.train]`` fitted to the
    split's capture (agent.defaults). The scenario file's own spec leaves unset what the fit filled, and
    baselines trained from it would be other models than the robots' (a larger field, another grid)."""
    import torch

    out = Path(out)
    spec = load_run_spec(out)
    run_doc = _run_doc(out)
    torch.set_num_threads(spec.report.threads)
    t0 = time.monotonic()

    def log(msg: str) -> None:
        echo(f"[report] {msg}")

    run = swarm_run(out, spec.ids, spec.record.enabled)
    telemetry = {i: read_telemetry(run.folder(i).telemetry) for i in spec.ids}
    opts = ScoringOptions(every=spec.report.eval_every, with_ssim=spec.report.ssim,
                          fit_pose_steps=spec.report.fit_heldout_poses_steps,
                          own_views_every=spec.report.own_views_every)
    parts: dict[str, float] = {}  # how long each part of the report took (s)

    def timed(part: str, fn):
        t = time.monotonic()
        try:
            return fn()
        finally:
            parts[part] = time.monotonic() - t

    scores = timed("scoring", lambda: score_run(run, opts, log, workers=spec.report.workers))
    report = _report_doc(spec, run_doc, scores, telemetry)
    if spec.record.replay:  # robots that trained while exploring: when they met, when they were aligned
        report["meetings"] = meetings(out, spec.ids, spec.links, (run_doc.get("split") or {}).get("recordings") or {},
                                      telemetry, spec.reference_id)
    if spec.training.own_holdout_every > 0:  # no truth needed: every robot on every robot's own held-out frames
        report["cross"] = timed("cross", lambda: _cross(run, spec, log))
    baselines = None
    if spec.baseline.enabled:
        baselines, reused = timed("baselines", lambda: _baselines(spec, run, log))
        report["baseline"] = {**baselines.to_dict(), "reused": reused}
    report["summary"] = summarise(scores, baselines).to_dict()
    report["figures"] = timed("figures", lambda: _figures(report, scores, spec, out, baselines, log))
    report["seconds_report"] = time.monotonic() - t0
    report["seconds_report_parts"] = parts
    report = _nan_to_none(report)
    (out / "report.json").write_text(json.dumps(report, indent=2, default=str) + "\n")
    (out / "report.md").write_text(_markdown(report, spec, spec.ids))
    log(f"wrote {out / 'report.md'} ({report['seconds_report']:.0f} s)")
    return report


def _figures(report: dict, scores: RunScores, spec: ScenarioSpec, out: Path, baselines: Baselines | None,
             log: Callable[[str], None]) -> dict:
    """convergence.png, renders.png and orbit.gif; what each shows (report.json's "figures")."""
    known = poses_known(spec)
    doc = {"poses_known": known,
           "convergence": plot_convergence(report, spec.ids, out / "convergence.png", show_pose=not known)}
    render_sheet(scores.finals, scores.evalset, spec, out / "renders.png",
                 baselines.centralised.renders if baselines is not None else None)
    if spec.report.orbit_frames and scores.finals:
        ref = spec.reference_id if spec.reference_id in scores.finals else min(scores.finals)
        models = scores.finals if spec.report.orbit_all_robots else {ref: scores.finals[ref]}
        orbit = write_orbit(models, ref, spec.report.orbit_frames, scores.evalset.views.width, out / "orbit.gif")
        log(f"orbit: {orbit['frames']} frames of robots {orbit['robots']} ({orbit['seconds']:.1f} s)")
        doc["orbit"] = orbit
    return doc


def _cross(run: SwarmRun, spec: ScenarioSpec, log: Callable[[str], None]) -> dict:
    """report.json's "cross": agent.evaluation.cross on the robots' final checkpoints."""
    from agent.evaluation.cross import score_cross

    setups = {i: run.load_setup(i) for i in run.ids if run.folder(i).checkpoint.exists()}
    log(f"robots {sorted(setups)} on each other's own held-out frames, through their estimated poses")
    return score_cross({i: s.trainer for i, s in setups.items()}, {i: s.holdout for i, s in setups.items()},
                       with_ssim=spec.report.ssim, run_dirs=run.run_dirs).to_dict()


def _baselines(spec: ScenarioSpec, run: SwarmRun, echo: Callable[[str], None]) -> tuple[Baselines, bool]:
    """The baselines, from the cache when the same inputs and code trained them before; and whether they were."""
    from agent.evaluation.baseline_cache import baseline_key, dataset_fingerprint, load_cached, store_cached
    from cli.config import to_dict

    steps = spec.baseline.steps or spec.training.total_steps
    split = {name: (run.split_dir / name).read_text() for name in ("split.json", "truth.json")
             if (run.split_dir / name).is_file()}
    key = baseline_key({"dataset": dataset_fingerprint(spec.resolved_dataset()), "width": spec.width,
                        "training": to_dict(spec.training), "split": split, "steps": steps,
                        "alone": spec.baseline.alone, "ssim": spec.report.ssim, "robots": spec.ids,
                        "workers": spec.report.workers,  # the centralised model's threads without the robots alone
                        "record": to_dict(spec.record) if spec.record.enabled else None,
                        "box": _swarm_box(run) if spec.record.enabled else None})
    if spec.baseline.reuse and (cached := load_cached(key)) is not None:
        echo(f"baseline: the same models on the same data and code were trained before: reused (cache {key})")
        return cached, True
    baselines = run_baselines(run, dataset=spec.resolved_dataset(), width=spec.width, training=spec.training,
                              test_every=spec.split.test_every, steps=steps, alone=spec.baseline.alone,
                              with_ssim=spec.report.ssim, echo=echo, on_robots_frames=spec.record.enabled,
                              workers=spec.report.workers)
    store_cached(key, baselines)
    return baselines, False


def _swarm_box(run: SwarmRun) -> list | None:
    """The box a recorded run's centralised model trains in (the swarm's: it may differ between runs
    of the same inputs, e.g. from the first keyframes of a replay), for the baselines' cache key."""
    from agent.evaluation.baselines import swarm_box
    from agent.evaluation.evalset import EvalSet

    box = swarm_box(run, EvalSet.from_dir(run.split_dir).reference_id)
    return None if box is None else box.tolist()


# --------------------------------------------------------------------------------------------
# report.json
# --------------------------------------------------------------------------------------------


def _report_doc(spec: ScenarioSpec, run_doc: dict, scores: RunScores, telemetry: dict[int, list[RoundRecord]]) -> dict:
    """report.json but for the baselines and the summary."""
    views = scores.evalset.views
    notes = list(scores.notes)
    if spec.split.depth_prior == "scaled":
        notes.append("depth prior: the true depth with a random per-image scale/shift (synthetic)")
    return {
        "scenario": spec.name,
        "description": spec.description,
        "mode": run_doc.get("mode"),
        "ok": run_doc.get("ok"),
        "reason": run_doc.get("reason"),
        "seconds_run": run_doc.get("seconds"),
        "split": run_doc.get("split"),
        "dataset": spec.dataset,
        "robots": {str(i): _robot_doc(i, telemetry[i], scores, run_doc) for i in spec.ids},
        "links_bytes": _links_bytes(telemetry),
        "faults": [e for e in run_doc.get("events", []) if e.get("event") == "fault"],
        "heldout_views": len(views),
        # [fx, width] of the held-out views: the truth the robots' SfM focal lengths are compared with
        "truth_focal_px": [float(views.intrinsics[0, 0]), views.width],
        "notes": notes,
    }


def _robot_doc(i: int, recs: list[RoundRecord], scores: RunScores, run_doc: dict) -> dict:
    """One robot: its rounds (telemetry and scores side by side), its final scores, its totals."""
    by_round = {r.round: _telemetry_row(r) for r in recs}
    scored = {k: s.to_dict() for k, s in scores.rounds[i].items()}
    final = scores.final(i)
    process = run_doc.get("robots", {}).get(str(i), {})
    doc = {
        "rounds": {str(k): {**by_round.get(k, {}), **scored.get(k, {})} for k in sorted(set(by_round) | set(scored))},
        "final_round": scores.final_round(i),
        "final": final.to_dict() if final is not None else {},
        "seconds_per_step_mean": finite_mean(r.seconds_per_step for r in recs),
        "seconds_compute_total": sum(r.seconds_compute for r in recs),
        "seconds_wait_total": sum(r.seconds_wait for r in recs),
        "bytes_out_total": sum(r.bytes_out for r in recs),
        "rejected": recs[-1].rejected if recs else {},
        "rounds_logged": len(recs),
        "starts": process.get("starts"),
        "state": process.get("state"),
    }
    if i in scores.evalset.calibration:
        doc["calibration"] = scores.evalset.calibration[i].summary()
    return doc


def _telemetry_row(r: RoundRecord) -> dict:
    return {
        "loss": r.loss, "own_psnr": r.psnr, "heard": r.heard, "live_neighbours": r.live_neighbours,
        "reference": r.reference, "bytes_in": {str(j): b for j, b in r.bytes_in.items()},
        "bytes_out": r.bytes_out, "seconds_compute": r.seconds_compute, "seconds_wait": r.seconds_wait,
        "seconds_per_step": r.seconds_per_step, "steps": r.steps, "time": r.time,
    }


def _links_bytes(telemetry: dict[int, list[RoundRecord]]) -> dict[str, int]:
    """Bytes received over the whole run, per link ``"<sender>-><receiver>"``."""
    links: dict[str, int] = {}
    for i, recs in telemetry.items():
        for r in recs:
            for sender, b in r.bytes_in.items():
                links[f"{sender}->{i}"] = links.get(f"{sender}->{i}", 0) + int(b)
    return links


# --------------------------------------------------------------------------------------------
# Markdown
# --------------------------------------------------------------------------------------------


def _f(x, fmt=".2f") -> str:
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, fmt)


def _markdown(report: dict, spec: ScenarioSpec, ids: list[int]) -> str:
    sections = (_md_header(report, spec), _md_finals(report, ids), _md_final_extras(report, spec, ids),
                _md_meetings(report), _md_cross(report), _md_calibration(report, ids), _md_comparison(report, spec, ids),
                _md_faults(report), _md_links(report))
    return "\n".join([line for lines in sections + (_md_figures(report),) for line in lines])


def _md_figures(report: dict) -> list[str]:
    figs = report.get("figures") or {}
    lines = ["## Convergence", ""]
    if figs.get("poses_known"):
        lines += ["The poses are known (shared frame, fixed at the identity): no pose panels.", ""]
    lines += ["![convergence](convergence.png)", "", "## Renders (held-out views, shared frame)", "",
              "![renders](renders.png)", ""]
    orbit = figs.get("orbit")
    if orbit:
        who = (f"robots {', '.join(map(str, orbit['robots']))}" if len(orbit["robots"]) > 1
               else f"robot {orbit['robots'][0]}")
        lines += ["## Orbit (final models, shared frame)", "",
                  f"The final model of {who} along one orbit of robot {orbit['orbit_of']}'s cameras "
                  f"({orbit['frames']} frames at {orbit['render_size'][1]}x{orbit['render_size'][0]}): colour | depth.",
                  "", "![orbit](orbit.gif)", ""]
    return lines


def _md_header(report: dict, spec: ScenarioSpec) -> list[str]:
    lines = [f"# Scenario `{spec.name}`", ""]
    if spec.description:
        lines += [spec.description, ""]
    sp = report.get("split") or {}
    parts = report.get("seconds_report_parts") or {}
    lines += [
        f"- outcome: **{'completed' if report['ok'] else 'FAILED'}** ({report['reason']}), "
        f"{_f(report['seconds_run'], '.0f')} s, mode `{report['mode']}`; this report "
        f"{_f(report.get('seconds_report'), '.0f')} s ("
        + ", ".join(f"{k} {_f(v, '.0f')} s" for k, v in parts.items()) + ")",
        f"- data: `{spec.dataset}` at {sp.get('resolution')}"
        + (f" (robots' images at {sp['robot_resolution']})" if sp.get("robot_resolution") not in (None, sp.get("resolution")) else "")
        + f", {spec.robots} robots, mean overlap "
        f"{_f(100 * sp['mean_overlap'] if sp.get('mean_overlap') is not None else None, '.0f')}%, "
        + ("images only (each robot's frame is its own SfM's), " if spec.split.images_only
           else "frames: each robot's own odometry frame (its bag's), " if spec.record.enabled
           else f"frames `{spec.split.frame}`, ")
        + f"topology `{spec.topology.kind}` ({', '.join(f'{a}-{b}' for a, b in spec.links)})",
        f"- training: {spec.training.rounds} rounds x {spec.training.steps_per_round} steps, rho0 "
        f"{spec.training.consensus.rho0:g}, pose `{spec.training.train.pose.mode}`",
        f"- evaluation: {report['heldout_views']} held-out views of the whole scene (every "
        f"{spec.split.test_every}th); 'others only' = held-out views outside the robot's own sector",
        *([f"- data credit: {spec.credit}"] if spec.credit else []),
        *([_md_recordings(spec, sp.get("recordings") or {})] if spec.record.enabled else []),
        "",
    ]
    return lines + [f"- note: {note}" for note in report.get("notes", [])]


def _md_recordings(spec: ScenarioSpec, recordings: dict) -> str:
    r = spec.record
    kinds = ", ".join(f"robot {i}: {v['storage']} ({v['images']} images, {v['tf']} transforms)"
                      for i, v in sorted(recordings.items(), key=lambda kv: int(kv[0])))
    return (f"- recordings: each robot ran from a ROS 2 bag of its views ({kinds}): images at {r.image_rate_hz:g} Hz "
            f"({r.encoding}), /tf at {r.tf_rate_factor}x that, camera tilted {r.mount_tilt_deg:g} deg on its mount, "
            f"lens k1 {r.k1:g} in CameraInfo, each in its own odometry frame (a random rotation and a "
            f"{r.offset_translation:g}-unit shift); swarm file as `init` writes it (local frames, no scene file); "
            "pose errors are against those offsets")


def _md_finals(report: dict, ids: list[int]) -> list[str]:
    s = report["summary"]
    lines = ["## Final state per robot", "",
             "| robot | round | PSNR all | SSIM all | PSNR others-only | rot err (deg) | trans err | disagreement | s/step | wait (s) | MB out | starts |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for i in ids:
        r = report["robots"][str(i)]
        f = r["final"]
        lines.append(
            f"| {i} | {r['final_round']} | {_f(f.get('psnr'))} | {_f(f.get('ssim'), '.3f')} | {_f(f.get('psnr_others_only'))} | "
            f"{_f(f.get('rotation_error_deg'))} | {_f(f.get('translation_error'), '.3f')} | {_f(f.get('disagreement'), '.2e')} | "
            f"{_f(r['seconds_per_step_mean'], '.3f')} | {_f(r['seconds_wait_total'], '.1f')} | "
            f"{_f(r['bytes_out_total'] / 1e6, '.1f')} | {r['starts']} |"
        )
    return lines + ["", f"Mean PSNR {_f(s['mean_psnr'])} dB (others-only {_f(s['mean_psnr_others_only'])} dB); "
                    f"worst pose error {_f(s['max_rotation_error_deg'])} deg / {_f(s['max_translation_error'], '.3f')} (scene units).", ""]


def _md_final_extras(report: dict, spec: ScenarioSpec, ids: list[int]) -> list[str]:
    """The final models' costlier scores, one sentence each, where they were computed."""

    def per_robot(key: str, text: str) -> list[str]:
        values = {i: report["robots"][str(i)]["final"].get(key) for i in ids}
        if all(v is None for v in values.values()):
            return []
        return [text + ", ".join(f"robot {i} {_f(v)}" for i, v in values.items()) + " dB.", ""]

    return (
        per_robot("psnr_pose_fitted", f"With each held-out view's pose fitted to its image through the robot's frozen field "
                  f"({spec.report.fit_heldout_poses_steps} steps; the test-time pose optimisation of pose-free NeRF "
                  f"evaluation): PSNR all ")
        + per_robot("psnr_own_views", f"Fit of each robot's own training views (one in {spec.report.own_views_every}, "
                    "through its own cameras, as refined if it refines them; a shared field that cannot fit every "
                    "robot's views, from cameras that disagree or a box that clips the scene, shows here first): PSNR ")
        + per_robot("psnr_true_intrinsics", "The held-out views are rendered through the shared frame's camera: the "
                    "reference's focal length as its SfM found it and training refined it (see 'Evaluation frames'). "
                    "With the truth's focal length instead, the views placed as above: PSNR all ")
    )


def _md_meetings(report: dict) -> list[str]:
    if "meetings" not in report:
        return []
    errors = {i: (r["final"].get("rotation_error_deg"), r["final"].get("translation_error"))
              for i, r in report["robots"].items()}
    return meeting_markdown(report["meetings"], errors)


def _md_cross(report: dict) -> list[str]:
    """Every robot's field on every robot's own held-out frames, and the frames found: what needs no truth."""
    cross = report.get("cross")
    if not cross or not cross.get("frames"):
        return []
    owners = sorted(cross["frames"], key=int)
    lines = ["## Without ground truth: each robot's field on each robot's own held-out frames", "",
             "Robot i's field (row) renders robot j's held-out frames (column) through robot j's *estimated* pose: "
             "equal rows mean the maps agree and the poses are right.", "",
             "| field of | " + " | ".join(f"robot {j}'s {cross['frames'][j]} frames" for j in owners)
             + " | mean on others' |", "|---|" + "---|" * (len(owners) + 1)]
    for i in sorted(cross["psnr"], key=int):
        lines.append(f"| robot {i} | " + " | ".join(_f(cross["psnr"][i].get(j)) for j in owners)
                     + f" | {_f(cross['mean_others'].get(i))} |")
    lines += ["", "| robot | state | rotation (deg) | |t| | coarse step: rotation sigma (deg) | via | inliers |",
              "|---|---|---|---|---|---|---|"]
    for i, r in sorted(cross["robots"].items(), key=lambda kv: int(kv[0])):
        lines.append(f"| {i} | {r['alignment']} | {_f(r['rotation_deg'])} | {_f(r['translation'], '.3f')} | "
                     f"{_f(r['rotation_sigma_deg'], '.3f')} | {r['via'] if r['via'] is not None else '-'} | "
                     f"{r['inliers'] if r['inliers'] is not None else '-'} |")
    return lines + [""]


def _md_calibration(report: dict, ids: list[int]) -> list[str]:
    cals = {i: report["robots"][str(i)].get("calibration") for i in ids}
    if not any(cals.values()):
        return []
    lines = ["## Evaluation frames (images only)", "",
             "Each robot's SfM frame is aligned to the world by a Sim(3) fit of its camera centres to the true ones "
             "(the standard evaluation of pose-free NeRF). The residuals bound how exactly the scores above can "
             "be measured: the held-out cameras are placed through the reference's fit, each pose error through two fits.",
             "",
             "| robot | cameras matched | used by the fit | centre error, median (scene units) | rotation error, median (deg) | scene units per SfM unit | focal length / truth's |",
             "|---|---|---|---|---|---|---|"]
    truth_focal = report.get("truth_focal_px")
    for i, c in cals.items():
        if c:
            ratio = (c["focal_px"] / truth_focal[0] * truth_focal[1] / c["width"]
                     if truth_focal and c.get("focal_px") else None)
            lines.append(f"| {i} | {c['matched']} | {c['inliers']} | {_f(c['centre_error_median'], '.4f')} | "
                         f"{_f(c['rotation_error_median_deg'], '.3f')} | {_f(c['scale'], '.4g')} | {_f(ratio, '.4f')} |")
        else:
            lines.append(f"| {i} | n/a | n/a | n/a | n/a | n/a | n/a |")
    return lines + [""]


def _md_comparison(report: dict, spec: ScenarioSpec, ids: list[int]) -> list[str]:
    b, s = report.get("baseline"), report["summary"]
    if not b:
        return []
    lines = ["## Comparison (same steps per model)", "",
             f"Centralised model ({'the frames the robots kept' if spec.record.enabled else 'all views'}, true poses, "
             f"{b['steps']} steps, {b['centralised'].get('field_parameters') or 'n/a'} field parameters): "
             f"PSNR **{_f(b['centralised']['psnr'])}** dB, "
             f"SSIM {_f(b['centralised']['ssim'], '.3f')}; swarm mean {_f(s['mean_psnr'])} dB "
             f"(gap {_f(s.get('gap_to_centralised_db'))} dB)."
             + (" The baselines were trained before on the same data, settings and code, and reused." if b.get("reused")
                else ""), ""]
    if "alone" not in b:
        return lines
    lines += ["| robot | swarm PSNR all | alone PSNR all | swarm others-only | alone others-only | gain others-only (dB) |",
              "|---|---|---|---|---|---|"]
    for i in ids:
        f, a = report["robots"][str(i)]["final"], b["alone"][str(i)]
        gain = s.get("gain_over_alone_others_only_db", {}).get(str(i))
        lines.append(f"| {i} | {_f(f.get('psnr'))} | {_f(a.get('psnr'))} | {_f(f.get('psnr_others_only'))} | "
                     f"{_f(a.get('psnr_others_only'))} | {_f(gain)} |")
    for i in ids:
        if b["alone"][str(i)].get("error"):
            lines.append(f"- robot {i} alone failed: {b['alone'][str(i)]['error']}")
    return lines + ["", "'Alone' trains on the robot's own views only, with its pose fixed to the truth"
                    + (" (images only: its calibrated SfM frame, and the split's field box)." if spec.split.images_only else "."), ""]


def _md_faults(report: dict) -> list[str]:
    lines = ["## Faults applied", ""]
    if not report["faults"]:
        return lines + ["none", ""]
    lines += ["| time (s) | swarm round | fault | how | rounds done per robot |", "|---|---|---|---|---|"]
    for e in report["faults"]:
        lines.append(f"| {_f(e.get('time'), '.1f')} | {e.get('swarm_round')} | {e.get('description')} | "
                     f"{e.get('how') or ''} | {e.get('robot_rounds')} |")
    return lines + [""]


def _md_links(report: dict) -> list[str]:
    lines = ["## Bytes per link (received, whole run)", ""]
    if not report["links_bytes"]:
        return lines + ["none recorded", ""]
    rows = [f"| {k} | {v / 1e6:.1f} |" for k, v in sorted(report["links_bytes"].items())]
    return lines + ["| link | MB |", "|---|---|"] + rows + [""]
