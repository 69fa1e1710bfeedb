"""stdr-data capture: frames from a video or a folder (stride, sharpest of each window, times),
camera poses by pycolmap, the Nerfies-format output the loader trains on; end to end on the
real phone capture in ../shared (images in, its own cameras as the reference)."""
import json
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from stdr.data import capture as cap
from stdr.data import capture_input as frames_mod
from stdr.data import pose_error

pycolmap = pytest.importorskip("pycolmap", reason="stdr-data capture needs the `capture` extra")
av = pytest.importorskip("av", reason="stdr-data capture needs the `capture` extra")


# ----------------------------------------------------------------------------- pieces
def _rotation(rng) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    from stdr.data.colmap import qvec_to_rotmat
    return qvec_to_rotmat(q)


def test_similarity_alignment_recovers_a_known_transform():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(20, 3))
    R, s, t = _rotation(rng), 3.7, np.array([1.0, -2.0, 0.5])
    s2, R2, t2 = pose_error.align_similarity(src, s * src @ R.T + t)
    assert s2 == pytest.approx(s) and np.allclose(R2, R, atol=1e-10) and np.allclose(t2, t, atol=1e-10)
    with pytest.raises(ValueError, match="N >= 3"):
        pose_error.align_similarity(src[:2], src[:2])


def _cam(R, c, f=300.0, pp=(100.0, 80.0), size=(200, 160)):
    return {"orientation": np.asarray(R).tolist(), "position": np.asarray(c).tolist(), "focal_length": f,
            "principal_point": list(pp), "image_size": list(size)}


def _turn_y(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def test_ray_errors_are_zero_up_to_a_similarity_and_see_a_turned_camera():
    rng = np.random.default_rng(1)
    n = 12
    R_ref = [_rotation(rng) for _ in range(n)]
    c_ref = rng.normal(size=(n, 3))
    # the same cameras in another world: x_est = A^T (x_ref - t) / s
    A, s, t = _rotation(rng), 0.25, np.array([3.0, 0.0, -1.0])
    est = [_cam(R @ A, (c - t) @ A / s) for R, c in zip(R_ref, c_ref)]
    ref = [_cam(R, c) for R, c in zip(R_ref, c_ref)]
    e = pose_error.ray_errors(est, ref)
    assert e["position_max"] < 1e-9 and e["ray_max_deg"] < 1e-5 and e["scale"] == pytest.approx(s)
    # one camera turned by 2 degrees about its own y axis: the ray through the centre turns by 2
    est[3]["orientation"] = (_turn_y(2.0) @ np.asarray(est[3]["orientation"])).tolist()
    e = pose_error.ray_errors(est, ref)
    assert e["ray_max_deg"] == pytest.approx(2.0, abs=1e-6) and e["ray_median_deg"] < 1e-5
    # one camera moved by 10 % of the trajectory's extent
    est = [_cam(R @ A, (c - t) @ A / s) for R, c in zip(R_ref, c_ref)]
    extent = np.linalg.norm(c_ref[:, None] - c_ref[None], axis=-1).max()
    moved = c_ref.copy()
    moved[5] += np.array([0.1 * extent, 0, 0])
    e = pose_error.ray_errors(est, [_cam(R, c) for R, c in zip(R_ref, moved)])
    assert 0.05 < e["position_max"] < 0.11  # (the alignment absorbs a little of it)


def test_ray_errors_see_through_a_principal_point_traded_for_a_rotation():
    """Two solutions of one camera: principal point at the centre, or 30 px to the right with the
    camera turned by atan(30 / f) about its y axis. They see the same centre ray, so the ray
    error is ~0 while their orientations differ by 5.7 degrees (what SfM runs that refine the
    principal point or not disagree on)."""
    rng = np.random.default_rng(3)
    f, d = 300.0, 30.0
    Rs = [_rotation(rng) for _ in range(6)]
    cs = rng.normal(size=(6, 3))
    centred = [_cam(R, c, f, (100.0, 80.0)) for R, c in zip(Rs, cs)]
    shifted = [_cam(_turn_y(-np.degrees(np.arctan(d / f))) @ R, c, f, (100.0 + d, 80.0)) for R, c in zip(Rs, cs)]
    e = pose_error.ray_errors(shifted, centred)
    assert e["ray_max_deg"] < 0.5  # quarter points differ a little (the two are not the same projection)
    assert np.degrees(np.arctan(d / f)) > 5.7


def _frames(n, h=48, w=64):
    """Textured frames; odd ones blurred (lower Laplacian variance)."""
    rng = np.random.default_rng(2)
    base = (rng.random((h, w, 3)) * 255).astype(np.uint8)
    out = []
    for i in range(n):
        img = np.roll(base, i, axis=1)
        if i % 2:
            img = cv2.GaussianBlur(img, (7, 7), 3)
        out.append(img)
    return out


def test_windows_keep_the_first_or_the_sharpest_frame():
    imgs = _frames(9)
    sharp = [i for i, _, _ in frames_mod._windows(enumerate(imgs), 3, "sharpest")]
    first = [i for i, _, _ in frames_mod._windows(enumerate(imgs), 3, "uniform")]
    assert first == [0, 3, 6]
    # windows {0,1,2} {3,4,5} {6,7,8}: blurred frames are the odd ones
    assert all(i % 2 == 0 for i in sharp) and len(sharp) == 3 and sharp[1] == 4
    assert frames_mod.sharpness(imgs[1]) < frames_mod.sharpness(imgs[0])


def _encode(frames, path: Path, fps: int) -> Path:
    with av.open(str(path), "w") as out:
        s = out.add_stream("libx264", rate=fps)
        s.width, s.height, s.pix_fmt = frames[0].shape[1], frames[0].shape[0], "yuv420p"
        s.options = {"crf": "12"}
        for f in frames:
            for p in s.encode(av.VideoFrame.from_ndarray(f, format="rgb24")):
                out.mux(p)
        for p in s.encode():
            out.mux(p)
    return path


def test_video_frames_keep_a_stride_and_their_presentation_times(tmp_path):
    video = _encode(_frames(30), tmp_path / "v.mp4", fps=10)
    out = tmp_path / "f"
    out.mkdir()
    recs = frames_mod.video_frames(video, out, cap.CaptureConfig(frames=10, select="uniform"))
    assert [r.source_index for r in recs] == list(range(0, 30, 3))
    assert [r.time_sec for r in recs] == pytest.approx([i / 10 for i in range(0, 30, 3)])
    assert sorted(p.name for p in out.iterdir()) == [f"{i:06d}.png" for i in range(0, 30, 3)]
    assert cv2.imread(str(out / "000003.png")).shape == (48, 64, 3)
    sharp = frames_mod.video_frames(video, tmp_path / "f", cap.CaptureConfig(frames=10, select="sharpest"))
    assert all(r.source_index % 2 == 0 for r in sharp)  # every window has a sharp (even) frame
    small = frames_mod.video_frames(video, tmp_path / "f", cap.CaptureConfig(frames=None, max_size=32))
    assert len(small) == 30 and cv2.imread(str(out / "000001.png")).shape == (24, 32, 3)


def test_bad_captures_are_named(tmp_path):
    with pytest.raises(cap.CaptureError, match="not found"):
        cap.capture(tmp_path / "nope.mp4", tmp_path / "o")
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(cap.CaptureError, match="not a video"):
        cap.capture(tmp_path / "notes.txt", tmp_path / "o")
    (tmp_path / "o").mkdir()
    (tmp_path / "clip.mp4").write_bytes(b"not a video")
    with pytest.raises(cap.CaptureError, match="exists already"):
        cap.capture(tmp_path / "clip.mp4", tmp_path / "o")
    with pytest.raises(cap.CaptureError, match="not a readable video"):
        cap.capture(tmp_path / "clip.mp4", tmp_path / "o2")
    assert not (tmp_path / "o2").exists()
    (tmp_path / "imgs").mkdir()
    with pytest.raises(cap.CaptureError, match="0 image"):
        cap.capture(tmp_path / "imgs", tmp_path / "o3")
    for i, h in enumerate((48, 48, 50)):  # one image of another size: named, with the first one's size
        cv2.imwrite(str(tmp_path / "imgs" / f"{i:03d}.png"), _frames(1, h=h)[0])
    with pytest.raises(cap.CaptureError, match=r"002.png: 64x50 pixels, but 000.png is 64x48"):
        cap.capture(tmp_path / "imgs", tmp_path / "o4")
    assert not (tmp_path / "o4").exists()
    for cfg, msg in ((dict(select="best"), "--select 'best'"), (dict(val_every=1), "--val-every 1"),
                     (dict(min_registered=0), "--min-registered 0"), (dict(vocab_tree="/no/tree.bin"), "--vocab-tree")):
        with pytest.raises(cap.CaptureError, match=msg):
            cap.CaptureConfig(**cfg).check()


def test_too_few_registered_frames_name_them_and_what_to_try():
    recs = [cap.FrameRecord(id=f"{i:06d}", source="", source_index=i, time_sec=i, sharpness=1.0) for i in range(10)]
    with pytest.raises(cap.CaptureError, match=r"registered 6 of 10 frames \(60% < --min-registered 70%\); "
                       r"not registered: 000006, 000007, 000008, 000009\. Try: --matcher exhaustive"):
        cap.check_registered(recs, {f"{i:06d}" for i in range(6)}, cap.CaptureConfig())
    cap.check_registered(recs, {f"{i:06d}" for i in range(7)}, cap.CaptureConfig())  # 70 %: enough


def test_capture_json_fills_the_loader_settings(tmp_path):
    from stdr.data.nerfies import capture_defaults
    assert capture_defaults(tmp_path) == {}
    (tmp_path / "capture.json").write_text(json.dumps({"loader": {"split_mode": "ids", "image_scale": 1}}))
    assert capture_defaults(tmp_path) == {"split_mode": "ids", "image_scale": 1}
    (tmp_path / "capture.json").write_text(json.dumps({"loader": {"split": "ids"}}))
    with pytest.raises(ValueError, match=r"capture.json: unknown loader setting\(s\) \['split'\]"):
        capture_defaults(tmp_path)


# ----------------------------------------------------------------------------- end to end on the phone capture
# Bounds. The reference is the capture's own COLMAP solution, not ground truth: made on its 4x
# images with the principal point refined (it sits 35 px right of the centre at 2x, f = 358 px)
# and strong tangential distortion (p2 = 0.03), where stdr's capture keeps the principal point
# centred. Camera centres: 2 % of the trajectory's extent (median) and 5 % (worst). Orientation,
# as the angle between the world rays through the same image points (ray_errors): 2 degrees
# (median) and 6 degrees (worst), about 12 and 36 px at this focal length. The centre bounds were
# stated before the first run; the orientation bounds were revised after it, when the
# orientations themselves (first bounds: 1 and 3 degrees) turned out to differ by the
# principal-point trade-off (5.4 degrees median) while the rays agree to 1.0 degree median,
# 4.0 worst (research/measurements/capture_toy). A wrong axis convention, a mirrored world or a
# mismatched frame order gives tens of percent or degrees.
POS_MEDIAN, POS_MAX, RAY_MEDIAN, RAY_MAX = 0.02, 0.05, 2.0, 6.0


def _cameras(folder: Path, ids):
    return [json.loads((folder / "camera" / f"{i}.json").read_text()) for i in ids]


@pytest.fixture(scope="module")
def toy_capture(shared_dir, tmp_path_factory):
    """The toy capture's 2x images through `stdr-data capture` (every image kept)."""
    toy = shared_dir / "data" / "nerfies" / "toy-capture"
    if not toy.is_dir():
        pytest.skip(f"{toy} not present")
    out = tmp_path_factory.mktemp("capture") / "toy"
    from stdr.cli.data import main
    t0 = time.perf_counter()
    main(["capture", str(toy / "rgb" / "2x"), "--out", str(out), "--frames", "0", "--threads", "2"])
    return toy, out, time.perf_counter() - t0


@pytest.mark.slow
def test_capture_finds_the_phone_captures_cameras(toy_capture):
    toy, out, seconds = toy_capture
    info = json.loads((out / "capture.json").read_text())
    ref_ids = json.loads((toy / "dataset.json").read_text())["ids"]
    ids = json.loads((out / "dataset.json").read_text())["ids"]
    common = [i for i in ref_ids if i in set(ids)]
    assert len(common) >= 0.9 * len(ref_ids), (len(common), len(ref_ids))
    e = pose_error.ray_errors(_cameras(out, common), _cameras(toy, common))
    print(f"capture of {len(ids)} frames in {seconds:.0f} s ({info['timings_s']}); pose errors {e}")
    assert e["position_median"] < POS_MEDIAN and e["position_max"] < POS_MAX, e
    assert e["ray_median_deg"] < RAY_MEDIAN and e["ray_max_deg"] < RAY_MAX, e
    # the layout: undistorted pinhole cameras, times by rank, every 8th frame held out
    d = json.loads((out / "dataset.json").read_text())
    assert d["val_ids"] == ids[4::8] and set(d["train_ids"]) | set(d["val_ids"]) == set(ids)
    cam = json.loads((out / "camera" / f"{ids[0]}.json").read_text())
    assert cam["radial_distortion"] == [0.0, 0.0, 0.0] and cam["tangential_distortion"] == [0.0, 0.0]
    meta = json.loads((out / "metadata.json").read_text())
    first = int(ids[0])  # image names 000001.png ...: time_id is the index from the first registered one
    assert [meta[i]["time_id"] for i in ids] == [int(i) - first for i in ids]
    assert np.load(out / "points.npy").shape[1] == 3 and info["loader"] == {"split_mode": "ids", "image_scale": 1}


@pytest.mark.slow
def test_the_capture_trains_with_only_its_path(toy_capture, tmp_path):
    """`stdr-train experiment=nerfies_deform data.path=DIR` and nothing else about the data."""
    from stdr.store import compose_config
    from stdr.train.run import run_training as run
    _, out, _ = toy_capture
    cfg = compose_config(["experiment=nerfies_deform", f"data.path={out}", "optim.iterations=20",
                          "baseline.warmup=10", "densify.refine_start=5", "densify.refine_every=5",
                          "train.checkpoint_every=0", "train.eval_at_warmup_end=false", "eval.fps_repeats=1",
                          "data.max_width=96", "eval.lpips=false", "train.progress=false", "eval.save_images=false",
                          "train.image_every=0", "device=cpu"])
    assert cfg.data.split_mode is None and cfg.data.image_scale is None
    res = run(cfg, tmp_path / "run")
    m = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert m["test"]["data"]["settings_from_capture_json"] == {"split_mode": "ids", "image_scale": 1}
    assert m["test"]["data"]["points_source"] == "points_npy" and res["psnr"] > 10


@pytest.mark.slow
def test_capture_from_a_video_of_the_same_frames(shared_dir, tmp_path):
    toy = shared_dir / "data" / "nerfies" / "toy-capture"
    if not toy.is_dir():
        pytest.skip(f"{toy} not present")
    names = sorted((toy / "rgb" / "2x").glob("*.png"))
    frames = [cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2RGB) for p in names]
    video = _encode(frames, tmp_path / "toy.mp4", fps=10)
    out = tmp_path / "toy_video"
    info = cap.capture(video, out, cap.CaptureConfig(frames=None, threads=2))
    ids = json.loads((out / "dataset.json").read_text())["ids"]
    # frame k of the video is image k + 1 of the capture (000001.png first)
    ref_ids = set(json.loads((toy / "dataset.json").read_text())["ids"])
    pairs = [(i, f"{int(i) + 1:06d}") for i in ids if f"{int(i) + 1:06d}" in ref_ids]
    assert len(pairs) >= 0.9 * len(ref_ids)
    e = pose_error.ray_errors(_cameras(out, [a for a, _ in pairs]), _cameras(toy, [b for _, b in pairs]))
    print(f"video capture: {info['timings_s']}; pose errors {e}")
    assert e["position_median"] < POS_MEDIAN and e["position_max"] < POS_MAX, e
    assert e["ray_median_deg"] < RAY_MEDIAN and e["ray_max_deg"] < RAY_MAX, e
    meta = json.loads((out / "metadata.json").read_text())
    # time_id: milliseconds from the first kept frame at 10 fps
    assert [meta[i]["time_id"] for i in ids] == [100 * (int(i) - int(ids[0])) for i in ids]


def test_a_camera_off_the_videos_track_is_dropped_and_named():
    """A hand-held video's cameras move smoothly; one that SfM placed wrongly (turned 60 degrees,
    or moved off the track) disagrees with both neighbours and is named; a smooth track, a fast
    but steady turn and the ends of the track keep every frame."""
    n = 24
    ang = np.linspace(0, np.pi, n)
    centres = np.stack([4 * np.cos(ang), 4 * np.sin(ang), np.zeros(n)], 1)
    forwards = -centres / np.linalg.norm(centres, axis=1, keepdims=True)  # looking at the origin
    ids = [f"{i:06d}" for i in range(n)]
    assert cap.track_outliers(ids, centres, forwards) == {}
    turned = forwards.copy()
    c, s = np.cos(np.radians(60)), np.sin(np.radians(60))
    f = turned[9]
    turned[9] = np.array([c * f[0] - s * f[1], s * f[0] + c * f[1], f[2]])
    out = cap.track_outliers(ids, centres, turned)
    assert list(out) == ["000009"] and "60 degrees" in out["000009"]
    moved = centres.copy()
    moved[15] += np.array([0.0, 0.0, 5.0])  # 4.6 times the distance between its neighbours
    out = cap.track_outliers(ids, moved, forwards)
    assert list(out) == ["000015"] and "off their track" in out["000015"]
    first = forwards.copy()
    first[0] = -first[0]  # the first frame, facing away
    assert list(cap.track_outliers(ids, centres, first)) == ["000000"]
    fast = np.linspace(0, 4 * np.pi, n)  # a fast, steady turn: 30 degrees a frame
    fc = np.stack([4 * np.cos(fast), 4 * np.sin(fast), np.zeros(n)], 1)
    assert cap.track_outliers(ids, fc, -fc / 4) == {}


def test_a_failed_capture_leaves_neither_its_folder_nor_a_partial_one(tmp_path):
    """A text file named .mp4, an empty file and a 1-frame video: each one line (exit 2), and no
    OUT or OUT.partial afterwards."""
    import subprocess
    import sys
    (tmp_path / "notes.mp4").write_text("these are my notes, not a video\n")
    (tmp_path / "empty.mp4").write_bytes(b"")
    _encode(_frames(1), tmp_path / "one.mp4", fps=10)
    for src, said in (("notes.mp4", "not a readable video"), ("empty.mp4", "not a readable video"),
                      ("one.mp4", "only 1 frame(s) decoded; a capture needs at least 3")):
        out = tmp_path / f"out_{src[:-4]}"
        r = subprocess.run([sys.executable, "-m", "stdr.cli.data", "capture", str(tmp_path / src), "--out", str(out)],
                           capture_output=True, text=True, timeout=300)
        assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr[-2000:]
        errors = [ln for ln in r.stderr.splitlines() if ln.startswith("stdr-data: error:")]
        assert len(errors) == 1 and said in errors[0], r.stderr
        assert not out.exists() and not out.with_name(out.name + ".partial").exists(), src


@pytest.mark.slow
@pytest.mark.parametrize("site, named", [("capture", r"capture\.json"), ("frames", r"images/\d+\.png")])
def test_a_disk_fault_at_the_end_of_a_capture_keeps_the_previous_one(toy_capture, tmp_path, monkeypatch, capsys,
                                                                      site, named):
    """--overwrite of a finished capture with the disk failing as its first frame is written
    (STDR_FAILPOINT=frames) or as the new one is complete (capture): one line naming the file,
    the previous capture intact, no .partial."""
    import hashlib
    import re
    from stdr.cli.data import main
    toy, out, _ = toy_capture
    before = {str(p.relative_to(out)): hashlib.sha256(p.read_bytes()).hexdigest() for p in out.rglob("*") if p.is_file()}
    monkeypatch.setenv("STDR_FAILPOINT", f"{site}:ENOSPC")
    with pytest.raises(SystemExit) as e:
        main(["capture", str(toy / "rgb" / "2x"), "--out", str(out), "--frames", "40", "--threads", "2", "--overwrite"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and re.search(f"stdr-data: error: cannot write \\S+{named}: No space left", err), err
    after = {str(p.relative_to(out)): hashlib.sha256(p.read_bytes()).hexdigest() for p in out.rglob("*") if p.is_file()}
    assert after == before and not out.with_name(out.name + ".partial").exists()
