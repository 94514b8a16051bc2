"""``dinerf-agent view``: the shared field and every robot's cameras in the browser (viser), live.

The field is rendered on the CPU from the browser's own camera, small while it moves and sharper
once it stops (agent.viewer.scene.RenderScheduler). The run folder is polled: a robot's newest
checkpoint is reloaded when it changes, and the panel follows its telemetry.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import typer

from cli.errors import UserError, friendly_errors
from cli.main import app
from cli.options import RUN_DATA_HELP, RUN_HELP, set_threads

LOOPBACK = ("127.0.0.1", "localhost", "::1")


class Viewer:
    """The viser server of one run: scene, panel, one render scheduler per browser, two threads."""

    def __init__(self, find, shown: int, width: int, moving_width: int, poll_s: float) -> None:
        self.find = find  # () -> the run's robots by id (agent.runs.RobotRun), robots still starting too
        self.models: dict = {}
        self.colours: dict[int, tuple[int, int, int]] = {}
        self._add_robots(self.find())
        self.shown, self.width, self.moving_width, self.poll_s = shown, width, moving_width, poll_s
        self.schedulers: dict[int, object] = {}  # client id -> RenderScheduler, once its camera reported
        self.lock = threading.Lock()
        self.stop = threading.Event()
        self.server = None
        self.panel = self.picker = None
        self.homed = False
        self.frustum_scale = None

    def serve(self, host: str, port: int) -> int:
        """Start the web server (after a first look at the run folder); returns the port bound."""
        import viser

        for model in self.models.values():
            model.refresh()
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        # viser's share button tunnels the page through a public relay: never from here, whoever clicks it
        self.server.request_share_url = lambda *args, **kwargs: None
        self.server.gui.configure_theme(control_width="large", show_share_button=False)
        self.server.scene.set_up_direction("+z")
        self.picker = self.server.gui.add_dropdown("Field of robot", [str(i) for i in self.models],
                                                   initial_value=str(self.shown))
        self.picker.on_update(lambda _: self._show(int(self.picker.value)))
        self.panel = self.server.gui.add_markdown("")
        self.server.on_client_connect(self._connected)
        self.server.on_client_disconnect(lambda c: self._forget(c.client_id))
        for rid in self.models:
            self._draw_cameras(rid)
        self._update_panel()
        for target in (self._render_loop, self._poll_loop):
            threading.Thread(target=target, daemon=True).start()
        return self.server.get_port()

    def close(self) -> None:
        self.stop.set()
        if self.server is not None:
            self.server.stop()

    def _add_robots(self, sources: dict) -> list[int]:
        """Watch the robots not seen before (robots started by hand appear one by one); returns their ids."""
        from agent.viewer.scene import colour_of
        from agent.viewer.source import RobotModel

        new = [i for i in sources if i not in self.models]
        if new:  # a new dict, never a changed one: other threads iterate it
            self.colours = {**self.colours, **{i: colour_of(i) for i in new}}
            self.models = dict(sorted({**self.models, **{i: RobotModel(sources[i]) for i in new}}.items()))
        return new

    def _show(self, robot_id: int) -> None:
        self.shown = robot_id
        if self.models[robot_id].trainer is None:  # nothing to draw yet: not the other robot's picture either
            for client in self.server.get_clients().values():
                client.scene.set_background_image(None)
        self._model_changed()
        self._update_panel()

    def _connected(self, client) -> None:
        from agent.viewer.scene import RenderScheduler

        def moved(_camera) -> None:
            with self.lock:
                if client.client_id not in self.schedulers:
                    self.schedulers[client.client_id] = (client, RenderScheduler(self.moving_width, self.width))
                self.schedulers[client.client_id][1].camera_moved(time.monotonic())

        client.camera.on_update(moved)

    def _forget(self, client_id: int) -> None:
        with self.lock:
            self.schedulers.pop(client_id, None)

    def _model_changed(self) -> None:
        with self.lock:
            for _, sched in self.schedulers.values():
                sched.model_changed()

    def _home(self, trainer) -> None:
        """The first time the shown robot has a model: start every camera at one of its views."""
        from agent.viewer.scene import home_view

        home = home_view(trainer)
        self.frustum_scale = self.frustum_scale or home.frustum_scale
        first = self.server.initial_camera
        first.up, first.position, first.look_at, first.fov = home.up, home.position, home.look_at, home.fov_y
        for client in self.server.get_clients().values():  # set position first: it moves look_at along
            cam = client.camera
            cam.up_direction, cam.position, cam.look_at, cam.fov = home.up, home.position, home.look_at, home.fov_y
        self.server.scene.set_up_direction(home.up)
        self.homed = True

    def _draw_cameras(self, robot_id: int) -> None:
        from agent.viewer.scene import frustums

        trainer = self.models[robot_id].trainer
        if trainer is None:
            return
        if not self.homed and robot_id == self.shown:
            self._home(trainer)
        scale = self.frustum_scale or 0.1
        for f in frustums(trainer, robot_id, self.colours[robot_id]):
            self.server.scene.add_camera_frustum(f.name, f.fov_y, f.aspect, scale=scale, color=f.colour, wxyz=f.wxyz,
                                                 position=f.position, thickness=2.5, thickness_units="screen",
                                                 cast_shadow=False, receive_shadow=False)

    def _update_panel(self) -> None:
        from agent.viewer.scene import panel_markdown
        from agent.viewer.source import RobotStatus

        statuses = [RobotStatus.read(m.source) for m in self.models.values()]
        errors = {i: m.error for i, m in self.models.items() if m.error}
        self.panel.content = panel_markdown(statuses, self.shown, self.models[self.shown].round, self.colours, errors)

    def _poll_loop(self) -> None:
        from agent.data.views import DataError

        while not self.stop.wait(self.poll_s):
            try:
                try:
                    if self._add_robots(self.find()):
                        self.picker.options = [str(i) for i in self.models]
                except DataError:
                    pass  # the folder as it was when we started still holds
                for rid, model in list(self.models.items()):
                    if model.refresh():
                        self._draw_cameras(rid)
                        if rid == self.shown:
                            self._model_changed()
                self._update_panel()
            except Exception as e:  # noqa: BLE001 - the viewer must outlive one bad look at the folder
                print(f"view: polling the run folder failed: {type(e).__name__}: {e}", flush=True)

    def _render_loop(self) -> None:
        while not self.stop.is_set():
            if not self._render_one():
                time.sleep(0.02)

    def _render_one(self) -> bool:
        """Render for the first browser that needs a picture; False when none did."""
        from agent.viewer.scene import c2w_from_browser, render_at_camera

        trainer = self.models[self.shown].trainer
        if trainer is None:
            return False
        now = time.monotonic()
        with self.lock:
            todo = [(c, s, plan) for c, s in self.schedulers.values() if (plan := s.next(now)) is not None]
        if not todo:
            return False
        client, sched, (width, token) = todo[0]
        try:
            cam = client.camera
            c2w = c2w_from_browser(cam.wxyz, cam.position)
            image = render_at_camera(trainer, c2w, cam.fov, cam.aspect, width)
            client.scene.set_background_image(image, format="jpeg", jpeg_quality=90)
        except Exception as e:  # noqa: BLE001 - a browser that left mid-render, say
            print(f"view: render failed: {type(e).__name__}: {e}", flush=True)
        sched.shown(token)
        return True


@app.command()
@friendly_errors
def view(
    run_dir: Path = typer.Argument(..., help=RUN_HELP),
    data: Path = typer.Option(None, "--data", help=RUN_DATA_HELP),
    port: int = typer.Option(8080, help="Port of the web page (the next free one if taken)."),
    host: str = typer.Option("127.0.0.1", help="Address to listen on; 0.0.0.0 shows the model to the whole network."),
    robot: int = typer.Option(None, "--robot", help="Whose model to render (default: the lowest id)."),
    width: int = typer.Option(160, help="Render width in pixels once the camera is still (CPU: keep it small)."),
    moving_width: int = typer.Option(64, help="Render width while the camera moves."),
    poll: float = typer.Option(2.0, help="Seconds between looks at the run folder (new checkpoints, telemetry)."),
    threads: int = typer.Option(1, help="CPU threads for torch (the swarm may be training beside it)."),
) -> None:
    """Look at a swarm's field and cameras in the browser, while it trains or after."""
    from agent.runs import open_run

    def find() -> dict:
        return open_run(run_dir, data, pending=True).robots

    if not (8 <= moving_width <= width <= 1024):
        raise UserError(f"--moving-width {moving_width} and --width {width}: need 8 <= moving width <= width <= 1024")
    if poll <= 0:
        raise UserError(f"--poll {poll}: must be > 0 seconds")
    set_threads(threads)
    sources = find()  # once here: a folder that is no run is refused before any server starts
    shown = min(sources) if robot is None else robot
    if shown not in sources:
        raise UserError(f"--robot {robot}: not one of this run's robots {sorted(sources)}")
    viewer = Viewer(find, shown, width, moving_width, poll)
    bound = viewer.serve(host, port)
    if host not in LOOPBACK:
        typer.echo(f"warning: listening on {host}: anyone who can reach it sees the model (no authentication)")
    note = "" if bound == port or port == 0 else f" (port {port} was taken)"
    typer.echo(f"viewer at http://{'localhost' if host in LOOPBACK else host}:{bound}{note}: robots "
               f"{', '.join(map(str, sources))}, field of robot {shown}; Ctrl-C to stop", err=False)
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        viewer.close()
