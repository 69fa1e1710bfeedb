import json
import re
import shutil

import numpy as np
import pytest
import torch

from stdr.errors import BadInput
from stdr.data.dnerf import load_dnerf, load_dnerf_split
from stdr.data.procedural import SceneOptions, generate_scene, look_at_c2w, render_frame

SMALL = SceneOptions(n_train=6, n_val=2, n_test=3, resolution=24)


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory):
    return generate_scene(tmp_path_factory.mktemp("proc") / "scene", SMALL)


def _copy(src, tmp_path):
    dst = tmp_path / "scene"
    shutil.copytree(src, dst)
    return dst


def test_procedural_scene_is_deterministic_and_dnerf_shaped(small_scene, tmp_path):
    again = generate_scene(tmp_path / "again", SMALL)
    for f in ("transforms_train.json", "train/r_000.png", "test/r_002.png"):
        assert (small_scene / f).read_bytes() == (again / f).read_bytes(), f
    d = load_dnerf(small_scene, ["train", "val", "test"])
    assert [len(d.frames(s)) for s in ("train", "val", "test")] == [6, 2, 3]
    train_t = d.train_times()
    assert train_t[0] == 0.0 and train_t[-1] == 1.0
    for s in ("val", "test"):
        for f in d.frames(s):
            assert np.abs(train_t - f.time).min() > 1e-3  # held-out times are unseen times
    f0 = d.frames("train")[0]
    assert f0.image.shape == (24, 24, 3) and f0.alpha is not None
    assert 0.02 < float(f0.alpha.mean()) < 0.9  # an object on a transparent background
    # each frame has its own camera
    assert not torch.allclose(d.frames("train")[0].camera.R, d.frames("train")[1].camera.R)


def test_procedural_motion_changes_the_image():
    c2w = look_at_c2w(np.array([0.5, -3.3, 0.8]))
    a, b = render_frame(c2w, 0.0, SMALL), render_frame(c2w, 0.25, SMALL)
    assert np.abs(a.astype(int) - b.astype(int)).mean() > 1.0


def test_background_and_resolution(small_scene):
    w = load_dnerf_split(small_scene, "train", background=(1, 1, 1))
    b = load_dnerf_split(small_scene, "train", background=(0, 0, 0))
    a = w[0].alpha
    assert torch.allclose(w[0].image - b[0].image, (1 - a)[..., None].expand(-1, -1, 3), atol=1e-5)
    half = load_dnerf_split(small_scene, "train", resolution_scale=0.5)
    assert half[0].image.shape == (12, 12, 3)
    assert half[0].camera.fx == pytest.approx(w[0].camera.fx / 2)
    capped = load_dnerf_split(small_scene, "train", max_width=8)
    assert capped[0].camera.width == 8 and capped[0].camera.height == 8


def test_missing_transforms(tmp_path):
    with pytest.raises(FileNotFoundError, match="transforms_train.json"):
        load_dnerf(tmp_path, ["train"])


def test_malformed_json(small_scene, tmp_path):
    d = _copy(small_scene, tmp_path)
    (d / "transforms_test.json").write_text('{"camera_angle_x": 0.7, "frames": [')
    with pytest.raises(ValueError, match=r"transforms_test.json: malformed JSON at line 1"):
        load_dnerf(d, ["test"])


def test_missing_image(small_scene, tmp_path):
    d = _copy(small_scene, tmp_path)
    (d / "train" / "r_003.png").unlink()
    with pytest.raises(FileNotFoundError, match=r"frames\[3\] image './train/r_003' not found"):
        load_dnerf(d, ["train"])


def test_mismatched_image_size(small_scene, tmp_path):
    import cv2
    d = _copy(small_scene, tmp_path)
    cv2.imwrite(str(d / "train" / "r_002.png"), np.zeros((10, 12, 4), np.uint8))
    with pytest.raises(ValueError, match=r"r_002.png: image is 12x10 but r_000.png is 24x24"):
        load_dnerf(d, ["train"])


@pytest.mark.parametrize("edit,match", [
    (lambda m: m.pop("camera_angle_x"), "missing key 'camera_angle_x'"),
    (lambda m: m["frames"][1].pop("time"), r"frames\[1\] has no 'time'"),
    (lambda m: m["frames"][1].update(time=1.5), r"frames\[1\]: time=1.5 is outside \[0, 1\]"),
    (lambda m: m["frames"][0].update(file_path="../../etc/passwd"), "outside the scene folder"),
    (lambda m: m["frames"][0].update(transform_matrix=[[1, 0], [0, 1]]), r"frames\[0\].transform_matrix"),
    # bad data is named at load, with its file and frame (a NaN pose used to train until the guard gave up)
    (lambda m: m["frames"][2]["transform_matrix"][1].__setitem__(3, float("nan")),
     r"transforms_train\.json: frames\[2\] \(\./train/r_002\): the transform_matrix has non-finite values \(nan\)"),
    (lambda m: m["frames"][1]["transform_matrix"][0].__setitem__(0, float("inf")), r"frames\[1\].*non-finite values \(inf\)"),
    (lambda m: m["frames"][1].update(transform_matrix=(2 * np.eye(4)).tolist()),
     r"frames\[1\].*rotation is not orthonormal \(\|R R\^T - I\| = 3\.0e\+00"),
    (lambda m: m["frames"][3].update(transform_matrix=np.diag([1.0, 1.0, -1.0, 1.0]).tolist()),
     r"frames\[3\].*rotation is a reflection \(det < 0\)"),
    (lambda m: m["frames"][1].update(transform_matrix=[["a", 0, 0, 0]] * 4), r"frames\[1\].*not a matrix of numbers"),
    (lambda m: m["frames"][1].update(time=float("nan")), r"frames\[1\]: time=nan is outside \[0, 1\]"),
    (lambda m: m["frames"][1].update(time="late"), r"frames\[1\]: time='late' is not a number"),
    (lambda m: m.update(camera_angle_x=float("nan")), r"camera_angle_x=nan must be a field of view"),
    (lambda m: m.update(camera_angle_x=-0.7), r"camera_angle_x=-0\.7 must be a field of view in radians, in \(0, pi\)"),
    (lambda m: m.update(camera_angle_y=4.0), r"camera_angle_y=4\.0 must be a field of view"),
])
def test_bad_keys(small_scene, tmp_path, edit, match):
    d = _copy(small_scene, tmp_path)
    meta = json.loads((d / "transforms_train.json").read_text())
    edit(meta)
    (d / "transforms_train.json").write_text(json.dumps(meta))
    with pytest.raises((KeyError, ValueError), match=match):
        load_dnerf(d, ["train"])


def test_shared_dnerf_scenes_load(shared_dir):
    expect = {"bouncingballs": 150, "hellwarrior": 100, "jumpingjacks": 200, "standup": 150}
    for name, n_train in expect.items():
        root = shared_dir / "data" / "dnerf" / name
        d = load_dnerf(root, ["train", "test"], background="white", max_width=200)
        assert len(d.frames("train")) == n_train and len(d.frames("test")) == 20
        f = d.frames("train")[0]
        assert (f.camera.width, f.camera.height) == (200, 200)
        assert f.camera.fx == pytest.approx(0.5 * 200 / np.tan(0.5 * 0.6911112070083618), rel=1e-6)
        # D-NeRF cameras look at the origin from about 4 units away: the origin projects near the centre
        uv, z = f.camera.project(torch.zeros(1, 3))
        assert 2.0 < float(z) < 6.0
        assert torch.allclose(uv, torch.tensor([[100.0, 100.0]]), atol=20)
        # times are read as written (in these copies every test time is also a train time:
        # the test views differ from the training views in camera, not in time)
        js = json.loads((root / "transforms_test.json").read_text())["frames"]
        assert [f.time for f in d.frames("test")] == [float(x["time"]) for x in js]


def _scene_copy(small_scene, tmp_path):
    import shutil
    dst = tmp_path / "scene"
    shutil.copytree(small_scene, dst)
    return dst, json.loads((dst / "transforms_train.json").read_text())


def _verify_line(folder):
    """stdr-data verify FOLDER as a user runs it: (exit code, its stdout + stderr)."""
    import subprocess
    import sys
    r = subprocess.run([sys.executable, "-m", "stdr.cli.data", "verify", str(folder)], capture_output=True,
                       text=True, timeout=300)
    assert "Traceback" not in r.stderr, r.stderr
    return r.returncode, r.stdout + r.stderr


def test_verify_decodes_every_image_and_names_an_undecodable_one(small_scene, tmp_path):
    scene, meta = _scene_copy(small_scene, tmp_path)
    rc, out = _verify_line(scene)
    assert rc == 0 and "ok" in out
    bad = scene / (meta["frames"][2]["file_path"] + ("" if meta["frames"][2]["file_path"].endswith(".png") else ".png"))
    bad.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(92)))  # 100 bytes: a PNG signature and no image
    rc, out = _verify_line(scene)
    assert rc != 0 and f"could not decode image {bad.resolve()}" in out
    with pytest.raises(BadInput, match="could not decode image"):
        load_dnerf(scene, ["train"])


def test_a_split_mixing_rgb_and_rgba_frames_or_repeating_an_image_is_named_at_load(small_scene, tmp_path):
    import cv2
    scene, meta = _scene_copy(small_scene, tmp_path)
    fp = meta["frames"][3]["file_path"]
    img = scene / (fp if fp.endswith(".png") else fp + ".png")
    cv2.imwrite(str(img), cv2.imread(str(img), cv2.IMREAD_UNCHANGED)[..., :3])  # the alpha channel dropped
    with pytest.raises(BadInput, match=rf"frames\[3\] \({img.name}\) has none but frames\[0\] \(\S+\) has an alpha "
                                       "channel: a D-NeRF split's images are all RGBA"):
        load_dnerf(scene, ["train"])
    rc, out = _verify_line(scene)
    assert rc != 0 and "has an alpha channel" in out
    scene, meta = _scene_copy(small_scene, tmp_path / "b")
    meta["frames"][4]["file_path"] = meta["frames"][1]["file_path"]
    (scene / "transforms_train.json").write_text(json.dumps(meta))
    with pytest.raises(BadInput, match=r"frames\[4\] and frames\[1\] both use the image"):
        load_dnerf(scene, ["train"])
    rc, out = _verify_line(scene)
    assert rc != 0 and "both use the image" in out


@pytest.mark.parametrize("change, said", [
    (lambda m: m["frames"][2].update(time=1.5), "frames[2]: time=1.5 is outside [0, 1]"),
    (lambda m: m.update(camera_angle_x=-0.5), "camera_angle_x=-0.5 must be a field of view in radians"),
    ("big", "all frames of a D-NeRF scene must have one size"),
])
def test_verify_refuses_what_stdr_train_refuses(small_scene, tmp_path, change, said):
    """stdr-data verify applies the loader's checks: a scene it calls ok is one stdr-train reads."""
    import cv2
    scene, meta = _scene_copy(small_scene, tmp_path)
    if change == "big":  # one image 4x the others' size
        fp = meta["frames"][1]["file_path"]
        img = scene / (fp if fp.endswith(".png") else fp + ".png")
        cv2.imwrite(str(img), cv2.resize(cv2.imread(str(img), cv2.IMREAD_UNCHANGED), (96, 96)))
    else:
        change(meta)
        (scene / "transforms_train.json").write_text(json.dumps(meta))
    rc, out = _verify_line(scene)
    assert rc != 0 and "FAIL" in out and said in out, out
    with pytest.raises(BadInput, match=re.escape(said)):
        load_dnerf(scene, ["train"])


def test_a_field_of_view_no_camera_has_is_said_once_where_it_is_read(small_scene, tmp_path, capsys):
    scene, meta = _scene_copy(small_scene, tmp_path)
    meta["camera_angle_x"] = 1e-9
    (scene / "transforms_train.json").write_text(json.dumps(meta))
    load_dnerf(scene, ["train"])
    err = capsys.readouterr().err
    assert "camera_angle_x=1e-09 rad" in err and "is not a field of view a camera has" in err
    load_dnerf(small_scene, ["train"])  # 0.69 rad (about 40 degrees): nothing said
    assert "field of view" not in capsys.readouterr().err
