"""Fuzzing what a user hands over (Hypothesis): D-NeRF transforms, Nerfies cameras, config
overrides, truncated and foreign checkpoints. Every input ends one of two ways: a correct load (its
values checked here) or a named error, a stdr.errors.UserError whose message names the file or key.
Any other exception is a traceback from our code and fails the test. Derandomized: CI tries the same
inputs every run; `pytest tests/test_fuzz.py -s` prints how many each test tried."""
import io
import json
import math
import shutil

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings, strategies as st

from stdr.errors import UserError

FUZZ = settings(max_examples=300, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
COUNT: dict[str, int] = {}

# any JSON value, including the non-finite numbers Python's json writes (NaN, Infinity)
SCALARS = st.one_of(st.none(), st.booleans(), st.integers(-10**6, 10**6),
                    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=8))
VALUES = st.recursive(SCALARS, lambda inner: st.one_of(st.lists(inner, max_size=5),
                                                       st.dictionaries(st.text(max_size=5), inner, max_size=3)),
                      max_leaves=12)


def _count(name: str) -> None:
    COUNT[name] = COUNT.get(name, 0) + 1


@pytest.fixture(scope="module", autouse=True)
def _report():
    yield
    print(f"\n[fuzz] inputs tried: {COUNT} (total {sum(COUNT.values())})")


def _mutate(doc, path, value, delete):
    """doc with the entry at `path` (keys / indices, taken modulo what exists) set or deleted."""
    node = doc
    for i, k in enumerate(path):
        last = i == len(path) - 1
        if isinstance(node, dict) and node:
            key = sorted(node)[k % len(node)] if isinstance(k, int) else k
        elif isinstance(node, list) and node:
            key = k % len(node) if isinstance(k, int) else 0
        else:
            return doc
        if last or not isinstance(node[key], (dict, list)):
            if delete and isinstance(node, dict):
                del node[key]
            elif delete and isinstance(node, list):
                node.pop(key)
            else:
                node[key] = value
            return doc
        node = node[key]
    return doc


PATHS = st.lists(st.integers(0, 30), min_size=1, max_size=5)


# ------------------------------------------------------------------ D-NeRF transforms
@pytest.fixture(scope="module")
def dnerf_scene(tmp_path_factory):
    from stdr.data.procedural import SceneOptions, generate_scene
    return generate_scene(tmp_path_factory.mktemp("fz") / "scene", SceneOptions(resolution=16, n_train=4, n_val=1,
                                                                                 n_test=1))


@FUZZ
@given(path=PATHS, value=VALUES, delete=st.booleans())
def test_dnerf_transforms_load_correctly_or_name_the_problem(dnerf_scene, path, value, delete):
    from stdr.data.dnerf import load_dnerf
    _count("dnerf transforms")
    good = json.loads((dnerf_scene / "transforms_train.json").read_text())
    doc = _mutate(json.loads(json.dumps(good)), path, value, delete)
    (dnerf_scene / "transforms_train.json").write_text(json.dumps(doc))
    try:
        scene = load_dnerf(dnerf_scene, ["train"])
    except UserError as e:
        assert "transforms_train.json" in str(e) or str(dnerf_scene) in str(e), str(e)
        return
    finally:
        (dnerf_scene / "transforms_train.json").write_text(json.dumps(good))
    for f in scene.frames("train"):  # a load is a correct one: every value the run reads is sane
        assert 0.0 <= f.time <= 1.0
        c = f.camera
        assert torch.isfinite(c.R).all() and torch.isfinite(c.t).all() and c.fx > 0 and c.fy > 0
        assert torch.allclose(c.R @ c.R.T, torch.eye(3, dtype=c.R.dtype), atol=1e-2)


# ------------------------------------------------------------------ Nerfies cameras
@pytest.fixture(scope="module")
def nerfies_scene(tmp_path_factory):
    from test_nerfies import make_scene
    root = tmp_path_factory.mktemp("fzn") / "scene"
    make_scene(root, n=4, size=(16, 12), scales=(1,))
    return root


@FUZZ
@given(which=st.integers(0, 3), path=st.lists(st.integers(0, 30), min_size=1, max_size=3), value=VALUES,
       delete=st.booleans())
def test_nerfies_cameras_load_correctly_or_name_the_problem(nerfies_scene, which, path, value, delete):
    from stdr.data.nerfies import load_nerfies
    _count("nerfies camera")
    cams = sorted((nerfies_scene / "camera").glob("*.json"))
    target = cams[which % len(cams)]
    good = target.read_text()
    doc = _mutate(json.loads(good), path, value, delete)
    target.write_text(json.dumps(doc))
    try:
        scene = load_nerfies(nerfies_scene, ("train", "test"), split_mode="ids", image_scale=1, cache_dir=None,
                             distortion="ignore")
    except UserError as e:
        assert target.name in str(e) or str(nerfies_scene) in str(e), str(e)
        return
    finally:
        target.write_text(good)
    for split in ("train", "test"):
        for f in scene.frames(split):
            c = f.camera
            assert torch.isfinite(c.R).all() and torch.isfinite(c.t).all() and c.fx > 0 and c.fy > 0
            assert 0 <= c.cx <= c.width and 0 <= c.cy <= c.height


# ------------------------------------------------------------------ config overrides
KEYS = ["optim.iterations", "data.max_width", "data.resolution_scale", "densify.refine_every", "densify.prune_opa",
        "densify.prune_scale2d", "model.sh_degree", "train.stop_at", "eval.fps_repeats", "optim.lambda_dssim",
        "render.near", "prune.share", "train.guard.lr_factor", "data.eval_split", "seed", "model.init_opacity"]
TEXT_VALUES = st.one_of(st.integers(-5, 5).map(str), st.sampled_from(["0", "-1", "nan", "inf", "-inf", "1e9", "0.5",
                                                                      "null", "abc", "1.5", "[]", "true"]))


@settings(max_examples=100, deadline=None, derandomize=True, database=None)
@given(pairs=st.lists(st.tuples(st.sampled_from(KEYS + ["optim.iteratons", "densify.prune_opaa"]), TEXT_VALUES,
                                st.booleans()), min_size=1, max_size=3))
def test_config_overrides_compose_to_a_checked_config_or_one_named_error(pairs):
    """An override is either refused (Hydra's composition error, or stdr's ConfigError naming the key)
    or gives a config every one of whose checked values is in range (never a silent bad value)."""
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from stdr.store import compose_config
    from stdr.errors import ConfigError
    from stdr.validate import KINDS, RULES, check_run_config
    _count("config overrides")
    overrides = [("+" if plus else "") + f"{k}={v}" for k, v, plus in pairs]
    try:
        cfg = compose_config(overrides)
    except (HydraException, OmegaConfBaseException):
        return  # stdr-train reports these in one line (stdr.cli.common.check_overrides)
    try:
        check_run_config(cfg)
    except ConfigError as e:
        assert any(k.split(".")[0] in str(e) for k, _, _ in pairs) or "unknown config" in str(e), str(e)
        return
    for key, kind in RULES.items():
        node, ok = cfg, True
        for part in key.split("."):
            if part not in node:
                ok = False
                break
            node = node[part]
        if ok:
            assert KINDS[kind][0](node), (key, node)
    for v in (cfg.optim.lambda_dssim, cfg.data.resolution_scale, cfg.render.near):
        assert math.isfinite(v)


# ------------------------------------------------------------------ checkpoints
@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    from stdr.io.checkpoint import save_checkpoint
    path = tmp_path_factory.mktemp("fzc") / "last.pt"
    save_checkpoint(path, {"model": {"step": 3, "params": {"means": torch.randn(20, 3)}}, "optimizers": {}})
    return path


@FUZZ
@given(cut=st.integers(0, 4000), flips=st.lists(st.tuples(st.integers(0, 10**6), st.integers(1, 255)), max_size=3),
       foreign=st.sampled_from([None, "path", "ndarray", "text"]))
def test_damaged_or_foreign_checkpoints_are_named(checkpoint, tmp_path_factory, cut, flips, foreign):
    from stdr.io.checkpoint import CheckpointError, load_checkpoint
    _count("checkpoints")
    raw = bytearray(checkpoint.read_bytes())
    if foreign == "path":  # another program's pickle: objects torch will not load without running code
        b = io.BytesIO()
        torch.save({"x": shutil.Error("x")}, b)
        raw = bytearray(b.getvalue())
    elif foreign == "ndarray":
        b = io.BytesIO()
        torch.save({"x": np.zeros(3, dtype=object)}, b)
        raw = bytearray(b.getvalue())
    elif foreign == "text":
        raw = bytearray(b"# not a checkpoint\n" * 10)
    for pos, x in flips:
        raw[pos % len(raw)] ^= x
    if cut and cut < len(raw):
        raw = raw[:cut]
    path = tmp_path_factory.mktemp("c") / "last.pt"
    path.write_bytes(bytes(raw))
    try:
        ck = load_checkpoint(path, require=("model",))
    except CheckpointError as e:
        assert str(path) in str(e) and "weights_only=False" not in str(e), str(e)
        return
    assert foreign is None  # only our own file loads, and then with its own values
    assert ck["model"]["step"] == 3 and ck["model"]["params"]["means"].shape == (20, 3)
