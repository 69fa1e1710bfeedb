"""Nerfies-format loader (NeRF-DS, HyperNeRF): lens model, undistortion, COLMAP, malformed input,
and the real phone capture in ../shared/data/nerfies/toy-capture."""
import json
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from stdr.data import colmap
from stdr.data.distortion import LensCamera, remap, undistortion
from stdr.data.nerfies import load_nerfies
from stdr.errors import IOFault

LENS = LensCamera(fx=75.0, fy=78.0, cx=41.3, cy=33.7, skew=0.0, k=(0.09, -0.23, 0.02), p=(0.0025, 0.03),
                  width=80, height=64)


def _rot(ax, ay, az):
    Rx = cv2.Rodrigues(np.array([ax, 0.0, 0.0]))[0]
    Ry = cv2.Rodrigues(np.array([0.0, ay, 0.0]))[0]
    Rz = cv2.Rodrigues(np.array([0.0, 0.0, az]))[0]
    return Rz @ Ry @ Rx


def make_scene(root: Path, n=8, size=(16, 12), scales=(1, 2), distortion=None, time_key="warp_id",
               val_every=4, skew=0.0):
    """A minimal Nerfies-format scene: n frames of one camera circling the origin."""
    root.mkdir(parents=True, exist_ok=True)
    ids = [f"{i:06d}" for i in range(n)]
    val = ids[1::val_every]
    train = [i for i in ids if i not in val]
    (root / "dataset.json").write_text(json.dumps({"count": n, "num_exemplars": len(train), "ids": ids,
                                                   "train_ids": train, "val_ids": val}))
    (root / "metadata.json").write_text(json.dumps(
        {i: {time_key: k, "appearance_id": k, "camera_id": 0} for k, i in enumerate(ids)}))
    (root / "scene.json").write_text(json.dumps({"center": [1.0, -2.0, 0.5], "scale": 0.25,
                                                 "near": 0.01, "far": 10.0}))
    (root / "camera").mkdir(exist_ok=True)
    rng = np.random.default_rng(0)
    for k, i in enumerate(ids):
        R = _rot(0.1, 0.2 * k / n, 0.05)
        cam = {"orientation": R.tolist(), "position": [1.0 + 0.5 * k, -2.0, -3.0],
               "focal_length": 20.0, "principal_point": [size[0] / 2 + 0.3, size[1] / 2 - 0.2],
               "skew": skew, "pixel_aspect_ratio": 1.05,
               "radial_distortion": [0.0, 0.0, 0.0] if distortion is None else distortion[0],
               "tangential_distortion": [0.0, 0.0] if distortion is None else distortion[1],
               "image_size": list(size)}
        (root / "camera" / f"{i}.json").write_text(json.dumps(cam))
        for s in scales:
            d = root / "rgb" / f"{s}x"
            d.mkdir(parents=True, exist_ok=True)
            img = rng.integers(0, 255, (size[1] // s, size[0] // s, 3), dtype=np.uint8)
            cv2.imwrite(str(d / f"{i}.png"), img)
    return ids, train, val


def load(root, **kw):
    args = dict(split_mode="ids", image_scale=1, cache_dir=None)
    args.update(kw)
    return load_nerfies(root, ("train", "test"), **args)


# ----------------------------------------------------------------------------- lens model
def test_distortion_matches_opencv_projectPoints():
    rng = np.random.default_rng(1)
    X = np.concatenate([rng.uniform(-0.5, 0.5, (200, 2)), rng.uniform(1.0, 3.0, (200, 1))], 1)
    K = np.array([[LENS.fx, 0, LENS.cx], [0, LENS.fy, LENS.cy], [0, 0, 1.0]])
    dist = np.array([LENS.k[0], LENS.k[1], LENS.p[0], LENS.p[1], LENS.k[2]])
    ref, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), K, dist)
    np.testing.assert_allclose(LENS.project(X), ref[:, 0], atol=1e-9)


def test_undistort_inverts_distort_over_the_image():
    u, v = np.meshgrid(np.linspace(0, LENS.width, 40), np.linspace(0, LENS.height, 30))
    xy_d = LENS.pixels_to_normalized(np.stack([u.ravel(), v.ravel()], -1))
    xy = LENS.undistort_normalized(xy_d)
    np.testing.assert_allclose(LENS.distort(xy), xy_d, atol=1e-10)
    assert np.abs(xy - xy_d).max() > 1e-2  # the lens really distorts


def test_undistortion_map_matches_opencv():
    pin, mx, my = undistortion(LENS)
    # OpenCV puts pixel centres at integer coordinates: shift the principal points by 0.5.
    K = np.array([[LENS.fx, 0, LENS.cx - 0.5], [0, LENS.fy, LENS.cy - 0.5], [0, 0, 1.0]])
    Kn = np.array([[pin.fx, 0, pin.cx - 0.5], [0, pin.fy, pin.cy - 0.5], [0, 0, 1.0]])
    dist = np.array([LENS.k[0], LENS.k[1], LENS.p[0], LENS.p[1], LENS.k[2]])
    rx, ry = cv2.initUndistortRectifyMap(K, dist, None, Kn, (LENS.width, LENS.height), cv2.CV_32FC1)
    np.testing.assert_allclose(mx, rx, atol=2e-3)
    np.testing.assert_allclose(my, ry, atol=2e-3)
    # every output pixel samples inside the source image, and the rectangle is tight
    assert mx.min() >= -0.5 - 1e-4 and mx.max() <= LENS.width - 0.5 + 1e-4
    assert my.min() >= -0.5 - 1e-4 and my.max() <= LENS.height - 0.5 + 1e-4
    assert min(-0.5 - mx.min(), -0.5 - my.min()) > -1.0  # touches the image edge within a pixel


@pytest.mark.parametrize("skew", [0.0, 3.5])
def test_undistorted_pinhole_sees_what_the_lens_sees(skew):
    """A point projected by the undistorted pinhole camera samples the source pixel that the
    lens (with skew, pixel aspect and distortion) projects it to."""
    lens = LensCamera(**{**LENS.__dict__, "skew": skew})
    pin, mx, my = undistortion(lens)
    rng = np.random.default_rng(2)
    uv_pin = np.stack([rng.uniform(2, lens.width - 2, 300), rng.uniform(2, lens.height - 2, 300)], -1)
    X = np.concatenate([(uv_pin - [pin.cx, pin.cy]) / [pin.fx, pin.fy], np.ones((300, 1))], 1) * 2.0
    grid = np.stack([mx, my], -1)[None]  # sample the maps bilinearly at the pinhole pixels
    src = cv2.remap(grid[0], (uv_pin[:, 0] - 0.5).astype(np.float32)[None],
                    (uv_pin[:, 1] - 0.5).astype(np.float32)[None], cv2.INTER_LINEAR)[0] + 0.5
    np.testing.assert_allclose(src, lens.project(X), atol=0.02)


def round_trip(lens, img):
    """Undistort img, then distort it back: (undistorted, redistorted, mask of pixels whose
    redistortion reads the inside of the undistorted image)."""
    W, H = lens.width, lens.height
    pin, mx, my = undistortion(lens)
    und = remap(img, mx, my)
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    xy = lens.undistort_normalized(lens.pixels_to_normalized(np.stack([u.ravel(), v.ravel()], -1)))
    bx = (xy[:, 0] * pin.fx + pin.cx - 0.5).reshape(H, W).astype(np.float32)
    by = (xy[:, 1] * pin.fy + pin.cy - 0.5).reshape(H, W).astype(np.float32)
    return und, remap(und, bx, by), (bx > 1) & (bx < W - 2) & (by > 1) & (by < H - 2)


def test_image_round_trip_through_undistortion():
    # a smooth image survives undistort -> redistort in the region the pinhole image covers
    W, H = LENS.width, LENS.height
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    img = np.stack([0.5 + 0.4 * np.sin(u / 7.0), 0.5 + 0.4 * np.cos(v / 5.0), (u + v) / (W + H)], -1)
    und, red, inside = round_trip(LENS, img.astype(np.float32))
    assert inside.mean() > 0.7
    err = np.abs(red - img)[inside].max()
    assert err < 0.02, err


# ----------------------------------------------------------------------------- the loader
def test_loads_split_times_intrinsics_and_normalization(tmp_path):
    ids, train, val = make_scene(tmp_path / "s")
    sc = load(tmp_path / "s")
    assert [f.name for f in sc.frames("train")] == [f"rgb/1x/{i}.png" for i in train]
    assert [f.name for f in sc.frames("test")] == [f"rgb/1x/{i}.png" for i in val]
    assert sc.meta["time_key"] == "warp_id"  # no time_id anywhere: falls back
    # t = warp_id / max over all frames
    assert [f.time for f in sc.frames("train")] == pytest.approx([ids.index(i) / 7 for i in train])
    cam = sc.frames("train")[0].camera
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == pytest.approx((20.0, 21.0, 8.3, 5.8))
    # positions are normalized by scene.json: (p - center) * scale
    np.testing.assert_allclose(cam.center.numpy(), (np.array([1.0, -2.0, -3.0]) - [1.0, -2.0, 0.5]) * 0.25,
                               atol=1e-6)
    raw = load(tmp_path / "s", normalize_scene=False).frames("train")[0].camera
    np.testing.assert_allclose(raw.center.numpy(), [1.0, -2.0, -3.0], atol=1e-5)
    assert sc.init_points is None  # no points.npy, no COLMAP model


def test_image_scale_scales_intrinsics(tmp_path):
    make_scene(tmp_path / "s")
    c1 = load(tmp_path / "s").frames("train")[1].camera
    c2 = load(tmp_path / "s", image_scale=2).frames("train")[1].camera
    assert (c2.width, c2.height) == (8, 6)
    X = torch.tensor([[0.3, -0.2, 0.4], [-0.1, 0.1, 0.2]])
    uv1, _ = c1.project(X)
    uv2, _ = c2.project(X)
    torch.testing.assert_close(uv2, uv1 / 2)  # the same point lands on the same image location


def test_time_id_preferred_and_interp_split(tmp_path):
    ids, _, _ = make_scene(tmp_path / "s", time_key="time_id")
    sc = load(tmp_path / "s", split_mode="interp")
    assert sc.meta["time_key"] == "time_id"
    assert [f.name[-10:-4] for f in sc.frames("train")] == ids[::4]
    assert [f.name[-10:-4] for f in sc.frames("test")] == ids[2::4]
    # test times are unseen in training (held out in time)
    assert not set(f.time for f in sc.frames("test")) & set(sc.train_times())


def test_points_npy_is_normalized_like_the_cameras(tmp_path):
    make_scene(tmp_path / "s")
    pts = np.array([[1.0, -2.0, 0.5], [5.0, 2.0, 4.5], [0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    np.save(tmp_path / "s" / "points.npy", pts)
    sc = load(tmp_path / "s")
    assert sc.meta["points_source"] == "points_npy"
    np.testing.assert_allclose(sc.init_points, (pts - [1.0, -2.0, 0.5]) * 0.25)
    np.save(tmp_path / "s" / "points.npy", pts[:, :2])
    with pytest.raises(ValueError, match=r"points\.npy.*\[P, 3\]"):
        load(tmp_path / "s")


def test_distortion_undistorted_once_and_cached(tmp_path):
    make_scene(tmp_path / "s", size=(40, 30), distortion=([0.05, -0.02, 0.0], [0.001, 0.002]), skew=0.4)
    with pytest.raises(ValueError, match=r"camera/000000\.json.*lens distortion.*data\.distortion=undistort"):
        load(tmp_path / "s", distortion="error")
    cache = tmp_path / "cache"
    a = load(tmp_path / "s", cache_dir=cache)
    assert a.meta["undistort_cache"]["misses"] == 8 and a.meta["undistort_cache"]["hits"] == 0
    b = load(tmp_path / "s", cache_dir=cache)
    assert b.meta["undistort_cache"]["hits"] == 8
    for fa, fb in zip(a.frames("train"), b.frames("train")):
        assert (fa.camera.fx, fa.camera.cx) == (fb.camera.fx, fb.camera.cx)
        assert (fa.image - fb.image).abs().max() < 1e-4  # 16-bit cache
    # the pinhole differs from the raw intrinsics, and the image differs from the raw image
    ign = load(tmp_path / "s", distortion="ignore")
    assert ign.frames("train")[0].camera.fx == pytest.approx(20.0)
    assert a.frames("train")[0].camera.fx != pytest.approx(20.0, rel=1e-3)
    # a changed source image is recomputed, not served stale
    img = cv2.imread(str(tmp_path / "s/rgb/1x/000000.png"))
    cv2.imwrite(str(tmp_path / "s/rgb/1x/000000.png"), 255 - img)
    c = load(tmp_path / "s", cache_dir=cache)
    assert c.meta["undistort_cache"]["misses"] == 1
    assert (c.frames("train")[0].image - a.frames("train")[0].image).abs().mean() > 0.1
    # a manifest from another layout (or damaged) is recomputed, not an error
    man = next(cache.rglob("000002.json"))
    _edit_json(man, lambda d: d.__setitem__("pinhole", {"fx": 1.0}))
    d = load(tmp_path / "s", cache_dir=cache)
    assert d.meta["undistort_cache"]["misses"] == 1
    assert d.frames("train")[1].camera.fx == pytest.approx(a.frames("train")[1].camera.fx)


def test_a_fault_while_caching_an_undistorted_image_names_it_and_leaves_no_half_file(tmp_path, monkeypatch):
    """The undistortion cache is written through the atomic writer: a full disk is one IOFault
    naming the image, no temporary or half PNG stays, and the next load fills the cache."""
    make_scene(tmp_path / "s", size=(40, 30), distortion=([0.05, -0.02, 0.0], [0.001, 0.002]))
    cache = tmp_path / "cache"
    monkeypatch.setenv("STDR_FAILPOINT", "cache:ENOSPC")
    with pytest.raises(IOFault, match=r"cannot write .*cache.*\.png: No space left on device"):
        load(tmp_path / "s", cache_dir=cache)
    assert [p.name for p in cache.rglob("*") if p.is_file()] == []
    monkeypatch.delenv("STDR_FAILPOINT")
    a = load(tmp_path / "s", cache_dir=cache)
    assert a.meta["undistort_cache"]["misses"] == 8
    assert load(tmp_path / "s", cache_dir=cache).meta["undistort_cache"]["hits"] == 8


@pytest.mark.parametrize("edit, said", [
    (lambda r: _edit_json(r / "scene.json", lambda d: d.__setitem__("scale", -1.0)), r"scene\.json: .*scale must be positive"),
    (lambda r: _edit_json(r / "metadata.json", lambda d: d.pop("000003")), r"metadata\.json.*000003"),
    (lambda r: _edit_json(r / "camera/000002.json", lambda d: d.pop("focal_length")), r"000002\.json.*focal_length"),
])
def test_verify_applies_the_nerfies_loaders_checks(tmp_path, edit, said):
    """stdr-data verify calls a Nerfies scene ok only if stdr-train reads it: every file is there
    and decodes, and the loader's own checks (times, cameras, normalization) pass at every scale."""
    from stdr.data.fetch import DataError
    from stdr.data.load import verify_scene
    make_scene(tmp_path / "s")
    assert verify_scene(tmp_path / "s", "nerfies") == 8
    edit(tmp_path / "s")
    with pytest.raises(DataError, match=r"not a Nerfies-format scene stdr-train reads .*data\.split_mode=ids") as e:
        verify_scene(tmp_path / "s", "nerfies")
    assert re.search(said, str(e.value))


def _edit_json(path: Path, fn):
    d = json.loads(path.read_text())
    fn(d)
    path.write_text(json.dumps(d))


@pytest.mark.parametrize("edit, kind, match", [
    (lambda r: (r / "camera/000002.json").unlink(), FileNotFoundError, r"camera/000002\.json not found"),
    (lambda r: _edit_json(r / "camera/000003.json", lambda d: d.pop("focal_length")), KeyError,
     r"camera/000003\.json: missing key 'focal_length'"),
    (lambda r: _edit_json(r / "camera/000003.json", lambda d: d.__setitem__("orientation", np.eye(3).tolist()[:2])),
     ValueError, r"000003\.json: orientation=.* is not a 3x3 matrix of numbers"),
    (lambda r: _edit_json(r / "camera/000003.json",
                          lambda d: d.__setitem__("orientation", (2 * np.eye(3)).tolist())),
     ValueError, r"000003\.json \(id '000003'\): the camera \(orientation, position\)'s rotation is not orthonormal"),
    # bad data is named at load, with its file and frame
    (lambda r: _edit_json(r / "camera/000003.json", lambda d: d["orientation"][1].__setitem__(2, float("nan"))),
     ValueError, r"000003\.json \(id '000003'\): the camera \(orientation, position\) has non-finite values \(nan\)"),
    (lambda r: _edit_json(r / "camera/000004.json", lambda d: d["position"].__setitem__(0, float("inf"))),
     ValueError, r"000004\.json \(id '000004'\): .*non-finite values \(inf\)"),
    (lambda r: _edit_json(r / "camera/000003.json", lambda d: d.__setitem__("orientation", np.diag([1.0, -1, 1]).tolist())),
     ValueError, r"000003\.json.*rotation is a reflection"),
    (lambda r: _edit_json(r / "camera/000003.json", lambda d: d.__setitem__("focal_length", float("nan"))),
     ValueError, r"000003\.json: focal_length=nan has non-finite values"),
    (lambda r: _edit_json(r / "camera/000003.json", lambda d: d.__setitem__("focal_length", -20.0)),
     ValueError, r"000003\.json: focal_length and pixel_aspect_ratio must be positive"),
    (lambda r: _edit_json(r / "camera/000003.json", lambda d: d.__setitem__("principal_point", [500.0, 10.0])),
     ValueError, r"000003\.json: principal point \(500, 10\) lies outside the \d+x\d+ image"),
    (lambda r: _edit_json(r / "camera/000003.json", lambda d: d.__setitem__("image_size", [float("nan"), 30])),
     ValueError, r"000003\.json: image_size=\[nan, 30\] has non-finite values"),
    (lambda r: cv2.imwrite(str(r / "rgb/1x/000002.png"), np.zeros((12, 15, 3), np.uint8)), ValueError,
     r"rgb/1x/000002\.png: image is 15x12.*data\.image_scale"),
    (lambda r: (r / "rgb/1x/000004.png").unlink(), FileNotFoundError, r"rgb/1x/000004\.png"),
    (lambda r: _edit_json(r / "metadata.json", lambda d: d.pop("000005")), KeyError,
     r"metadata\.json: no entry for id '000005'"),
    (lambda r: _edit_json(r / "metadata.json", lambda d: d["000005"].pop("warp_id")), KeyError,
     r"metadata\.json: missing key 'warp_id' in entry '000005'"),
    (lambda r: _edit_json(r / "metadata.json", lambda d: d["000005"].__setitem__("time_id", 5)), KeyError,
     r"some entries have 'time_id' and some not"),
    (lambda r: _edit_json(r / "dataset.json", lambda d: d.pop("train_ids")), KeyError,
     r"dataset\.json: missing key 'train_ids'.*split_mode=interp"),
    (lambda r: _edit_json(r / "dataset.json", lambda d: d["train_ids"].append("000001")), ValueError,
     r"in both train_ids and val_ids"),
    (lambda r: _edit_json(r / "dataset.json", lambda d: d.__setitem__("val_ids", [])), ValueError,
     r"val_ids is empty.*split_mode=interp"),
    (lambda r: _edit_json(r / "scene.json", lambda d: d.pop("scale")), KeyError, r"scene\.json: missing key 'scale'"),
    (lambda r: (r / "dataset.json").write_text("{ids: 1"), ValueError, r"dataset\.json: malformed JSON"),
])
def test_malformed_input_is_named(tmp_path, edit, kind, match):
    make_scene(tmp_path / "s")
    edit(tmp_path / "s")
    with pytest.raises(kind, match=match):
        load(tmp_path / "s")


@pytest.mark.parametrize("kw, match", [
    (dict(split_mode=None), r"data\.split_mode is not set"),
    (dict(split_mode="folder"), r"data\.split_mode='folder'"),
    (dict(image_scale=None), r"data\.image_scale"),
    (dict(image_scale=4), r"rgb/4x not found.*rgb/\{1x,2x\}"),
    (dict(time_key="frame"), r"data\.time_key='frame'"),
    (dict(intrinsics="colmap"), r"colmap/sparse/0: data\.intrinsics=colmap needs a COLMAP"),
    (dict(points_source="colmap"), r"no COLMAP model"),
])
def test_bad_options_are_named(tmp_path, kw, match):
    make_scene(tmp_path / "s")
    with pytest.raises((ValueError, KeyError, FileNotFoundError), match=match):
        load(tmp_path / "s", **kw)


def test_data_config_selects_the_loader(tmp_path):
    from omegaconf import OmegaConf

    from stdr.config import DataConfig
    from stdr.data.load import load_scene
    make_scene(tmp_path / "s")
    cfg = OmegaConf.merge(OmegaConf.structured(DataConfig), OmegaConf.load("stdr/configs/data/nerfies.yaml"),
                          {"path": str(tmp_path / "s"), "split_mode": "ids", "image_scale": 2,
                           "undistort_cache": None})
    sc = load_scene(cfg, ("train", "test"))
    assert sc.meta["format"] == "nerfies" and sc.background == (0.0, 0.0, 0.0)
    assert sc.frames("test")[0].image.shape == (6, 8, 3)


# ----------------------------------------------------------------------------- the real capture
@pytest.fixture(scope="module")
def toy(shared_dir):
    root = shared_dir / "data" / "nerfies" / "toy-capture"
    if not root.is_dir():
        pytest.skip(f"{root} not found")
    return root


def test_colmap_reader_on_the_capture(toy, tmp_path):
    m = colmap.read_model(toy / "colmap" / "sparse" / "0")
    assert len(m.images) == 92 and len(m.xyz) == 1305
    cam = m.cameras[1]
    assert (cam.model, cam.width, cam.height) == ("OPENCV", 120, 214)
    # COLMAP's own poses equal the camera files' (same world frame)
    img = next(i for i in m.images.values() if i.name == "000010.png")
    cj = json.loads((toy / "camera" / "000010.json").read_text())
    np.testing.assert_allclose(img.R, cj["orientation"], atol=1e-6)
    np.testing.assert_allclose(-img.R.T @ img.tvec, cj["position"], atol=1e-5)
    # a truncated file is an error naming it
    bad = tmp_path / "m"
    shutil.copytree(toy / "colmap" / "sparse" / "0", bad)
    (bad / "points3D.bin").write_bytes((toy / "colmap/sparse/0/points3D.bin").read_bytes()[:-7])
    with pytest.raises(ValueError, match=r"points3D\.bin: truncated"):
        colmap.read_model(bad)


DEGENERATE_DEPTH = 1e-4  # scene units; far from both the degenerate point (3.5e-9) and the rest (>= 3.3e-3)


def _reprojection(scene, model, root, image_scale, lens_source):
    """Distance (in 4x pixels) between the loaded cameras' projections of the COLMAP points and
    COLMAP's keypoints carried into the loaded (undistorted) images through the same lens."""
    from stdr.data.lenses import lens_from_camera_json, lens_from_colmap
    pid = {p: i for i, p in enumerate(model.point_ids)}
    by_name = {Path(i.name).stem: i for i in model.images.values()}
    errs, inside, depth_ok, degenerate = [], [], [], []
    for f in [f for s in scene.splits.values() for f in s]:
        fid = Path(f.name).stem
        im = by_name[fid]
        sel = im.point3d_ids >= 0
        X = (model.xyz[[pid[p] for p in im.point3d_ids[sel]]] - scene.meta["scene_center"]) * scene.meta["scene_scale"]
        # float64, and points in the camera's own depth plane excluded explicitly: one COLMAP point
        # of the capture lies at depth 3.5e-9 (the next at 3.3e-3, the median 0.23), which float32
        # rounds to exactly 0.0 on some CPUs and not others
        R, t = f.camera.R.double().numpy(), f.camera.t.double().numpy()
        xc = X @ R.T + t
        ok = np.abs(xc[:, 2]) > DEGENERATE_DEPTH
        degenerate.append(int((~ok).sum()))
        z = xc[ok, 2]
        uv = np.stack([f.camera.fx * xc[ok, 0] / z + f.camera.cx, f.camera.fy * xc[ok, 1] / z + f.camera.cy], -1)
        W, H = f.camera.width, f.camera.height
        inside.append(((uv >= 0) & (uv <= [W, H])).all(1))
        depth_ok.append(z > 0)
        # keypoints are pixels of the raw 4x images: undistort them with the lens the loader used
        if lens_source == "colmap":
            lens = lens_from_colmap(model, fid, root)
        else:
            lens = lens_from_camera_json(json.loads((root / "camera" / f"{fid}.json").read_text()), root)
            lens = lens.scaled(120, 214)
        xy = lens.undistort_normalized(lens.pixels_to_normalized(im.xys[sel][ok]))
        kp = xy * [f.camera.fx, f.camera.fy] + [f.camera.cx, f.camera.cy]
        errs.append(np.linalg.norm(uv - kp, axis=1) * image_scale / 4)
    return np.concatenate(errs), np.concatenate(inside), np.concatenate(depth_ok), sum(degenerate)


def test_toy_capture_loads_and_colmap_points_project_where_observed(toy, tmp_path):
    sc = load_nerfies(toy, ("train", "val"), split_mode="ids", image_scale=2, cache_dir=tmp_path / "c")
    assert len(sc.frames("train")) == 82 and len(sc.frames("val")) == 5
    assert sc.meta["time_key"] == "warp_id"
    assert sc.frames("train")[0].image.shape == (428, 240, 3)
    t = sc.train_times()
    assert t.min() == 0.0 and t.max() == 1.0 and len(t) == 82
    assert sc.meta["points_source"] == "colmap" and sc.init_points.shape == (1305, 3)
    assert sc.init_colors.shape == (1305, 3) and 0.0 <= sc.init_colors.min() and sc.init_colors.max() <= 1.0
    # the camera files' fy disagrees with COLMAP's (pixel_aspect_ratio 1.0 vs fy/fx = 1.033): recorded
    assert sc.meta["intrinsics_check"]["max_rel_focal_diff"] == pytest.approx(0.0332, abs=1e-3)

    model = colmap.read_model(toy / "colmap" / "sparse" / "0")
    err, inside, front, degenerate = _reprojection(sc, model, toy, 2, "camera")
    assert degenerate == 1 and front.size == 11947 - 1  # one COLMAP point in a camera's depth plane
    assert front.all() and inside.mean() > 0.999
    sc_c = load_nerfies(toy, ("train", "val"), split_mode="ids", image_scale=2, intrinsics="colmap",
                        cache_dir=tmp_path / "c")
    err_c, inside_c, _, _ = _reprojection(sc_c, model, toy, 2, "colmap")
    assert inside_c.mean() > 0.999
    # with COLMAP's intrinsics the chain (normalization, pose, undistortion) reproduces COLMAP's own
    # residual (mean 0.46 px at 4x); the camera files' aspect ratio costs about a pixel more
    print(f"median reprojection error (4x px): camera files {np.median(err):.3f}, colmap {np.median(err_c):.3f}")
    assert np.median(err_c) < 0.6, np.median(err_c)
    assert np.median(err) > np.median(err_c) + 0.4


def test_toy_capture_undistortion_round_trips(toy):
    cj = json.loads((toy / "camera" / "000010.json").read_text())
    from stdr.data.images import read_image
    from stdr.data.lenses import lens_from_camera_json
    lens = lens_from_camera_json(cj, toy / "camera" / "000010.json").scaled(240, 428)
    assert lens.has_distortion
    img = read_image(toy / "rgb" / "2x" / "000010.png")
    und, red, inside = round_trip(lens, img)
    assert inside.mean() > 0.85
    mse = float(((red - img)[inside] ** 2).mean())
    psnr = -10 * np.log10(mse)
    assert psnr > 30, psnr  # two bilinear resamplings of a real photo
    # and undistortion is not the identity on this lens
    assert float(((und - img) ** 2).mean()) > 10 * mse


@pytest.mark.slow
def test_toy_capture_short_training_run(toy, tmp_path):
    """A short deform run on the real capture (4x, 600 iterations) fits its held-out frames."""
    from hydra import compose, initialize_config_dir

    from stdr.config import CONFIG_DIR
    from stdr.train.run import run_training as run
    from stdr.store import register
    register()
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base=None):
        cfg = compose("train", overrides=[
            "experiment=nerfds_deform", "data=nerfies", f"data.path={toy}", "data.split_mode=ids",
            "data.image_scale=4", "data.intrinsics=colmap", f"data.undistort_cache={tmp_path / 'cache'}",
            "optim.iterations=600", "optim.means_lr_max_steps=600", "baseline.warmup=200",
            "baseline.lr_max_steps=600", "densify.refine_stop=450", "densify.max_gaussians=6000",
            "eval.lpips=false", "eval.save_images=false", "train.progress=false", "train.image_every=0",
            "train.checkpoint_every=0"])
    res = run(cfg, tmp_path / "run")
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())["test"]
    assert metrics["data"]["format"] == "nerfies" and metrics["data"]["intrinsics"] == "colmap"
    # the trivial predictor: every pixel the mean colour of the training images
    from stdr.data.load import load_scene
    sc = load_scene(cfg.data, ("train", "test"))
    mean = torch.stack([f.image for f in sc.frames("train")]).mean((0, 1, 2))
    mse0 = torch.stack([((f.image - mean) ** 2).mean() for f in sc.frames("test")]).mean()
    psnr0 = float(-10 * torch.log10(mse0))
    print(f"toy capture 4x, 600 it: val PSNR {res['psnr']:.2f} dB (mean-colour predictor {psnr0:.2f} dB), "
          f"{res['num_gaussians']} Gaussians, {res['train_seconds']:.0f} s")
    assert res["psnr"] > 24.0 and res["psnr"] > psnr0 + 10.0
