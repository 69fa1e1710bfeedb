"""baseline.compile: the deformation MLP through torch.compile, an option (off by default)."""
import numpy as np
import pytest
import torch
from stdr.baselines import DeformMLP


def _mlp(seed=0, cond_dim=0):
    torch.manual_seed(seed)
    return DeformMLP(depth=4, width=32, skips=(1,), xyz_freqs=4, t_freqs=3, time_out=8, cond_dim=cond_dim)


@pytest.mark.slow
def test_the_compiled_trunk_matches_the_eager_one_forward_and_backward():
    eager, comp = _mlp(cond_dim=5), _mlp(cond_dim=5)
    comp.compile_network()
    assert comp._compiled is not None and eager._compiled is None
    g = torch.Generator().manual_seed(1)
    for n in (50, 73):  # a new Gaussian count reuses the dynamic-shape graph
        xyz, cond = torch.rand(n, 3, generator=g), torch.rand(n, 5, generator=g)
        w = torch.randn(n, 32, generator=g)
        outs = []
        for m in (eager, comp):
            m.zero_grad(set_to_none=True)
            c = cond.clone().requires_grad_(True)
            h = m.trunk(xyz, 0.37, c)
            (h * w).sum().backward()
            outs.append((h.detach(), c.grad, [p.grad for p in m.parameters()]))
        (h0, c0, g0), (h1, c1, g1) = outs
        assert h0.abs().max() > 0
        assert torch.allclose(h0, h1, rtol=1e-5, atol=1e-6)
        assert torch.allclose(c0, c1, rtol=1e-4, atol=1e-6)
        assert [a is None for a in g0] == [b is None for b in g1]  # the heads are not in the trunk
        assert sum(a is not None for a in g0) > 4
        for a, b in zip(g0, g1):
            assert a is None or torch.allclose(a, b, rtol=1e-4, atol=1e-6)


@pytest.mark.slow
def test_compiled_training_is_deterministic_on_the_cpu(tmp_path):
    from stdr.testing import tiny_config
    from stdr.train.trainer import Trainer
    sched = ["optim.iterations=12", "baseline.warmup=2", "densify.refine_start=4", "densify.refine_every=4",
             "train.checkpoint_every=0", "train.eval_at_warmup_end=false", "baseline.compile=true"]
    runs = []
    for name in ("a", "b"):
        tr = Trainer(tiny_config(tmp_path, sched), tmp_path / name)
        assert tr.state.model.deform._compiled is not None
        tr.train()
        runs.append(tr)
    a, b = runs
    assert a.state.model.params.keys() == b.state.model.params.keys()
    for k in a.state.model.params:
        assert torch.equal(a.state.model.params[k], b.state.model.params[k]), k
    for (ka, va), (kb, vb) in zip(a.state.model.deform.state_dict().items(), b.state.model.deform.state_dict().items()):
        assert torch.equal(va, vb), ka


def test_every_mlp_baseline_has_the_option_and_4dgs_names_the_key(tmp_path):
    from stdr.store import compose_config
    from stdr.baselines.registry import build_deformation
    for exp, trunk in (("embedded_deform", lambda m: m), ("embedded_scgs", lambda m: m.net),
                       ("embedded_spgs", lambda m: m.net)):
        cfg = compose_config([f"experiment={exp}", "baseline.compile=true"])
        assert trunk(build_deformation(cfg.baseline))._compiled is not None, exp
        assert trunk(build_deformation(compose_config([f"experiment={exp}"]).baseline))._compiled is None, exp
    times = np.linspace(0.0, 1.0, 10)
    with pytest.raises(ValueError, match="baseline.compile=true"):
        build_deformation(compose_config(["experiment=embedded_4dgs", "baseline.compile=true"]).baseline,
                          train_times=times)
    build_deformation(compose_config(["experiment=embedded_4dgs"]).baseline, train_times=times)  # off: builds
