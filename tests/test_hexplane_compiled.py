"""The compiled HexPlane sampling (4dgs's feature field) pinned to its torch twin."""
import pytest
import torch

from stdr.baselines.fourdgs import HexPlaneField
from stdr.verified import VERIFIED
from stdr.baselines import fourdgs as hexplane_mod

BACKENDS = ["cpu"] + (["cuda"] if torch.cuda.is_available() and torch.version.cuda else [])
NO_CUDA = "no CUDA device on this machine (torch.cuda.is_available() is False)"


def _field(dtype, seed=0, base_res=9, multires=(1, 2), channels=5, time_res=7, compiled_=None):
    """A field with random plane values (drawn in float64, so every dtype holds the same ones)."""
    torch.manual_seed(seed)
    f = HexPlaneField(base_res, multires, channels, time_res, compiled=compiled_).double()
    with torch.no_grad():  # values away from the initial ones (time planes start at 1)
        for p in f.parameters():
            p.uniform_(-1.0, 1.5)
    return f.to(dtype)


def _coords(n, dtype, t, seed=1):
    """Points inside, on the edges (-1, 1) and outside [-1, 1]; the time column is 2t - 1."""
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 3, generator=g, dtype=torch.float64) * 2.4 - 1.2
    x[:6] = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0], [1.0, -1.0, 0.0], [0.0, 0.0, 0.0],
                          [-1.3, 0.2, 0.1], [0.5, 1.0000001, -0.99999]], dtype=torch.float64)
    return torch.cat([x, torch.full((n, 1), 2.0 * t - 1.0, dtype=torch.float64)], 1).to(dtype)


def _features_and_grads(field, c, t, kind, weights):
    field.zero_grad(set_to_none=True)
    planes = [p for planes in field.grids for p in planes]
    if kind == "torch":
        out = field.features_torch(c, t)
    else:
        dev = "cuda" if kind == "cuda" else "cpu"
        planes = [p.detach().to(dev).requires_grad_(True) for p in planes]
        out = hexplane_mod.hexplane_compiled(c.to(dev), planes, kind)
    (out * weights.to(out.device, out.dtype)).sum().backward()
    return out.detach().cpu(), [p.grad.detach().cpu() for p in planes]


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-11), (torch.float32, 1e-5)])
@pytest.mark.parametrize("t", [0.0, 0.37, 1.0])
def test_compiled_sampling_matches_the_torch_twin(backend, dtype, tol, t):
    if backend == "cuda" and dtype == torch.float64:
        pytest.skip("the CUDA kernel is float32")
    field = _field(dtype)
    c = _coords(300, dtype, t)
    w = torch.randn(300, field.feat_dim, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    # the oracle: the twin in float64
    f64 = _field(torch.float64)
    ref, ref_g = _features_and_grads(f64, c.double(), t, "torch", w)
    out, grads = _features_and_grads(field, c, t, backend, w)
    scale = ref.abs().max()
    assert scale > 0.1  # the points see the planes
    assert (out.double() - ref).abs().max() <= tol * scale
    assert (out[4] == 0).all()  # x = -1.3: outside every plane that uses x
    for a, b in zip(grads, ref_g):
        assert b.abs().max() > 0
        assert (a.double() - b).abs().max() <= tol * max(1.0, b.abs().max().item())


def test_cpu_backward_is_deterministic_and_pure():
    field = _field(torch.float32, base_res=32, channels=16)
    c = _coords(5000, torch.float32, 0.6)
    w = torch.randn(5000, field.feat_dim, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    a = _features_and_grads(field, c, 0.6, "cpu", w)
    b = _features_and_grads(field, c, 0.6, "cpu", w)
    assert torch.equal(a[0], b[0]) and all(torch.equal(x, y) for x, y in zip(a[1], b[1]))


def test_the_field_uses_it_where_verified_and_the_key_overrides(monkeypatch):
    assert VERIFIED["baseline.hexplane.compiled"] == ("cpu",)  # CUDA: once a GPU check has run these tests there
    c = _coords(50, torch.float32, 0.5)
    calls = []
    real = hexplane_mod.hexplane_compiled
    monkeypatch.setattr(hexplane_mod, "hexplane_compiled", lambda *a, **k: calls.append(a[2]) or real(*a, **k))
    for setting, used in ((None, ["cpu"]), (True, ["cpu"]), (False, [])):
        calls.clear()
        field = _field(torch.float32, compiled_=setting)
        out = field(c[:, :3], 0.75)
        assert calls == used, setting
        ref = field.features_torch(field.normalize(c[:, :3], 0.75), 0.75)
        assert (out - ref).abs().max() <= 1e-5 * ref.abs().max()
    # coordinates that need a gradient take the torch ops, whatever the key
    calls.clear()
    _field(torch.float32, compiled_=True)(c[:, :3].clone().requires_grad_(True), 0.5)
    assert calls == []
    # where it has not been verified, null keeps the torch ops
    monkeypatch.setitem(VERIFIED, "baseline.hexplane.compiled", ())
    assert _field(torch.float32).compiled_kind(c) is None
    assert _field(torch.float32, compiled_=True).compiled_kind(c) == "cpu"


def test_compiled_true_names_the_key_when_it_cannot_run():
    field = _field(torch.float16, compiled_=True)
    with pytest.raises(ValueError, match="baseline.hexplane.compiled"):
        field.compiled_kind(_coords(8, torch.float16, 0.5))


def test_bad_inputs_are_rejected_with_what_is_wrong():
    field = _field(torch.float32)
    planes = [p for planes in field.grids for p in planes]
    c = _coords(10, torch.float32, 0.5)
    with pytest.raises(ValueError, match=r"coords must be \[N, 4\]"):
        hexplane_mod.hexplane_compiled(c[:, :3], planes)
    with pytest.raises(ValueError, match="6 per scale"):
        hexplane_mod.hexplane_compiled(c, planes[:5])
    with pytest.raises(ValueError, match="float64"):
        hexplane_mod.hexplane_compiled(c, [p.double() for p in planes])
    with pytest.raises(ValueError, match=r"C=5"):
        hexplane_mod.hexplane_compiled(c, planes[:-1] + [torch.zeros(4, 3, 3)])


def test_4dgs_trains_with_it_and_the_key_composes(tmp_path, monkeypatch):
    """A 4dgs training step samples its field with the compiled kernel under the default and
    with the torch ops under baseline.hexplane.compiled=false; the losses agree to float rounding."""
    from stdr.testing import tiny_config
    from stdr.train.trainer import Trainer

    calls = []
    real = hexplane_mod.hexplane_compiled
    monkeypatch.setattr(hexplane_mod, "hexplane_compiled", lambda *a, **k: calls.append(a[2]) or real(*a, **k))
    loss = {}
    for setting in ("null", "false"):
        calls.clear()
        cfg = tiny_config(tmp_path / setting, ["experiment=embedded_4dgs", "baseline.warmup=0",
                                               f"baseline.hexplane.compiled={setting}"])
        tr = Trainer(cfg, tmp_path / setting / "run", splits=("train",))
        loss[setting] = float(tr.train_step()["loss"])
        assert calls == (["cpu"] if setting == "null" else []), setting
        assert all(p.grad is None for p in tr.state.model.deform.grid.parameters())  # stepped and cleared
    assert abs(loss["null"] - loss["false"]) <= 1e-6 * abs(loss["false"])


@pytest.mark.skipif("cuda" not in BACKENDS, reason=NO_CUDA)
def test_cuda_hexplane_matches_the_cpu_extension_with_200k_points():
    field = _field(torch.float32, base_res=64, channels=32, time_res=75)
    c = _coords(200_000, torch.float32, 0.3)
    w = torch.randn(200_000, field.feat_dim, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    a = _features_and_grads(field, c, 0.3, "cpu", w)
    b = _features_and_grads(field, c, 0.3, "cuda", w)
    assert (a[0] - b[0]).abs().max() <= 1e-5 * a[0].abs().max()
    for x, y in zip(a[1], b[1]):
        assert (x - y).abs().max() <= 1e-4 * max(1.0, x.abs().max().item())
