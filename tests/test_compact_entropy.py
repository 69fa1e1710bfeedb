"""Entropy coding of the compact file's streams (stdr.compression.entropy): lossless, smaller where a
stream has redundancy, and a file with it loads to the same model as one without."""
import pytest
import torch
from hypothesis import given, settings, strategies as st

from stdr.compression import entropy

pytest.importorskip("zstandard")


def test_a_smooth_grid_plane_is_delta_coded_and_comes_back_exact():
    """A smooth 8-bit plane (a ramp plus small steps, wrapping through 0 and 255) packs into far
    fewer bytes with the row-difference filter, and unpacks bit for bit."""
    g = torch.Generator().manual_seed(0)
    steps = torch.randint(-2, 3, (256, 64, 8), generator=g)
    plane = (torch.cumsum(steps, 0) + 250).remainder(256).to(torch.uint8)  # crosses 255 -> 0 and back
    e = entropy.pack(plane)
    assert isinstance(e, dict) and e["delta"] and e["zstd"].numel() < plane.numel() // 3
    back = entropy.unpack(e)
    assert back.dtype == torch.uint8 and torch.equal(back, plane)


def test_floats_are_byte_shuffled_and_exact():
    g = torch.Generator().manual_seed(1)
    for t in (torch.randn(2000, 3, generator=g).half(), torch.randn(500, 7, generator=g) * 1e-3):
        e = entropy.pack(t)
        assert isinstance(e, dict) and e["shuffle"] == t.element_size() and not e["delta"]
        assert e["zstd"].numel() < t.numel() * t.element_size()
        back = entropy.unpack(e)
        assert back.dtype == t.dtype and torch.equal(back, t)


def test_a_stream_that_would_not_shrink_stays_a_tensor():
    g = torch.Generator().manual_seed(2)
    noise = torch.randint(0, 256, (400, 16), dtype=torch.uint8, generator=g)  # incompressible
    assert entropy.pack(noise) is noise
    tiny = torch.tensor([1.5])
    assert entropy.pack(tiny) is tiny


@settings(max_examples=60, deadline=None)
@given(dtype=st.sampled_from([torch.uint8, torch.int16, torch.int32, torch.float16, torch.float32, torch.float64]),
       shape=st.lists(st.integers(1, 12), min_size=0, max_size=3), seed=st.integers(0, 2 ** 16),
       levels=st.integers(1, 300))
def test_any_stream_round_trips_exactly(dtype, shape, seed, levels):
    """Whatever a codec hands over (any dtype, any shape, few or many distinct values), unpack(pack(x))
    is x, dtype and shape included."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randint(0, levels, shape or [1], generator=g)
    if dtype.is_floating_point:
        x = (x.double() / 7.0 - 3.0).to(dtype)
    else:
        x = (x - levels // 2).to(dtype) if dtype != torch.uint8 else x.remainder(256).to(dtype)
    x = x.reshape(shape)
    e = entropy.pack_tree({"a": [x, {"b": x}]})
    back = entropy.unpack_tree(e)
    for y in (back["a"][0], back["a"][1]["b"]):
        assert y.dtype == x.dtype and y.shape == x.shape and torch.equal(y, x)


@pytest.mark.slow
def test_a_file_with_entropy_coding_loads_to_the_model_of_the_file_without(tmp_path):
    """A trained model written with the preset's codecs, with and without `entropy: zstd`: the two
    files decode to bit-identical models, and the entropy-coded one is smaller."""
    from stdr.compact.pack import write_compact
    from stdr.model import load_model
    from stdr.testing import tiny_config
    from stdr.train.trainer import Trainer
    cfg = tiny_config(tmp_path, ["experiment=embedded_4dgs_stdr", "model.init_num=400", "optim.iterations=30",
                                 "baseline.warmup=10", "stdr.warmup_end=12", "stdr.freeze_at=20",
                                 "densify.refine_start=1000"])
    t = Trainer(cfg, tmp_path / "run", splits=("train",))
    t.train()
    spec = {"means": "q16", "scales": "q8", "quats": "q8", "opacities": "q8", "sh0": "q8", "shN": "vq:64",
            "state": "f16", "state:grids": "q8"}
    plain = write_compact(t.state.model, tmp_path / "plain.stdrc", {**spec, "entropy": "none"})
    coded = write_compact(t.state.model, tmp_path / "coded.stdrc", {**spec, "entropy": "zstd"})
    assert coded["bytes"] < plain["bytes"] and coded["spec"]["entropy"] == "zstd"
    a, b = load_model(tmp_path / "plain.stdrc", "cpu"), load_model(tmp_path / "coded.stdrc", "cpu")
    sa, sb = a.state_dict(), b.state_dict()
    assert sa["params"].keys() == sb["params"].keys()
    for k in sa["params"]:
        assert torch.equal(sa["params"][k], sb["params"][k]), k
    for (ka, va), (kb, vb) in zip(sa["deform"].items(), sb["deform"].items()):
        assert ka == kb and torch.equal(va, vb), ka


def test_a_bad_entropy_value_is_a_config_error_naming_the_key():
    """stdr-train checks pack.codecs before training: an unknown coder is a ConfigError (one line,
    exit code 2) naming the key and what to write, never a traceback after the run."""
    from stdr.compact.pack import check_pack_config
    from stdr.errors import ConfigError
    from stdr.store import compose_config
    cfg = compose_config(["compact=on", "+pack.codecs.entropy=zz"])
    with pytest.raises(ConfigError, match=r"pack\.codecs: compact spec entropy='zz': use none, zstd or zstd:<level"):
        check_pack_config(cfg)
    assert check_pack_config(compose_config(["compact=on", "+pack.codecs.entropy=zstd:3"]))["entropy"] == "zstd:3"
