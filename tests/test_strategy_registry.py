"""Densification strategies are registered like baselines (stdr.densify.strategy): a second one,
written in this test, becomes `densify=<name>` with typed keys, joins the schedule and trains
through the one loop; the default is unchanged."""
from dataclasses import dataclass

import pytest
import torch

from stdr.densify.strategy import STRATEGIES, DensifyStrategy, get_strategy, register_strategy, unregister_strategy
from stdr.store import resolve_schedule
from stdr.testing import make_cfg, tiny_config


@dataclass
class Thinning(DensifyStrategy):
    """Never grows; every `every` steps removes the `share` of the Gaussians with the lowest opacity."""

    name: str = "thinning"
    every: int = 10
    share: float = 0.1

    @classmethod
    def stages(cls, d):
        return [(int(d.every), "densify.every", "first thinning")], ["thinning: no growth"]

    def step_post_backward(self, params, optimizers, state, step, means2d, radii, width, height, generator=None,
                           opacity_fn=None, reset_fn=None, rows=None, opacities=None):
        from stdr.densify.strategy import remove
        if step % self.every:
            return {}
        n = params["means"].shape[0]
        k = int(n * self.share)
        drop = torch.zeros(n, dtype=torch.bool, device=params["means"].device)
        drop[torch.topk(-params["opacities"].detach().squeeze(-1), k).indices] = True
        remove(params, optimizers, state, drop)
        return {"pruned": k}


@pytest.fixture
def thinning():
    register_strategy("thinning", Thinning)
    yield
    unregister_strategy("thinning")
    assert "thinning" not in STRATEGIES


def test_registration_is_checked():
    @dataclass
    class Unnamed(DensifyStrategy):
        pass

    with pytest.raises(TypeError, match="dataclass subclassing"):
        register_strategy("loose", object)
    with pytest.raises(ValueError, match="Unnamed.name defaults to 'default'; set `name: str = 'x'`"):
        register_strategy("x", Unnamed)
    with pytest.raises(ValueError, match=r"densify.name='nope' is not a registered densification strategy.*default"):
        get_strategy("nope")
    with pytest.raises(Exception, match="nope"):
        make_cfg(["densify=nope"])


def test_a_second_strategy_is_an_option_with_typed_keys_and_stages(thinning):
    cfg = make_cfg(["experiment=dnerf_deform", "data.path=/x", "densify=thinning", "densify.share=0.25"])
    assert cfg.densify.name == "thinning" and cfg.densify.share == 0.25
    assert cfg.densify.refine_stop == 1500  # the budget's shared keys still apply
    with pytest.raises(Exception, match="share"):
        make_cfg(["densify=thinning", "densify.share=lots"])
    with pytest.raises(Exception, match="share"):  # the default strategy has no such key
        make_cfg(["densify.share=0.5"])
    s = resolve_schedule(cfg)
    assert "10  first thinning  [densify.every]" in s.describe() and "thinning: no growth" in s.notes
    assert "densify.refine_start" not in s.describe()  # its stages replace the default's
    from stdr.store import load_config
    from omegaconf import OmegaConf
    assert load_config(OmegaConf.to_container(cfg, resolve=True)).densify.share == 0.25


@pytest.mark.slow
def test_a_second_strategy_trains_through_the_loop(tmp_path, thinning):
    from stdr.train.trainer import Trainer
    t = Trainer(tiny_config(tmp_path, ["experiment=embedded_deform", "densify=thinning", "densify.every=10",
                                       "densify.share=0.1", "optim.iterations=30", "baseline.warmup=10",
                                       "train.checkpoint_every=0", "train.eval_at_warmup_end=false"]),
                tmp_path / "run")
    assert isinstance(t.strategy, Thinning)
    n0 = t.state.model.num_gaussians
    t.train()
    n = n0
    for _ in range(3):  # at 10, 20, 30
        n -= int(n * 0.1)
    assert t.state.model.num_gaussians == n
    assert all(v.shape[0] == n for v in t.state.model.params.values())
