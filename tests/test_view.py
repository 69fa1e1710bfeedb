"""stdr-view and stdr-render: camera conversions, views, the viser server on a free
port (page served, renders equal to render(), clean shutdown, clear errors), a real browser when
Chromium is installed, and videos with the expected frame count and size."""
import socket
import time
import urllib.request

import numpy as np
import pytest
import torch
from stdr.view.browser import find_chromium
from stdr.data.colmap import qvec_to_rotmat as _quat_to_matrix
from stdr.view.core import (_matrix_to_quat, available_views, camera_from_viser, camera_to_viser,
                            open_run, render_view, to_uint8)

SCHED = ["optim.iterations=60", "baseline.warmup=20", "densify.refine_start=10", "densify.refine_every=10",
         "train.checkpoint_every=0", "train.eval_at_warmup_end=false", "eval.fps_repeats=1"]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A tiny STDR run (past its freeze: every view exists) and a tiny plain run."""
    from stdr.train.run import run_training as run
    from stdr.testing import tiny_config
    root = tmp_path_factory.mktemp("view")
    run(tiny_config(root, SCHED + ["stdr=on", "stdr.warmup_end=25", "stdr.freeze_at=40"]), root / "stdr")
    run(tiny_config(root, SCHED), root / "plain")
    return root


def test_quaternions_round_trip():
    g = torch.Generator().manual_seed(0)
    for _ in range(50):
        q = torch.randn(4, generator=g).double().numpy()
        q /= np.linalg.norm(q)
        R = _quat_to_matrix(q)
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1.0)
        assert np.allclose(_quat_to_matrix(_matrix_to_quat(R)), R, atol=1e-12)
    for R in (np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])):  # trace -1
        assert np.allclose(_quat_to_matrix(_matrix_to_quat(R)), R, atol=1e-12)


@pytest.mark.slow
def test_dataset_cameras_survive_the_viser_convention(runs):
    r = open_run(runs / "stdr", device="cpu")
    for f in r.frames["train"][:10] + r.frames["test"]:
        c = f.camera
        wxyz, pos, fov = camera_to_viser(c)
        back = camera_from_viser(wxyz, pos, fov, c.width, c.height)
        assert torch.allclose(back.R, c.R, atol=1e-6) and torch.allclose(back.t, c.t, atol=1e-5)
        assert (back.fx, back.fy, back.cx, back.cy) == pytest.approx((c.fx, c.fy, c.cx, c.cy), rel=1e-9)
        assert np.allclose(pos, c.center.double().numpy(), atol=1e-6)


@pytest.mark.slow
def test_views(runs):
    r = open_run(runs / "stdr", device="cpu")
    assert available_views(r) == ["rgb", "depth", "alpha", "mask", "dynamic"]
    f = r.frames["test"][0]
    rgb = render_view(r.model, f.camera, f.time, "rgb")
    assert np.array_equal(rgb, to_uint8(r.model.render(f.camera, f.time).image))  # the stdr-eval render
    assert rgb.shape == (f.camera.height, f.camera.width, 3) and rgb.dtype == np.uint8
    a = render_view(r.model, f.camera, f.time, "alpha")
    assert np.array_equal(a[..., 0], to_uint8(r.model.render(f.camera, f.time).alpha[..., None])[..., 0])
    for v in ("depth", "mask", "dynamic"):
        img = render_view(r.model, f.camera, f.time, v)
        assert img.shape == rgb.shape and img.std() > 0, v
    assert not np.array_equal(render_view(r.model, f.camera, 0.0, "rgb"), render_view(r.model, f.camera, 1.0, "rgb"))
    plain = open_run(runs / "plain", device="cpu")
    assert available_views(plain) == ["rgb", "depth", "alpha"]
    with pytest.raises(ValueError, match="stdr.enabled"):
        render_view(plain.model, f.camera, f.time, "mask")
    with pytest.raises(ValueError, match="not one of"):
        render_view(plain.model, f.camera, f.time, "normals")


class _Cam:  # what the viewer reads of a viser client's camera
    def __init__(self, wxyz, position, fov, w, h):
        self.wxyz, self.position, self.fov, self.image_width, self.image_height = wxyz, position, fov, w, h


class _Client:
    def __init__(self, cam):
        self.camera = cam


@pytest.mark.slow
def test_viewer_serves_renders_and_stops(runs):
    from stdr.view.server import Viewer, check_port, free_port
    r = open_run(runs / "stdr", device="cpu")
    port = free_port()
    v = Viewer(r, port=port)
    try:
        page = urllib.request.urlopen(f"{v.url}/", timeout=30).read().decode()
        assert page.lower().startswith("<!doctype html>")
        with pytest.raises(RuntimeError, match=f"port {port} on 127.0.0.1 is taken"):
            check_port("127.0.0.1", port)
        # a browser's camera: the first test camera in viser's terms, on a 2:1 canvas
        f = r.frames["test"][0]
        wxyz, pos, fov = camera_to_viser(f.camera)
        client = _Client(_Cam(wxyz, pos, fov, 640, 320))
        img = v.render_client(client)
        cam = v.camera_for(wxyz, pos, fov, 640, 320)
        assert img.shape == (cam.height, cam.width, 3) and cam.width == int(v.gui_width.value)
        assert cam.width == 2 * cam.height
        assert np.array_equal(img, to_uint8(r.model.render(cam, float(v.gui_time.value)).image))
        # the start: the first test camera at its own time, so the image equals stdr-eval's render
        assert v.gui_time.value == pytest.approx(f.time, abs=1e-3)
        same = v.render_client(_Client(_Cam(wxyz, pos, fov, f.camera.width, f.camera.height)))
        diff = np.abs(same.astype(int) - to_uint8(r.model.render(f.camera, f.time).image).astype(int))
        assert diff.max() <= 2 and diff.mean() < 0.05  # float32 round trip of the pose
        v.gui_view.value = "mask"
        assert not np.array_equal(v.render_client(client), img)
        assert v.frame_ms and "frame time" in v._info()
    finally:
        v.stop()
    time.sleep(0.5)
    check_port("127.0.0.1", port)  # free again after stop


def test_bad_run_directories_are_named(tmp_path, capsys):
    from stdr.cli.view import render_main, view_main
    from stdr.view.server import free_port
    with pytest.raises(SystemExit) as e:  # bad input: one line, exit code 2 (stdr.errors.reported)
        view_main([str(tmp_path / "nope"), "--port", str(free_port())])
    assert e.value.code == 2 and "stdr-view: error:" in (err := capsys.readouterr().err) and "no such folder" in err
    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit) as e:
        render_main([str(tmp_path / "empty")])
    assert e.value.code == 2 and "not a trained run: config.yaml, checkpoints/last.pt missing" in capsys.readouterr().err
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        with pytest.raises(SystemExit, match="is taken"):
            view_main([str(tmp_path / "empty"), "--port", str(s.getsockname()[1])])


@pytest.mark.slow
def test_stdr_render_writes_videos_of_the_expected_size(runs, tmp_path):
    import imageio.v3 as iio
    from stdr.cli.view import render_main
    render_main([str(runs / "stdr"), "--out", str(tmp_path / "v"), "--frames", "5", "--fps", "5",
                 "--format", "gif", "--view", "rgb"])
    r = open_run(runs / "stdr", device="cpu")
    cam = r.frames["test"][0].camera
    n_test = len(r.frames["test"])
    for kind, n, w in (("time", 5, cam.width), ("orbit", 5, cam.width), ("compare", n_test, 3 * cam.width)):
        frames = iio.imread(tmp_path / "v" / f"{kind}_rgb.gif", index=None)
        assert frames.shape[0] == n and frames.shape[1:3] == (cam.height, w), kind
    # the time sweep moves and the orbit turns: consecutive frames differ
    sweep = iio.imread(tmp_path / "v" / "time_rgb.gif", index=None)
    assert not np.array_equal(sweep[0], sweep[-1])
    with pytest.raises(SystemExit, match="--kinds spin"):
        render_main([str(runs / "stdr"), "--kinds", "spin", "--out", str(tmp_path / "w")])


@pytest.mark.slow
@pytest.mark.skipif(find_chromium() is None, reason="no Chromium: `apt-get install -y chromium` runs this test")
def test_a_real_browser_shows_a_render(runs, tmp_path):
    import subprocess
    import sys

    from PIL import Image
    from stdr.view.server import free_port
    # stdr-view --screenshot as a user runs it (its own process: the exit status counts; it was 134,
    # an abort at shutdown, after the PNG was saved): headless Chromium opens the page, connects,
    # sends its camera and gets a frame rendered for it (else the command fails on its timeout)
    p = subprocess.run([sys.executable, "-c", "from stdr.cli.view import view_main; view_main()", str(runs / "stdr"),
                        "--port", str(free_port()), "--view", "mask", "--screenshot", str(tmp_path / "shot.png")],
                       capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-2000:]
    assert "frame time" in p.stdout
    img = np.asarray(Image.open(tmp_path / "shot.png").convert("RGB")).astype(float)
    assert img.shape[0] > 100 and img.std() > 5  # not a blank page
    h, w = img.shape[:2]
    assert img[h // 3: 2 * h // 3, w // 4: w // 2].mean() < 250  # the render behind the panel, not white


@pytest.mark.parametrize("ignore_term", [False, True])
def test_the_browser_and_every_helper_it_forked_are_stopped(ignore_term):
    """stdr-view --screenshot stops Chromium's whole process group (its helpers outlive the main
    process and kept writing to the profile folder, so removing it failed): here a main process
    with two forked children; with SIGTERM ignored, SIGKILL follows."""
    import subprocess
    from stdr.view.browser import stop_process_group
    trap = 'trap "" TERM; ' if ignore_term else ""
    proc = subprocess.Popen(["bash", "-c", f"{trap}sleep 300 & sleep 300 & wait"], start_new_session=True)
    t0 = time.time()
    while len(_live_group_members(proc.pid)) < 3 and time.time() - t0 < 20:  # a loaded machine forks slowly
        time.sleep(0.05)
    assert len(_live_group_members(proc.pid)) == 3  # bash and its two children
    t0 = time.time()
    stop_process_group(proc, timeout=1.0)
    assert proc.returncode is not None and time.time() - t0 < 5.0
    assert _live_group_members(proc.pid) == []  # (zombies awaiting init's reaping do not count)


def _live_group_members(pgid: int) -> list[int]:
    """Processes of group pgid that are not zombies, from /proc/<pid>/stat."""
    import os
    live = []
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                stat = open(f"/proc/{d}/stat").read()
            except OSError:
                continue
            fields = stat[stat.rindex(")") + 2:].split()  # state, ppid, pgrp, ...
            if int(fields[2]) == pgid and fields[0] != "Z":
                live.append(int(d))
    return live


# ----------------------------------------------------------------------------- camera paths (nerfstudio's format)
def _path_file(tmp_path, entries, **top):
    import json
    d = {"camera_type": "perspective", "render_width": 80, "render_height": 60, "fps": 12.0, "seconds": 1.0,
         "camera_path": entries, **top}
    p = tmp_path / "camera_path.json"
    p.write_text(json.dumps(d))
    return p


def test_camera_path_axes_follow_nerfstudio():
    """A hand-made path entry: OpenGL camera-to-world (identity rotation: looking down -z with y
    up) at (0, 0, 5), vertical fov 90 deg at 80x60. By hand: f = 30 / tan(45 deg) = 30 px, the
    origin projects to the centre (40, 30) at depth 5; world +y (up) lands above the centre at
    v = 30 - 30 * 1 / 5 = 24, world +x right of it at u = 40 + 30 / 5 = 46."""
    import tempfile
    from pathlib import Path

    from stdr.view.camera_path import read_camera_path
    m = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 5, 0, 0, 0, 1]
    with tempfile.TemporaryDirectory() as d:
        cp = read_camera_path(_path_file(Path(d), [{"camera_to_world": m, "fov": 90.0, "aspect": 4 / 3,
                                                    "render_time": 0.25}]))
    c = cp.cameras[0]
    assert (c.width, c.height, c.fx, c.fy, c.cx, c.cy) == (80, 60, pytest.approx(30.0), pytest.approx(30.0), 40.0, 30.0)
    assert cp.times == [0.25] and cp.fps == 12.0

    def project(p):
        x = c.R.double().numpy() @ np.asarray(p, float) + c.t.double().numpy()
        return c.fx * x[0] / x[2] + c.cx, c.fy * x[1] / x[2] + c.cy, x[2]
    assert project([0, 0, 0]) == pytest.approx((40.0, 30.0, 5.0))
    assert project([0, 1, 0]) == pytest.approx((40.0, 24.0, 5.0))
    assert project([1, 0, 0]) == pytest.approx((46.0, 30.0, 5.0))


def test_camera_path_round_trip_and_defaults(tmp_path):
    """Cameras written by write_camera_path read back equal (pose, intrinsics, times, fps); a path
    without render_time on every entry runs evenly from 0 to 1 (nerfstudio ignores partial times)."""
    import json

    from stdr.view.camera_path import read_camera_path, write_camera_path
    from stdr.view.core import camera_from_viser
    g = np.random.default_rng(0)
    cams, times = [], [0.0, 0.3, 0.9]
    for _ in times:
        q = g.normal(size=4)
        cams.append(camera_from_viser(q / np.linalg.norm(q), g.normal(size=3), 0.8, 64, 48))
    p = write_camera_path(tmp_path / "p.json", cams, times, fps=24.0)
    back = read_camera_path(p)
    assert back.times == pytest.approx(times) and back.fps == 24.0
    for a, b in zip(cams, back.cameras):
        assert torch.allclose(a.R, b.R, atol=1e-6) and torch.allclose(a.t, b.t, atol=1e-5)
        assert (b.fx, b.fy, b.cx, b.cy, b.width, b.height) == pytest.approx((a.fx, a.fy, a.cx, a.cy, 64, 48))
    half = read_camera_path(p, width=32)
    assert (half.cameras[0].width, half.cameras[0].height) == (32, 24)
    d = json.loads(p.read_text())
    del d["camera_path"][1]["render_time"]
    p.write_text(json.dumps(d))
    assert read_camera_path(p).times == pytest.approx([0.0, 0.5, 1.0])


@pytest.mark.parametrize("change, message", [
    ({"camera_type": "fisheye"}, "camera_type 'fisheye'"),
    ({"camera_path": []}, "non-empty 'camera_path'"),
    ({"render_width": None}, "render_width: expected a number"),
    ({"entry": {"fov": 200.0}}, "fov 200.0 is not a vertical field of view"),
    ({"entry": {"camera_to_world": [2, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 5, 0, 0, 0, 1]}}, "not a rotation"),
    ({"entry": {"camera_to_world": [1, 0, 0]}}, "has 3 numbers"),
    ({"entry": {"render_time": 1.5}}, "render_time 1.5 outside"),
])
def test_bad_camera_paths_are_named(tmp_path, change, message):
    from stdr.view.camera_path import read_camera_path
    e = {"camera_to_world": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 5, 0, 0, 0, 1], "fov": 50.0, "render_time": 0.0}
    e.update(change.pop("entry", {}))
    p = _path_file(tmp_path, [e], **change)
    with pytest.raises(ValueError, match=message) as err:
        read_camera_path(p)
    assert str(p) in str(err.value)


def test_keyframes_interpolate_through_their_poses_and_times():
    from stdr.view.camera_path import interpolate
    from stdr.view.core import camera_from_viser
    a = camera_from_viser([1, 0, 0, 0], [0, 0, 0], 0.8, 40, 30)
    b = camera_from_viser([np.cos(0.5), 0, np.sin(0.5), 0], [2, 0, 0], 0.8, 40, 30)  # turned 1 rad about y
    cams, times = interpolate([(a, 0.0), (b, 1.0)], 5)
    assert times == pytest.approx([0, 0.25, 0.5, 0.75, 1])
    assert torch.allclose(cams[0].R, a.R, atol=1e-6) and torch.allclose(cams[-1].R, b.R, atol=1e-6)
    mid = cams[2]
    assert np.allclose(mid.center.numpy(), [1, 0, 0], atol=1e-6)
    # half-way orientation: turned 0.5 rad about y
    ang = np.degrees(np.arccos((np.trace(a.R.double().numpy().T @ mid.R.double().numpy()) - 1) / 2))
    assert ang == pytest.approx(np.degrees(0.5), abs=1e-3)


@pytest.mark.slow
def test_stdr_render_follows_a_camera_path_as_mp4(runs, tmp_path):
    """stdr-render --path: one MP4 frame per path entry, each the render of that camera at its
    time (the viewer's save button writes such a file: Viewer.save_path)."""
    import imageio.v3 as iio
    from stdr.cli.view import render_main
    from stdr.view.camera_path import read_camera_path
    from stdr.view.server import Viewer, free_port
    r = open_run(runs / "stdr", device="cpu")
    v = Viewer(r, port=free_port())
    try:
        for f, t in ((r.frames["test"][0], 0.1), (r.frames["train"][3], 0.9)):
            wxyz, pos, fov = camera_to_viser(f.camera)
            v.gui_time.value = t
            v.add_keyframe(_Client(_Cam(wxyz, pos, fov, 64, 48)))
        v.gui_path_seconds.value, v.gui_path_fps.value, v.gui_path_name.value = 1.0, 6.0, "sweep"
        path = v.save_path()
    finally:
        v.stop()
    assert path == runs / "stdr" / "camera_paths" / "sweep.json"
    cp = read_camera_path(path)
    assert len(cp.cameras) == 6 and cp.times[0] == pytest.approx(0.1) and cp.times[-1] == pytest.approx(0.9)
    render_main([str(runs / "stdr"), "--path", str(path), "--out", str(tmp_path / "v")])
    video = iio.imread(tmp_path / "v" / "sweep_rgb.mp4", index=None)
    assert video.shape[:3] == (6, 48, 64)
    for k in (0, 5):
        want = to_uint8(r.model.render(cp.cameras[k], cp.times[k]).image).astype(float)
        assert np.abs(video[k].astype(float) - want).mean() < 6  # H.264 at quality 8
    assert np.abs(video[0].astype(float) - video[5].astype(float)).mean() > 6  # the path moves


def test_the_viewer_refuses_a_websocket_from_another_page(runs):
    """Any page open in the user's browser could connect to a running stdr-view; only the viewer's
    own page (and a non-browser client, which sends no Origin) gets through the handshake."""
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    from stdr.view.server import Viewer, free_port
    r = open_run(runs / "plain", device="cpu")
    port = free_port()
    v = Viewer(r, port=port, allow_origins=("https://viewer.lab.example",))
    try:
        uri = f"ws://127.0.0.1:{port}"
        for origin in ("http://evil.example", f"http://evil.example:{port}", "null"):
            with pytest.raises(InvalidStatus) as e:
                connect(uri, origin=origin, open_timeout=20).close()
            assert e.value.response.status_code == 403, origin
        for origin in (f"http://127.0.0.1:{port}", f"http://localhost:{port}", "https://viewer.lab.example", None):
            connect(uri, origin=origin, open_timeout=20).close()
    finally:
        v.stop()
