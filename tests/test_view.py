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
    from stdr.cli.train import run
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


def test_bad_run_directories_are_named(tmp_path):
    from stdr.cli.view import render_main, view_main
    from stdr.view.server import free_port
    with pytest.raises(SystemExit, match="no such folder"):
        view_main([str(tmp_path / "nope"), "--port", str(free_port())])
    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit, match="not a trained run: config.yaml, checkpoints/last.pt missing"):
        render_main([str(tmp_path / "empty")])
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
def test_a_real_browser_shows_a_render(runs, tmp_path, capsys):
    from PIL import Image
    from stdr.cli.view import view_main
    from stdr.view.server import free_port
    # stdr-view --screenshot: headless Chromium opens the page, connects, sends its camera and
    # gets a frame rendered for it (else the command fails on its timeout), then a PNG is saved
    view_main([str(runs / "stdr"), "--port", str(free_port()), "--view", "mask", "--screenshot",
               str(tmp_path / "shot.png")])
    assert "frame time" in capsys.readouterr().out
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
    time.sleep(0.3)
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
