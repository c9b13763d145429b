"""`pidg view` as a person uses it: the server starts on a free port, a client connects over viser's websocket
protocol with its camera, and rendered frames arrive (a quick preview, then full size); a headless Chromium shows
the scene; bad input (not a run, a port in use, viser missing) is one line."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import asyncio
import base64
import dataclasses
import io
import json
import math
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request

import numpy as np
import pytest
from PIL import Image

from pidg.cli import main
from pidg.render import Camera
from pidg.viewer import Quality, ViewerOptions, camera_from_pose, pose_of_camera, start_viewer
from pidg.viewer.frames import STRESS
from pidg.viewer.server import training_views


def _needs_viser():
    return pytest.importorskip("viser", reason="pidg view needs viser: pip install 'pidg[view]'")


# ---- a minimal viser client: what the browser page does on the wire -------------------------------------------------
def _decode(raw: bytes) -> list[tuple[dict, list[bytes]]]:
    """viser's server -> client frame: [u64 msgpack size][u64 zstd size][zstd msgpack][pad][binary buffers]."""
    import msgspec
    import zstandard

    size, packed = int.from_bytes(raw[:8], "little"), int.from_bytes(raw[8:16], "little")
    payload = msgspec.msgpack.decode(zstandard.ZstdDecompressor().decompress(raw[16 : 16 + packed], max_output_size=size))
    offset = 16 + packed
    buffers = []
    for length in payload["binaryBufferLengths"]:
        offset += (-offset) % 8
        buffers.append(raw[offset : offset + length])
        offset += length
    return [(message, buffers) for message in payload["messages"]]


class Client:
    """Connects like the page does, reports a camera, and collects the background pictures the server sends."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.images: list[np.ndarray] = []

    async def __aenter__(self):
        import viser
        import websockets

        self.ws = await websockets.connect(f"ws://127.0.0.1:{self.port}", subprotocols=[f"viser-v{viser.__version__}"], max_size=None)
        return self

    async def __aexit__(self, *exc):
        await self.ws.close()

    async def send_camera(self, camera, canvas: tuple[int, int]) -> None:
        import msgspec

        wxyz, position = pose_of_camera(camera)
        message = {
            "type": "ViewerCameraMessage", "wxyz": tuple(wxyz.tolist()), "position": tuple(position.tolist()),
            "fov": camera.fov_y, "near": 0.01, "far": 100.0, "image_width": canvas[0], "image_height": canvas[1],
            "look_at": (0.0, 0.0, 0.0), "up_direction": (0.0, 0.0, 1.0),
        }
        await self.ws.send(msgspec.msgpack.encode(message))

    async def next_image(self, timeout: float = 20.0) -> np.ndarray:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            raw = await asyncio.wait_for(self.ws.recv(), deadline - time.monotonic())
            for message, buffers in _decode(raw):
                data = message.get("rgb_data") if message["type"] == "BackgroundImageMessage" else None
                if data is None:
                    continue
                data = buffers[data["__binary_index"]] if isinstance(data, dict) else data
                self.images.append(np.asarray(Image.open(io.BytesIO(bytes(data))).convert("RGB")))
                return self.images[-1]
        raise TimeoutError("no frame arrived")


@pytest.fixture
def viewer(viewer_run):
    _needs_viser()
    v = start_viewer(viewer_run, ViewerOptions(port=0, device="cpu", quality=Quality(preview_scale=0.25, rest_seconds=0.15)))
    yield v
    v.stop()


def test_a_client_gets_a_preview_then_the_full_frame_and_follows_the_time(viewer, viewer_run):
    camera = training_views(viewer_run)[1].camera
    canvas = (128, 96)

    rest = viewer.quality.rest_seconds
    # nothing counts as resting until the first frame is in: a slow start (a loaded machine) would otherwise let the
    # view rest before its first render, which then comes at full size
    viewer.quality = dataclasses.replace(viewer.quality, rest_seconds=60.0)

    async def session():
        async with Client(viewer.port) as client:
            await client.send_camera(camera, canvas)
            first = await client.next_image()
            viewer.quality = dataclasses.replace(viewer.quality, rest_seconds=rest)
            viewer.set_time(0.5)  # the same time again: wakes the view, which now rests after `rest` seconds
            while client.images[-1].shape[:2] != (96, 128):  # previews until the camera has rested
                await client.next_image()
            full = client.images[-1]
            viewer.set_time(0.9)  # the slider moves: a new frame of that time arrives
            await client.next_image()
            viewer._mode.value = STRESS  # the dropdown changes the picture
            await client.next_image()
            return first, full

    first, full = asyncio.run(asyncio.wait_for(session(), 60))
    assert first.shape[:2] == (24, 32)  # a quarter of the canvas while things change
    wxyz, position = pose_of_camera(camera)
    expected = viewer.renderer.render(camera_from_pose(wxyz, position, camera.fov_y, *canvas), 0.5).image
    assert full.std() > 5 and np.abs(full.astype(float) - expected).mean() < 4.0  # the scene, up to JPEG loss
    stats = viewer.frames
    assert stats[0].full is False and any(s.full and (s.width, s.height) == canvas for s in stats)
    assert any(s.t == 0.9 for s in stats) and stats[-1].mode == STRESS
    assert all(s.total_ms >= s.render_ms > 0 for s in stats)


def test_playing_advances_the_time_in_preview_quality(viewer, viewer_run):
    camera = training_views(viewer_run)[0].camera

    async def session():
        async with Client(viewer.port) as client:
            await client.send_camera(camera, (64, 48))
            await client.next_image()
            viewer.loop_seconds = 2.0
            viewer.set_playing(True)
            for _ in range(3):
                await client.next_image()
            viewer.set_playing(False)
            while client.images[-1].shape[:2] != (48, 64):  # at rest again: full size
                await client.next_image()

    asyncio.run(asyncio.wait_for(session(), 60))
    played = [s for s in viewer.frames if s.t != 0.5]
    assert len({s.t for s in played}) >= 3 and not any(s.full for s in played[:3])
    assert viewer.frames[-1].full and viewer.frames[-1].t == played[-1].t


def _listening_socket() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    s.bind(("127.0.0.1", 0))
    s.listen(1)
    return s


def test_a_port_in_use_is_named(viewer_run, capsys):
    _needs_viser()
    with _listening_socket() as busy:
        port = busy.getsockname()[1]
        with pytest.raises(OSError, match=rf"--port {port}: port {port} on 127.0.0.1 is in use"):
            start_viewer(viewer_run, ViewerOptions(port=port, device="cpu"))
        assert main(["view", str(viewer_run), "--port", str(port), "--device", "cpu"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "is in use" in err and "--port 0" in err


def test_bad_input_is_one_line(tmp_path, viewer_run, capsys, monkeypatch):
    _needs_viser()
    assert main(["view", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "not a pidg run folder (no checkpoint.pt" in err
    assert main(["view", str(viewer_run), "--port", "70000"]) == 2
    assert "--port 70000: must be in 0..65535" in capsys.readouterr().err


def test_without_viser_pidg_view_says_what_to_install(viewer_run, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "viser", None)  # import viser now fails, as when it is not installed
    assert main(["view", str(viewer_run)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "pip install 'pidg[view]'" in err


# ---- the page in a real browser ---------------------------------------------------------------------------------------
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


async def _screenshot(debug_port: int, url: str, width: int, height: int, ready) -> bytes:
    """Open ``url`` in the running Chromium over the DevTools protocol; screenshot once ``ready()`` is true."""
    import websockets

    for _ in range(100):
        try:
            targets = json.load(urllib.request.urlopen(f"http://127.0.0.1:{debug_port}/json"))
            page = next(t for t in targets if t["type"] == "page")
            break
        except (OSError, StopIteration):
            await asyncio.sleep(0.1)
    async with websockets.connect(page["webSocketDebuggerUrl"], max_size=None) as ws:
        ids = iter(range(1, 1000))

        async def call(method, **params):
            i = next(ids)
            await ws.send(json.dumps({"id": i, "method": method, "params": params}))
            while True:
                reply = json.loads(await ws.recv())
                if reply.get("id") == i:
                    return reply.get("result", {})

        await call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1, mobile=False)
        await call("Page.navigate", url=url)
        deadline = time.monotonic() + 40
        while not ready() and time.monotonic() < deadline:
            await asyncio.sleep(0.1)
        await asyncio.sleep(1.0)  # the page draws the last frame it received
        return base64.b64decode((await call("Page.captureScreenshot", format="png"))["data"])


def test_headless_chromium_shows_the_rendered_scene(viewer, tmp_path):
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        pytest.skip("headless Chromium is not installed (apt-get install chromium)")
    width, height = 1024, 640
    # the page starts at a camera we choose; what it shows must be pidg's render of that camera built independently
    # (Camera.look_at, horizontal field of view from viser's vertical one), so the browser's pose is read right
    eye, target, up, fov_y = (0.4, -3.2, 1.6), (0.1, 0.2, 0.0), (0.0, 0.0, 1.0), 0.8
    initial = viewer.server.initial_camera
    initial.position, initial.look_at, initial.up, initial.fov = eye, target, up, fov_y
    fov_x = 2.0 * math.atan(width / height * math.tan(fov_y / 2))
    expected = viewer.renderer.render(Camera.look_at(eye, target, up, width, height, fov_x), viewer.time).image
    debug_port = _free_port()
    browser = subprocess.Popen(
        [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--use-gl=swiftshader", "--enable-unsafe-swiftshader",
         f"--remote-debugging-port={debug_port}", "--remote-allow-origins=*", f"--user-data-dir={tempfile.mkdtemp(dir=tmp_path)}",
         f"--window-size={width},{height}", "about:blank"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    try:
        ready = lambda: any(s.full and s.width == width for s in viewer.frames)  # noqa: E731
        png = asyncio.run(_screenshot(debug_port, viewer.url, width, height, ready))
    finally:
        browser.terminate()
        browser.wait(10)
    shot = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(float)
    assert shot.shape == (height, width, 3)
    # compare the middle of the page left of the control panel (~330 px wide, top right); frustum lines are thin
    box = (slice(height // 4, 3 * height // 4), slice(width // 8, width - 360))
    close = (np.abs(shot[box] - expected[box]).max(axis=-1) < 40).mean()
    assert expected[box].std() > 5 and close > 0.95, f"only {close:.0%} of the page's middle matches the render"
