"""`dinerf-agent view` end to end: a real swarm trains, the viewer follows it, headless Chromium looks.

Two robots train for real (`up` processes over Zenoh, a tiny procedural scene). The viewer starts
once robot 1 has its first checkpoint, with no --data (the run dirs record their data folders), so
it must reload the newer ones and re-read telemetry while the swarm trains. Chromium (the Debian package, driven by playwright; no browser is
downloaded) then loads the page: the screenshot must show the field (the centre of the picture
is not the plain background, and its colours vary) and both robots' cameras (pixels in their
colours), and the panel must give each robot's final round and PSNR. A drag turns the camera
and the picture follows; the panel's picker switches to robot 2's model.

Needs /usr/bin/chromium (``apt-get install -y chromium``); skipped with that reason without it.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from agent.viewer.scene import colour_of
from tests.system.harness import REPO, make_swarm

CHROMIUM = os.environ.get("DINERF_CHROMIUM", "/usr/bin/chromium")
pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not Path(CHROMIUM).is_file(), reason=f"no {CHROMIUM}: `apt-get install -y chromium` to run it"),
]
ROUNDS = 2
SHOTS = Path(os.environ.get("DINERF_VIEW_SHOTS", "")) if os.environ.get("DINERF_VIEW_SHOTS") else None


def tiny_swarm(root: Path):
    """Two robots, 24 views of 32 px, 2 rounds of 60 steps: ~17 dB, enough to see the scene."""
    return make_swarm(root, robots=2, topology="line", views=24, width=32, training={
        "rounds": ROUNDS, "steps_per_round": 60, "consensus": {"rho0": 1e-5}, "train": {"rays_per_step": 1024}},
        daemon={"startup_wait_s": 10.0})


def _start_viewer(run: Path, log: Path) -> tuple[subprocess.Popen, int]:
    env = dict(os.environ, PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1")
    cmd = [sys.executable, "-m", "cli", "view", str(run), "--port", "0", "--poll", "0.5",
           "--width", "128", "--moving-width", "48"]
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=open(log, "w"), stderr=subprocess.STDOUT)
    t0 = time.monotonic()
    while time.monotonic() - t0 < 60:
        found = re.search(r"viewer at http://localhost:(\d+)", log.read_text())
        if found:
            return proc, int(found.group(1))
        if proc.poll() is not None:
            raise AssertionError(f"the viewer exited with {proc.returncode}:\n{log.read_text()[-3000:]}")
        time.sleep(0.2)
    proc.kill()
    raise AssertionError(f"the viewer did not start:\n{log.read_text()[-3000:]}")


def _near(pixels: np.ndarray, colour: tuple[int, int, int], tol: float = 30.0) -> int:
    return int((np.linalg.norm(pixels.astype(float) - np.array(colour), axis=-1) < tol).sum())


def _field_shown(shot: np.ndarray) -> bool:
    """The middle of the picture is not the plain background and has many colours (not a few lines)."""
    h, w = shot.shape[:2]
    centre = shot[int(0.3 * h):int(0.7 * h), int(0.3 * w):int(0.6 * w)].reshape(-1, 3).astype(int)
    off_white = (np.abs(centre - 255).max(axis=-1) > 40).mean()
    distinct = len({tuple(p) for p in (centre // 16).tolist()})
    return off_white > 0.2 and distinct > 20


def test_viewer_shows_the_field_the_cameras_and_each_robots_round_and_psnr(tmp_path):
    pytest.importorskip("playwright", reason="playwright (the test extra) is not installed")
    from playwright.sync_api import sync_playwright
    import cv2

    swarm = tiny_swarm(tmp_path)
    viewer, t_start = None, time.monotonic()
    try:
        swarm.start_all()
        swarm.wait_round(1, 1)
        viewer, port = _start_viewer(swarm.root / "run", tmp_path / "view.log")  # no --data: data.json
        swarm.wait_all(timeout=120)
        print(f"trained in {time.monotonic() - t_start:.1f} s")
        psnr = {i: swarm.telemetry(i)[-1].psnr for i in swarm.robots}
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox", "--use-gl=swiftshader",
                                                                         "--enable-unsafe-swiftshader"])
            page = browser.new_page(viewport={"width": 800, "height": 600})
            page.goto(f"http://127.0.0.1:{port}")
            done_rows = [re.compile(rf"{i}\s+{ROUNDS} done\s+{psnr[i]:.2f} \(round {ROUNDS}\)") for i in swarm.robots]
            t0, shot, text = time.monotonic(), None, ""
            while time.monotonic() - t0 < 30:
                page.wait_for_timeout(500)
                text = page.inner_text("body")
                path = tmp_path / "view.png"
                page.screenshot(path=str(path))
                shot = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
                if all(r.search(text) for r in done_rows) and f"round {ROUNDS}." in text and _field_shown(shot):
                    page.wait_for_timeout(2000)  # the sharp render follows the small one once the camera is still
                    page.screenshot(path=str(path))
                    shot = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
                    break
            # the free camera: an orbit drag makes the server render the field from the new viewpoint
            page.mouse.move(400, 420)
            page.mouse.down()
            page.mouse.move(520, 400, steps=8)
            page.mouse.up()
            page.wait_for_timeout(2500)
            page.screenshot(path=str(tmp_path / "turned.png"))
            turned = cv2.cvtColor(cv2.imread(str(tmp_path / "turned.png")), cv2.COLOR_BGR2RGB)
            # the panel's robot picker: robot 2's own model instead
            page.get_by_text("Field of robot").locator("xpath=following::input[1]").click()
            page.get_by_role("option", name="2", exact=True).click()
            page.wait_for_timeout(2500)
            switched = page.inner_text("body")
            page.screenshot(path=str(tmp_path / "robot2.png"))
            other = cv2.cvtColor(cv2.imread(str(tmp_path / "robot2.png")), cv2.COLOR_BGR2RGB)
            browser.close()
        print(f"page right after {time.monotonic() - t0:.1f} s")
        if SHOTS:
            SHOTS.mkdir(parents=True, exist_ok=True)
            for name in ("view.png", "turned.png", "robot2.png"):
                shutil.copy(tmp_path / name, SHOTS / name)
        for i, row in zip(swarm.robots, done_rows):
            assert psnr[i] is not None and row.search(text), (i, text)
        assert f"Field drawn: robot 1's model, round {ROUNDS}." in text, text  # the newest checkpoint was reloaded
        assert _field_shown(shot), "the field is not in the middle of the picture"
        for i in swarm.robots:  # every robot's frustums, in its colour
            assert _near(shot, colour_of(i)) > 40, f"no camera of robot {i} in sight"
        h, w = shot.shape[:2]
        middle = (slice(int(0.3 * h), int(0.7 * h)), slice(int(0.3 * w), int(0.6 * w)))
        assert _field_shown(turned), "after the drag the field is not in the middle of the picture"
        assert np.abs(turned[middle].astype(int) - shot[middle]).mean() > 5, "the picture did not follow the camera"
        assert f"Field drawn: robot 2's model, round {ROUNDS}." in switched, switched
        assert _field_shown(other), "robot 2's field is not in the middle of the picture"
        assert viewer.poll() is None, (tmp_path / "view.log").read_text()[-3000:]
    finally:
        swarm.stop()
        if viewer is not None:
            viewer.terminate()
            viewer.wait(timeout=10)
