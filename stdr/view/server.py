"""stdr-view: a web viewer of a trained run on viser (https://viser.studio), on localhost.

The browser shows the scene; every camera move, time change or view change is rendered here with
`stdr.view.core.render_view` (the stdr-eval render path) and sent back as the background image.
Each connected browser has one render thread that always renders the newest request (older
ones are dropped), and one lock serializes access to the model.
"""
from __future__ import annotations

import errno
import socket
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Optional

import numpy as np

from .core import (ViewRun, available_views, camera_from_viser, camera_to_viser, look_at_point, render_view,
                   with_size)
from .camera_path import interpolate, write_camera_path

MAX_FRUSTA = 200


def check_port(host: str, port: int) -> None:
    """A clear error when `port` on `host` cannot be served (viser would silently move to the
    next free port, and the URL printed would be wrong)."""
    if not 0 < port < 65536:
        raise ValueError(f"--port {port}: must be in 1..65535")
    fam = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(fam, socket.SOCK_STREAM) as s:
        # as servers bind: connections of a closed server (TIME_WAIT) do not hold the port, a live
        # listener does (Linux refuses the bind then, SO_REUSEADDR or not)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError as e:
            if e.errno == errno.EADDRINUSE:
                raise RuntimeError(f"port {port} on {host} is taken (another stdr-view, or another program): "
                                   "pick a free one with --port") from None
            raise RuntimeError(f"cannot serve on {host}:{port}: {e.strerror} (check --host)") from None


LOOPBACK = ("127.0.0.1", "localhost", "::1")


def allowed_origins(host: str, port: int, extra: tuple[str, ...] = ()) -> list[Optional[str]]:
    """The WebSocket origins the viewer accepts: its own page, as a browser names it. On a
    loopback host, http://127.0.0.1, localhost and [::1] at `port`; on another (e.g. 0.0.0.0), also
    this machine's host name, its fully qualified name and its addresses. `extra`: origins to add
    (a reverse proxy's, e.g. https://viewer.lab.example). No Origin header at all (a script, not a
    browser) is accepted: the check is against web pages, which always send one."""
    names = {"127.0.0.1", "localhost", "[::1]"}
    if host not in LOOPBACK:
        names.add(f"[{host}]" if ":" in host else host)
        hn = socket.gethostname()
        names |= {hn, socket.getfqdn()}
        try:
            names |= {f"[{a[4][0]}]" if ":" in a[4][0] else a[4][0] for a in socket.getaddrinfo(hn, None)}
        except OSError:
            pass
        names.discard("0.0.0.0")
        names.discard("[::]")
    return [None, *sorted(f"{scheme}://{n}:{port}" for n in names for scheme in ("http", "https")), *extra]


@contextmanager
def _origins_checked(origins: list[Optional[str]]):
    """viser has no setting for it: while its server starts, its WebSocket server (websockets'
    `serve`) is given `origins`, so a handshake from any other page is refused with 403."""
    import websockets.asyncio.server as ws

    serve = ws.serve

    def checked(*args, **kwargs):
        kwargs["origins"] = origins
        return serve(*args, **kwargs)
    ws.serve = checked
    try:
        yield
    finally:
        ws.serve = serve


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


class _ClientRenderer:
    """One browser: a thread that renders its newest request."""

    def __init__(self, viewer: "Viewer", client):
        self.viewer, self.client = viewer, client
        self.wake = threading.Event()
        self.alive = True
        self.thread = threading.Thread(target=self._loop, name=f"stdr-view-{client.client_id}", daemon=True)
        self.thread.start()

    def request(self) -> None:
        self.wake.set()

    def _loop(self) -> None:
        while self.alive and not self.viewer.stopped.is_set():
            if not self.wake.wait(timeout=0.5):
                continue
            self.wake.clear()
            try:
                img = self.viewer.render_client(self.client)
            except Exception as e:  # noqa: BLE001 - shown in the page, the viewer goes on
                self.viewer.set_status(f"render failed: {type(e).__name__}: {e}")
                continue
            if img is not None and self.alive and not self.viewer.stopped.is_set():  # (not to a closed page)
                self.client.scene.set_background_image(img, format="jpeg", jpeg_quality=92)


class Viewer:
    """A viser server showing `run`: free camera starting at a test camera, time slider and
    play/pause, the views of `available_views`, dataset camera frusta and a dropdown to jump to
    any train/val/test camera."""

    def __init__(self, run: ViewRun, host: str = "127.0.0.1", port: int = 8080, max_width: Optional[int] = None,
                 verbose: bool = False, allow_origins: tuple[str, ...] = ()):
        import viser

        check_port(host, port)
        self.run = run
        self.lock = threading.Lock()
        self.stopped = threading.Event()
        self.frame_ms: list[float] = []
        self.renderers: dict[int, _ClientRenderer] = {}
        cam0, t0 = run.default_camera()
        self.base_width = cam0.width
        self.origins = allowed_origins(host, port, tuple(allow_origins))
        with _origins_checked(self.origins):  # only this viewer's own page may drive it
            self.server = viser.ViserServer(host=host, port=port, verbose=verbose)
        if self.server.get_port() != port:  # taken between the check and the start
            self.server.stop()
            raise RuntimeError(f"port {port} on {host} was taken while starting: pick another with --port")
        self.host, self.port = host, port
        gui = self.server.gui
        self.views = available_views(run)
        self.gui_view = gui.add_dropdown("view", tuple(self.views), initial_value="rgb")
        self.gui_time = gui.add_slider("time", min=0.0, max=1.0, step=0.001, initial_value=float(t0))
        self.gui_play = gui.add_checkbox("play", False)
        self.gui_period = gui.add_slider("seconds per sweep", min=1.0, max=30.0, step=0.5, initial_value=5.0)
        self.gui_width = gui.add_slider("image width", min=64, max=max(1600, 2 * cam0.width), step=8,
                                        initial_value=int(max_width or cam0.width))
        labels = [lb for lb, _ in run.cameras()]
        self.gui_camera = gui.add_dropdown("camera", tuple(labels) if labels else ("(no dataset cameras)",),
                                           initial_value=labels[0] if labels else "(no dataset cameras)")
        self.gui_frusta = gui.add_checkbox("training cameras", True)
        self.gui_info = gui.add_markdown(self._info())
        self.gui_status = gui.add_markdown(run.data_note or "")
        self._add_path_panel(gui)
        for h in (self.gui_view, self.gui_time, self.gui_width):
            h.on_update(lambda _: self.request_all())
        self.gui_camera.on_update(lambda _: self.jump_all())
        self.gui_frusta.on_update(lambda _: self._show_frusta(self.gui_frusta.value))
        self._add_frusta()
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)
        self.player = threading.Thread(target=self._play, name="stdr-view-play", daemon=True)
        self.player.start()

    # ------------------------------------------------------------------ state
    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    def _info(self) -> str:
        m = self.run.model
        ft = f"{np.median(self.frame_ms[-20:]):.0f} ms" if self.frame_ms else "–"
        return (f"**{self.run.cfg.name}** · {m.num_gaussians:,} Gaussians · backend {m.backend} on {m.device} · "
                f"image width {int(self.gui_width.value)} px · frame time {ft}")

    def set_status(self, text: str) -> None:
        self.gui_status.content = text

    def _add_frusta(self) -> None:
        self.frusta = []
        frames = self.run.frames.get("train", [])
        step = max(1, len(frames) // MAX_FRUSTA)
        for i, f in enumerate(frames[::step]):
            wxyz, pos, fov = camera_to_viser(f.camera)
            self.frusta.append(self.server.scene.add_camera_frustum(
                f"/cameras/train_{i * step}", fov=fov, aspect=f.camera.width / f.camera.height, scale=0.08,
                wxyz=wxyz, position=pos, color=(90, 90, 200)))

    def _show_frusta(self, on: bool) -> None:
        for h in self.frusta:
            h.visible = on

    # ------------------------------------------------------------------ camera path
    def _add_path_panel(self, gui) -> None:
        """Keyframes (the current camera and time) interpolated into a camera path saved as
        RUN/camera_paths/<name>.json (nerfstudio's format; `stdr-render RUN --path FILE`)."""
        self.keyframes: list = []
        with gui.add_folder("camera path", expand_by_default=False):
            add = gui.add_button("add keyframe (camera + time)")
            clear = gui.add_button("clear keyframes")
            self.gui_path_seconds = gui.add_number("seconds", initial_value=4.0, min=0.1, step=0.5)
            self.gui_path_fps = gui.add_number("fps", initial_value=30.0, min=1.0, step=1.0)
            self.gui_path_name = gui.add_text("name", initial_value="path")
            save = gui.add_button("save camera path")
        add.on_click(lambda ev: self.add_keyframe(ev.client))
        clear.on_click(lambda _: self.clear_keyframes())
        save.on_click(lambda _: self.save_path())

    def add_keyframe(self, client=None) -> None:
        clients = list(self.server.get_clients().values())
        client = client or (clients[0] if clients else None)
        if client is None or client.camera.image_width <= 0:
            self.set_status("no browser camera to record")
            return
        c = client.camera
        self.keyframes.append((self.camera_for(c.wxyz, c.position, c.fov, c.image_width, c.image_height),
                               float(self.gui_time.value)))
        self.set_status(f"{len(self.keyframes)} keyframe(s)")

    def clear_keyframes(self) -> None:
        self.keyframes = []
        self.set_status("keyframes cleared")

    def save_path(self) -> Optional[Path]:
        if len(self.keyframes) < 2:
            self.set_status("a camera path needs at least two keyframes")
            return None
        name = "".join(ch for ch in str(self.gui_path_name.value) if ch.isalnum() or ch in "-_") or "path"
        fps = float(self.gui_path_fps.value)
        frames = max(2, int(round(fps * float(self.gui_path_seconds.value))))
        W, H = self.keyframes[0][0].width, self.keyframes[0][0].height
        kf = [(with_size(c, W, H), t) for c, t in self.keyframes]
        cams, times = interpolate(kf, frames)
        path = write_camera_path(self.run.run_dir / "camera_paths" / f"{name}.json", cams, times, fps, keyframes=kf)
        self.set_status(f"saved {path} ({frames} frames); render it with `stdr-render {self.run.run_dir} --path {path}`")
        return path

    # ------------------------------------------------------------------ clients
    def _connect(self, client) -> None:
        self._jump(client)
        r = _ClientRenderer(self, client)
        self.renderers[client.client_id] = r
        client.camera.on_update(lambda _: r.request())
        r.request()

    def _disconnect(self, client) -> None:
        r = self.renderers.pop(client.client_id, None)
        if r is not None:
            r.alive = False
            r.wake.set()

    def _selected(self):
        for lb, f in self.run.cameras():
            if lb == self.gui_camera.value:
                return f
        return None

    def _jump(self, client) -> None:
        """Put the client's camera at the selected dataset camera (and its time)."""
        f = self._selected()
        cam = f.camera if f is not None else self.run.default_camera()[0]
        wxyz, pos, fov = camera_to_viser(cam)
        with client.atomic():
            client.camera.fov = fov
            client.camera.up_direction = -cam.R.detach().double().cpu().numpy()[1]
            client.camera.position = pos
            client.camera.look_at = look_at_point(self.run, cam)
        if f is not None:
            self.gui_time.value = float(f.time)

    def jump_all(self) -> None:
        for c in self.server.get_clients().values():
            self._jump(c)
        self.request_all()

    def request_all(self) -> None:
        self.gui_info.content = self._info()
        for r in list(self.renderers.values()):
            r.request()

    # ------------------------------------------------------------------ rendering
    def camera_for(self, wxyz, position, fov: float, canvas_w: int, canvas_h: int):
        """Our camera for a viser view, at the chosen image width and the canvas' aspect."""
        w = int(self.gui_width.value)
        h = max(1, int(round(w * canvas_h / max(canvas_w, 1))))
        return camera_from_viser(wxyz, position, fov, w, h)

    def render(self, camera, t: float, view: str) -> np.ndarray:
        """One frame (uint8 [H, W, 3]), timed; the model is used by one render at a time."""
        with self.lock:
            t0 = time.perf_counter()
            img = render_view(self.run.model, camera.to(self.run.model.device), float(t), view)
            self.frame_ms.append(1000.0 * (time.perf_counter() - t0))
        return img

    def render_client(self, client) -> Optional[np.ndarray]:
        c = client.camera
        if c.image_width <= 0 or c.image_height <= 0:
            return None
        cam = self.camera_for(c.wxyz, c.position, c.fov, c.image_width, c.image_height)
        img = self.render(cam, float(self.gui_time.value), str(self.gui_view.value))
        self.gui_info.content = self._info()
        return img

    def _play(self) -> None:
        last = time.perf_counter()
        while not self.stopped.wait(0.05):
            now = time.perf_counter()
            if self.gui_play.value:
                dt = (now - last) / float(self.gui_period.value)
                self.gui_time.value = float((self.gui_time.value + dt) % 1.0)
            last = now

    def stop(self, timeout: float = 30.0) -> None:
        """Stop the server and wait for the player and every render thread to end: a daemon thread
        still inside a render (torch, the JPEG encoder) while the interpreter shuts down aborted
        the process (exit 134 after `stdr-view --screenshot` had saved its PNG)."""
        self.stopped.set()
        renderers = list(self.renderers.values())
        for r in renderers:
            r.alive = False
            r.wake.set()
        deadline = time.perf_counter() + timeout
        for th in [self.player] + [r.thread for r in renderers]:  # a render in flight finishes first,
            if th is not threading.current_thread():              # then the server stops
                th.join(max(0.0, deadline - time.perf_counter()))
        self.server.stop()

