"""``pidg view RUN``: a web viewer of a trained dynamic scene, built on viser.

The browser is a free camera; every frame is rendered here by pidg's own renderer (the numba kernel on a CPU, gsplat
on CUDA) and sent to the page as its background picture, so what you see is what ``pidg render`` would write. The
panel has the time slider (dataset time in [0, 1]) with play/pause, the picture to show (colour, depth, the material
field's velocity as arrows or colours and its stress magnitude, the dynamic/static split, as far as the run has
them), the training cameras as frustums (click one to look through it at its time) and the last frame's size and
render time.

Progressive quality: while the camera moves or the time plays, frames are rendered at a fraction of the canvas
(``--preview-scale``); once nothing has changed for a quarter of a second the view is rendered again at full size.
Each browser tab has its own render thread that always renders the newest camera, so a slow frame never queues up
stale ones. viser is an optional dependency (``pip install 'pidg[view]'``), imported only when a viewer starts.
"""
from __future__ import annotations

import dataclasses
import errno
import logging
import math
import socket
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pidg.checkpoint import CONFIG_FILE
from pidg.config_tools import load_config
from pidg.data import load_scene
from pidg.device import Device
from pidg.export import check_run_folder, check_time, open_run_model
from pidg.models.dynamic_gaussians import DynamicGaussians
from pidg.render import Camera
from pidg.training.config import TrainConfig
from pidg.viewer.frames import COLOUR, Quality, ViewRenderer, camera_from_pose, measure_frame_times, pose_of_camera

logger = logging.getLogger(__name__)

VISER_HINT = "pidg view needs viser: pip install 'pidg[view]' (or pip install 'viser>=1.0')"


def import_viser() -> Any:
    """The viser module, or an ImportError that says in one line what to install."""
    try:
        import viser
    except ImportError as err:
        raise ImportError(f"{VISER_HINT} ({err})") from None
    return viser


def check_port(host: str, port: int) -> None:
    """Raise an OSError naming the port when nothing could listen on ``host:port`` now (0: any free port)."""
    if not 0 <= port <= 65535:
        raise ValueError(f"--port {port}: must be in 0..65535 (0: any free port)")
    if port == 0:
        return
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server will: a closed one's TIME_WAIT is no obstacle
        try:
            probe.bind((host, port))
        except OSError as err:
            if err.errno == errno.EADDRINUSE:
                raise OSError(
                    f"--port {port}: port {port} on {host} is in use (another pidg view?): choose another with --port, "
                    "or --port 0 for any free one"
                ) from None
            raise OSError(f"--host {host} --port {port}: cannot listen there ({err.strerror or err})") from None


DEFAULT_UP = (0.0, 0.0, 1.0)  # without training cameras: z up (D-NeRF's and Blender's worlds)
DEFAULT_EYE_OFFSET = (0.0, -3.0, 1.5)  # ... and the camera this many scene radii from the centre
START_BEHIND = 1.4  # the browser starts this many times farther from the centre than the first training camera
FRUSTUM_SIZE = 0.04  # frustum depth as a fraction of the training cameras' distance to the centre


def scene_centre_and_radius(model: DynamicGaussians, t: float) -> tuple[np.ndarray, float]:
    """Where the Gaussians are at time ``t``: their median position and the radius holding 95 % of them."""
    with torch.no_grad():
        means = model.at(t).means.detach().float().cpu()
    if not len(means):
        return np.zeros(3), 1.0
    centre = means.median(dim=0).values
    radius = float(torch.quantile((means - centre).norm(dim=-1), 0.95))
    return centre.numpy().astype(np.float64), max(radius, 1e-3)


def cameras_focus(cameras: list[Camera]) -> np.ndarray | None:
    """The point the cameras look at: least squares over their optical axes (None when they are parallel)."""
    a, b = np.zeros((3, 3)), np.zeros(3)
    for camera in cameras:
        _, centre = pose_of_camera(camera)
        axis = np.asarray(camera.viewing_direction.tolist(), np.float64)
        off_axis = np.eye(3) - np.outer(axis, axis) / max(float(axis @ axis), 1e-12)
        a += off_axis
        b += off_axis @ centre
    if len(cameras) < 2 or np.linalg.cond(a) > 1e6:
        return None
    return np.linalg.solve(a, b)


@dataclass(frozen=True)
class TrainingView:
    """A training camera and its dataset time, drawn as a frustum."""

    camera: Camera
    time: float


def training_views(run_dir: Path) -> list[TrainingView]:
    """The run's training cameras, read from its dataset (RUN/config.json names it); none, with a warning, when the
    dataset is not where the run left it."""
    config_path = Path(run_dir) / CONFIG_FILE
    if not config_path.is_file():
        logger.warning("%s: no %s, so no training cameras to show", run_dir, CONFIG_FILE)
        return []
    try:
        data = load_config(TrainConfig, config_path).data
        scene = load_scene(dataclasses.replace(data, splits=("train",), progress=False, max_frames=None))
    except (OSError, ValueError, KeyError) as err:
        logger.warning("training cameras not shown: %s", " ".join(str(err).split()))
        return []
    return [TrainingView(frame.camera, frame.time) for frame in scene.train]


@dataclass
class FrameStat:
    """One frame sent to a browser: its size, quality, render time and render + JPEG-encode time (ms)."""

    width: int
    height: int
    full: bool
    mode: str
    t: float
    render_ms: float
    total_ms: float


class _ClientView:
    """One browser tab: a thread that renders its newest camera, a preview while things change, then full size."""

    def __init__(self, viewer: "Viewer", client: Any) -> None:
        self.viewer = viewer
        self.client = client
        self._cond = threading.Condition()
        self._version = 0  # bumped by every change of camera, time or picture
        self._changed_at = time.monotonic()
        self._shown_version = -1
        self._shown_full = False
        self._closed = False
        client.camera.on_update(lambda _camera: self.touch())
        self._thread = threading.Thread(target=self._run, name=f"pidg-view-client-{client.client_id}", daemon=True)
        self._thread.start()

    def touch(self) -> None:
        with self._cond:
            self._version += 1
            self._changed_at = time.monotonic()
            self._cond.notify()

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify()

    def _next(self) -> tuple[int, bool] | None:
        """Wait until there is something to render: (version, full quality), or None once closed."""
        rest = self.viewer.quality.rest_seconds
        with self._cond:
            while not self._closed:
                idle = time.monotonic() - self._changed_at
                resting = idle >= rest and not self.viewer.playing
                if self._version != self._shown_version or (resting and not self._shown_full):
                    return self._version, resting
                self._cond.wait(None if self._shown_full or self.viewer.playing else max(rest - idle, 0.01))
            return None

    def _run(self) -> None:
        while True:
            job = self._next()
            if job is None:
                return
            version, full = job
            try:
                self._render(full)
            except Exception:  # noqa: BLE001 - a failed frame is logged; the viewer keeps serving
                logger.exception("pidg view: a frame failed")
                time.sleep(0.5)
            with self._cond:
                self._shown_version, self._shown_full = version, full

    def _render(self, full: bool) -> None:
        camera_handle = self.client.camera
        quality = self.viewer.quality
        width, height = quality.size(camera_handle.image_width, camera_handle.image_height, full)
        camera = camera_from_pose(camera_handle.wxyz, camera_handle.position, camera_handle.fov, width, height,
                                  camera_handle.near, camera_handle.far)
        start = time.perf_counter()
        view = self.viewer.renderer.render(camera, self.viewer.time, self.viewer.mode)
        jpeg = quality.jpeg_quality_full if full else quality.jpeg_quality_preview
        self.client.scene.set_background_image(view.image, format="jpeg", jpeg_quality=jpeg)
        total = 1000.0 * (time.perf_counter() - start)
        self.viewer._record(FrameStat(width, height, full, view.mode, view.t, view.render_ms, total), view.caption)


@dataclass
class ViewerOptions:
    """Settings of ``pidg view`` besides the run."""

    host: str = "127.0.0.1"
    port: int = 8080
    device: Device = "auto"
    quality: Quality = field(default_factory=Quality)
    loop_seconds: float = 6.0  # playback: seconds for the time to run from 0 to 1
    cameras: bool = True  # read the training cameras from the run's dataset


class Viewer:
    """A running viewer: a viser server showing ``model`` (``stop()`` ends it)."""

    def __init__(self, model: DynamicGaussians, views: list[TrainingView], options: ViewerOptions, title: str = "pidg") -> None:
        viser = import_viser()
        check_port(options.host, options.port)
        self.model = model
        self.views = views
        self.quality = options.quality
        self.renderer = ViewRenderer(model)
        self.time = 0.5
        self.mode = COLOUR
        self.playing = False
        self.loop_seconds = options.loop_seconds
        self.frames: list[FrameStat] = []  # every frame sent, in order (the last 1000)
        self._frames_lock = threading.Lock()
        self._clients: dict[int, _ClientView] = {}
        self._clients_lock = threading.Lock()
        self._stopped = threading.Event()
        self._play_wake = threading.Event()

        self.server = viser.ViserServer(host=options.host, port=options.port, label=title, verbose=False)
        if options.port and self.server.get_port() != options.port:  # taken between the check and the start
            bound = self.server.get_port()
            self.server.stop()
            raise OSError(f"--port {options.port}: port {options.port} on {options.host} is in use (viser moved to {bound}): choose another with --port")
        self.server.gui.configure_theme(show_share_button=False)  # no public tunnel one click away
        self._build_scene()
        self._build_gui(title)
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)
        self._player = threading.Thread(target=self._play_loop, name="pidg-view-play", daemon=True)
        self._player.start()

    # ---- address -------------------------------------------------------------------------------------------------
    @property
    def port(self) -> int:
        return int(self.server.get_port())

    @property
    def url(self) -> str:
        host = self.server.get_host()
        host = "127.0.0.1" if host in ("0.0.0.0", "") else f"[{host}]" if ":" in host else host
        return f"http://{host}:{self.port}"

    # ---- scene: frustums and the starting camera ---------------------------------------------------------------------
    def _build_scene(self) -> None:
        centre, radius = scene_centre_and_radius(self.model, self.time)
        self._centre = centre
        scene = self.server.scene
        initial = self.server.initial_camera
        self._frustums = []
        if self.views:
            focus = cameras_focus([v.camera for v in self.views])
            centre = centre if focus is None else focus  # where the capture looked (D-NeRF: the origin)
            self._centre = centre
            ups = []
            distance = float(np.median([np.linalg.norm(pose_of_camera(v.camera)[1] - centre) for v in self.views]))
            for i, view in enumerate(self.views):
                wxyz, position = pose_of_camera(view.camera)
                ups.append(-np.asarray(view.camera.world_to_camera[1, :3].tolist()))  # camera -y (image up) in the world
                colour = (int(255 * view.time), 60, int(255 * (1.0 - view.time)))  # blue at t = 0 to red at t = 1
                frustum = scene.add_camera_frustum(
                    f"/training_cameras/{i:04d}", fov=view.camera.fov_y, aspect=view.camera.width / view.camera.height,
                    scale=FRUSTUM_SIZE * distance, thickness=2.0, thickness_units="screen", color=colour, wxyz=wxyz, position=position,
                )
                frustum.on_click(lambda event, view=view: self._look_through(event.client, view))
                self._frustums.append(frustum)
            up = np.mean(ups, axis=0)
            up = up / max(np.linalg.norm(up), 1e-9)
            first = self.views[0]
            _, eye = pose_of_camera(first.camera)
            eye = centre + START_BEHIND * (eye - centre)  # behind the first training camera: its frustum in view
            initial.fov = first.camera.fov_y
        else:
            up = np.array(DEFAULT_UP)
            eye = centre + radius * np.array(DEFAULT_EYE_OFFSET)
        scene.set_up_direction(tuple(float(v) for v in up))
        initial.position = tuple(float(v) for v in eye)
        initial.look_at = tuple(float(v) for v in centre)
        initial.up = tuple(float(v) for v in up)

    def _look_through(self, client: Any, view: TrainingView) -> None:
        """Put a browser's camera where a training camera was and the time at that frame's time."""
        wxyz, position = pose_of_camera(view.camera)
        forward = np.asarray(view.camera.viewing_direction.tolist())
        distance = float(np.dot(self._centre - position, forward))
        with client.atomic():
            client.camera.fov = view.camera.fov_y
            client.camera.position = tuple(float(v) for v in position)
            client.camera.look_at = tuple(float(v) for v in position + forward * max(distance, 1e-3))
        self.set_time(view.time)

    # ---- panel -------------------------------------------------------------------------------------------------------
    def _build_gui(self, title: str) -> None:
        gui = self.server.gui
        model = self.model
        split = "" if model.dynamic_mask is None else f", {int(model.dynamic_mask.sum())} dynamic"
        gui.add_markdown(f"**{title}**  \n{model.num_gaussians} Gaussians{split}; {len(self.views)} training cameras")
        self._time_slider = gui.add_slider("time t", 0.0, 1.0, 0.001, round(self.time, 3),
                                           hint="dataset time: 0 is the first frame of the video, 1 the last")
        self._time_slider.on_update(lambda _event: self._on_time(self._time_slider.value))
        self._play_button = gui.add_button("Play", hint="play the time from where it is, looping over [0, 1]")
        self._play_button.on_click(lambda _event: self.set_playing(not self.playing))
        self._loop_seconds = gui.add_number("seconds per loop", self.loop_seconds, min=0.5, max=600.0, step=0.5,
                                            hint="playback speed: seconds for the time to run from 0 to 1")
        self._loop_seconds.on_update(lambda _event: setattr(self, "loop_seconds", float(self._loop_seconds.value)))
        self._mode = gui.add_dropdown("show", self.renderer.modes, initial_value=self.mode,
                                      hint="velocity in pixels per training frame; stress on a fixed colour scale")
        self._mode.on_update(lambda _event: self._on_mode(self._mode.value))
        if self.views:
            frustums = gui.add_checkbox("training cameras", True, hint="frustums coloured blue (t = 0) to red (t = 1); click one to look through it")
            frustums.on_update(lambda _event: self._show_frustums(frustums.value))
        self._preview = gui.add_slider("preview scale", 0.05, 1.0, 0.05, self.quality.preview_scale,
                                       hint="resolution while the camera moves, as a fraction of the full size")
        self._preview.on_update(lambda _event: self._on_preview(self._preview.value))
        self._stats = gui.add_markdown("waiting for a browser...")

    def _show_frustums(self, visible: bool) -> None:
        for handle in self._frustums:
            handle.visible = visible

    def _on_time(self, t: float) -> None:
        self.time = check_time(min(max(float(t), 0.0), 1.0), "time")
        self._touch_all()

    def _on_mode(self, mode: str) -> None:
        self.mode = mode
        self._touch_all()

    def _on_preview(self, scale: float) -> None:
        self.quality = dataclasses.replace(self.quality, preview_scale=float(scale))
        self._touch_all()

    def set_time(self, t: float) -> None:
        """Move the time slider (every browser follows)."""
        t = check_time(t, "time")
        if round(t, 3) == self._time_slider.value:
            self._on_time(t)
        else:
            self._time_slider.value = round(t, 3)  # calls _on_time

    def set_playing(self, playing: bool) -> None:
        self.playing = bool(playing)
        self._play_button.label = "Pause" if self.playing else "Play"
        self._play_wake.set()
        self._touch_all()

    def _play_loop(self) -> None:
        last = time.monotonic()
        while not self._stopped.is_set():
            if not self.playing:
                self._play_wake.wait(0.5)
                self._play_wake.clear()
                last = time.monotonic()
                continue
            time.sleep(1.0 / 30.0)  # the renders pick up the newest time; no point stepping faster
            now = time.monotonic()
            t = self.time + (now - last) / max(self.loop_seconds, 1e-3)
            last = now
            self.set_time(t - math.floor(t) if t > 1.0 else t)

    # ---- clients -----------------------------------------------------------------------------------------------------
    def _connect(self, client: Any) -> None:
        with self._clients_lock:
            self._clients[client.client_id] = view = _ClientView(self, client)
        view.touch()

    def _disconnect(self, client: Any) -> None:
        with self._clients_lock:
            view = self._clients.pop(client.client_id, None)
        if view is not None:
            view.close()

    def _touch_all(self) -> None:
        with self._clients_lock:
            views = list(self._clients.values())
        for view in views:
            view.touch()

    def _record(self, stat: FrameStat, caption: str) -> None:
        with self._frames_lock:
            self.frames.append(stat)
            del self.frames[:-1000]
        quality = "full" if stat.full else "preview"
        text = f"last frame: {stat.width}x{stat.height} ({quality}), render {stat.render_ms:.0f} ms, sent after {stat.total_ms:.0f} ms"
        self._stats.content = text + (f"  \n{caption}" if caption else "")

    def wait_for_frames(self, count: int = 1, timeout: float = 30.0, full: bool | None = None) -> list[FrameStat]:
        """Block until ``count`` frames (of that quality, when ``full`` is given) were sent; the frames so far."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self._frames_lock:
                frames = [f for f in self.frames if full is None or f.full == full]
            if len(frames) >= count:
                return frames
            time.sleep(0.02)
        raise TimeoutError(f"pidg view: fewer than {count} frames sent in {timeout:g} s")

    def stop(self) -> None:
        self._stopped.set()
        self._play_wake.set()
        with self._clients_lock:
            views = list(self._clients.values())
            self._clients.clear()
        for view in views:
            view.close()
        self.server.stop()


def start_viewer(run_dir: Path | str, options: ViewerOptions | None = None) -> Viewer:
    """Load a run and start its viewer in the background (``stop()`` ends it); errors are one line each."""
    options = options or ViewerOptions()
    import_viser()  # before loading anything: say what to install first
    check_port(options.host, options.port)
    run_dir = check_run_folder(run_dir)
    model = open_run_model(run_dir, options.device)
    views = training_views(run_dir) if options.cameras else []
    return Viewer(model, views, options, title=f"pidg view {run_dir.resolve().name}")


def serve_run(run_dir: Path | str, options: ViewerOptions | None = None) -> None:
    """``pidg view``: start the viewer and serve until Ctrl-C."""
    viewer = start_viewer(run_dir, options)
    print(f"pidg view: open {viewer.url} in a browser (Ctrl-C stops)", flush=True)
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        print("pidg view: stopped", flush=True)
    finally:
        viewer.stop()


def measure_run(run_dir: Path | str, size: tuple[int, int] = (800, 800), device: Device = "auto", repeats: int = 5,
                quality: Quality | None = None) -> dict[str, Any]:
    """``pidg view RUN --measure``: the viewer's frame times for this run at ``size`` (width, height), seen from its
    first training camera (or the viewer's starting camera without one), without starting a server."""
    run_dir = check_run_folder(run_dir)
    model = open_run_model(run_dir, device)
    views = training_views(run_dir)
    width, height = size
    if views:
        camera = views[0].camera.resized(width, height)
    else:
        centre, radius = scene_centre_and_radius(model, 0.5)
        eye = centre + radius * np.array(DEFAULT_EYE_OFFSET)
        camera = Camera.look_at(tuple(eye), tuple(centre), DEFAULT_UP, width, height, math.radians(50.0))
    with torch.no_grad():
        return measure_frame_times(ViewRenderer(model), camera, quality, repeats)
