"""Stress transforms of the training set: what each key does, that the evaluation
splits are untouched, reproducibility, and errors naming the key."""
import json

import numpy as np
import pytest
import torch
from stdr.data.load import load_scene
from stdr.testing import tiny_config


def _scene(tmp_path, extra=(), seed=0):
    cfg = tiny_config(tmp_path, list(extra))
    return load_scene(cfg.data, ("train", "val", "test"), seed=seed)


@pytest.fixture(scope="module")
def plain(tmp_path_factory):
    return _scene(tmp_path_factory.mktemp("plain"))


def _same_split(a, b):
    assert [f.name for f in a] == [f.name for f in b]
    for x, y in zip(a, b):
        assert x.time == y.time and torch.equal(x.camera.R, y.camera.R) and torch.equal(x.camera.t, y.camera.t)


def test_no_stress_is_the_identity(tmp_path, plain):
    again = _scene(tmp_path)
    for s in ("train", "val", "test"):
        _same_split(plain.frames(s), again.frames(s))
    assert "stress" not in again.meta


def test_drop_window_removes_exactly_those_times_and_leaves_evaluation_alone(tmp_path, plain):
    sc = _scene(tmp_path, ["data.stress.drop_times=[0.3,0.6]"])
    kept = [f.name for f in sc.frames("train")]
    want = [f.name for f in plain.frames("train") if not 0.3 <= f.time <= 0.6]
    assert kept == want and len(kept) < len(plain.frames("train"))
    for s in ("val", "test"):
        _same_split(plain.frames(s), sc.frames(s))
    st = sc.meta["stress"]
    assert st["train_frames"]["dropped_window"] == len(plain.frames("train")) - len(kept)
    assert st["keys"]["drop_times"] == [0.3, 0.6]


def test_keep_fraction_is_exact_seeded_and_reproducible(tmp_path, plain):
    n = len(plain.frames("train"))
    a = _scene(tmp_path, ["data.stress.keep_fraction=0.25"], seed=0)
    b = _scene(tmp_path, ["data.stress.keep_fraction=0.25"], seed=0)
    c = _scene(tmp_path, ["data.stress.keep_fraction=0.25"], seed=1)
    d = _scene(tmp_path, ["data.stress.keep_fraction=0.25", "data.stress.seed=1"], seed=0)
    names = lambda s: [f.name for f in s.frames("train")]  # noqa: E731
    assert len(names(a)) == round(0.25 * n)
    assert names(a) == names(b) and names(a) != names(c) and names(c) == names(d)
    order = [f.name for f in plain.frames("train")]
    assert [order.index(x) for x in names(a)] == sorted(order.index(x) for x in names(a))  # order kept


def test_sparse_window_thins_only_inside(tmp_path, plain):
    sc = _scene(tmp_path, ["data.stress.sparse_times=[0.5,1.0]", "data.stress.sparse_keep=0.2"])
    out_before = [f.name for f in plain.frames("train") if not 0.5 <= f.time <= 1.0]
    in_before = [f.name for f in plain.frames("train") if 0.5 <= f.time <= 1.0]
    names = [f.name for f in sc.frames("train")]
    assert all(x in names for x in out_before)  # dense part untouched
    inside = [x for x in names if x in in_before]
    assert 0 < len(inside) < 0.6 * len(in_before)


def test_pose_noise_turns_cameras_about_their_centres_and_shifts_them(tmp_path, plain):
    rot = _scene(tmp_path, ["data.stress.pose_rot_deg=3"])
    angles = []
    for a, b in zip(plain.frames("train"), rot.frames("train")):
        Rb = b.camera.R.double()
        assert torch.allclose(Rb @ Rb.T, torch.eye(3, dtype=torch.float64), atol=1e-5)
        assert torch.linalg.det(Rb) == pytest.approx(1.0, abs=1e-5)
        assert torch.allclose(a.camera.center.double(), b.camera.center.double(), atol=1e-4)  # about the centre
        cos = ((a.camera.R.double().T @ Rb).trace() - 1) / 2
        angles.append(float(np.degrees(np.arccos(np.clip(float(cos), -1, 1)))))
    # |N(0, 3 deg)| has mean 3 * sqrt(2 / pi) = 2.39 deg; 40 cameras
    assert 1.4 < np.mean(angles) < 3.4
    assert rot.meta["stress"]["pose_noise"]["rotation_deg_mean"] == pytest.approx(np.mean(angles), abs=0.05)
    sh = _scene(tmp_path, ["data.stress.pose_trans=0.1"])
    r = sh.meta["stress"]["pose_noise"]["scene_radius"]
    d = [float((a.camera.center.double() - b.camera.center.double()).norm())
         for a, b in zip(plain.frames("train"), sh.frames("train"))]
    assert 0.6 * 0.1 * r < np.sqrt(np.mean(np.square(d))) < 1.4 * 0.1 * r
    for a, b in zip(plain.frames("train"), sh.frames("train")):
        assert torch.allclose(a.camera.R, b.camera.R)  # no rotation asked for


def test_time_jitter_stays_in_range_and_spares_evaluation(tmp_path, plain):
    sc = _scene(tmp_path, ["data.stress.time_jitter=0.05"])
    t0 = np.array([f.time for f in plain.frames("train")])
    t1 = np.array([f.time for f in sc.frames("train")])
    assert (t1 >= 0).all() and (t1 <= 1).all() and not np.array_equal(t0, t1)
    assert np.abs(t1 - t0).max() < 0.3
    _same_split(plain.frames("test"), sc.frames("test"))


@pytest.mark.parametrize("override,match", [
    ("data.stress.keep_fraction=0", "keep_fraction"), ("data.stress.keep_fraction=1.5", "keep_fraction"),
    ("data.stress.drop_times=[0.6,0.3]", "drop_times"), ("data.stress.drop_times=[0.2]", "drop_times"),
    ("data.stress.sparse_keep=2", "sparse_keep"), ("data.stress.pose_rot_deg=-1", "pose_rot_deg"),
    ("data.stress.drop_times=[0.0,1.0]", "leaves 0 of 40 training frames")])
def test_bad_stress_keys_are_named(tmp_path, override, match):
    with pytest.raises(ValueError, match=match):
        _scene(tmp_path, [override])


@pytest.mark.slow
def test_a_stressed_run_records_the_stress_and_keeps_the_cap(tmp_path):
    from stdr.train.run import run_training as run
    cfg = tiny_config(tmp_path, ["optim.iterations=60", "baseline.warmup=20", "densify.refine_start=5",
                                 "densify.refine_every=5", "densify.grow_grad2d=1e-7", "densify.max_gaussians=1600",
                                 "train.checkpoint_every=0", "train.eval_at_warmup_end=false",
                                 "data.stress.drop_times=[0.4,0.7]", "data.stress.pose_rot_deg=2",
                                 "data.stress.pose_trans=0.05", "eval.fps_repeats=1"])
    run(cfg, tmp_path / "stressed")
    m = json.loads((tmp_path / "stressed" / "metrics.json").read_text())["test"]
    st = m["data"]["stress"]
    assert st["keys"]["drop_times"] == [0.4, 0.7] and st["train_frames"]["dropped_window"] > 0
    assert st["pose_noise"]["rotation_deg_max"] > 0
    g = m["guard"]
    # densification wanted to grow (every seen Gaussian passes the gradient threshold), the cap held
    assert g["max_gaussians"] == 1600 and 1500 < g["peak_gaussians"] <= 1600
    assert m["num_gaussians"] <= 1600
    assert g["peak_memory_mb"] > 50 and m["conventions"]["memory"].startswith("resident set")  # recorded
