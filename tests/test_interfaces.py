"""The extension interfaces themselves: small (at most 12 public members each for Deformation and
Plugin), a minimal baseline of 2 methods and a minimal plug-in of 2 that train, and one typed
context (stdr.context.StepContext) that every training hook gets, filled as the step goes."""
from dataclasses import dataclass, field

import pytest
import torch
from torch import nn

from stdr.baselines import BaselineConfig, Deformation, Deltas, register_baseline, unregister_baseline
from stdr.context import DEFORMING, STATIC, StepContext
from stdr.plugins import Conditioner, Densifying, Plugin, Reporting, register_plugin, unregister_plugin
from stdr.testing import tiny_config

SCHED = ["optim.iterations=24", "baseline.warmup=8", "densify.refine_start=4", "densify.refine_every=4",
         "densify.reset_every=0", "train.checkpoint_every=0", "train.eval_at_warmup_end=false"]


def public_members(cls: type) -> set[str]:
    """What the class body itself defines that a subclass or caller sees (no leading underscore)."""
    return {k for k in vars(cls) if not k.startswith("_")}


@pytest.mark.parametrize("cls", [Deformation, Plugin])
def test_each_interface_defines_at_most_twelve_public_members(cls):
    members = public_members(cls)
    assert len(members) <= 12, sorted(members)


def test_the_roles_are_apart_from_the_plugin_and_hooks_share_one_name_per_role():
    """Conditioning, densification and reporting are roles a plug-in adds (not members of Plugin);
    baselines and plug-ins name their common roles alike."""
    for role in (Conditioner, Densifying, Reporting):
        assert not public_members(role) & public_members(Plugin), role
    shared = {"init_gaussians", "param_groups", "before_step", "regularizers", "stages"}
    assert shared <= public_members(Deformation) and shared <= public_members(Plugin)


# ------------------------------------------------------------------ minimal forms that train
@dataclass
class DriftOptions:
    speed: float = 0.01


@dataclass
class DriftConfig(BaselineConfig):
    name: str = "mindrift"
    mindrift: DriftOptions = field(default_factory=DriftOptions)


class MinDrift(Deformation):
    """A minimal baseline: its constructor, config_kwargs and forward."""

    def __init__(self, speed: float = 0.01):
        super().__init__()
        self.v = nn.Parameter(torch.tensor([speed, 0.0, 0.0]))

    @classmethod
    def config_kwargs(cls, b, cond_dim=0, train_times=None, seed=0, schedule=None):
        return {"speed": b.mindrift.speed}

    def forward(self, params, t, cond=None):
        return Deltas(means=(float(t) * self.v).expand_as(params["means"]))


@dataclass
class SeeConfig:
    enabled: bool = False
    weight: float = 0.1


class See(Plugin):
    """A minimal plug-in: from_config and one hook. It records the contexts it is handed."""

    name = "see"
    seen: list = []

    @classmethod
    def from_config(cls, pcfg, cfg, schedule, train_times, device):
        p = cls()
        p.weight = float(pcfg.weight)
        return p

    def regularizers(self, ctx):
        See.seen.append(ctx)
        return {"pull": -self.weight * ctx.params["opacities"].mean()}


def _own_methods(cls: type) -> set[str]:
    """The methods the class body defines."""
    return {k for k, v in vars(cls).items() if callable(v) or isinstance(v, classmethod)}


@pytest.fixture
def minimal():
    register_baseline("mindrift", MinDrift, DriftConfig)
    register_plugin("see", See, SeeConfig, label="+see")
    See.seen.clear()
    yield
    unregister_plugin("see")
    unregister_baseline("mindrift")


def test_a_minimal_baseline_and_a_minimal_plugin_train_and_the_hooks_get_one_filled_context(tmp_path, minimal):
    from stdr.train.trainer import Trainer

    assert _own_methods(MinDrift) == {"__init__", "config_kwargs", "forward"}
    assert _own_methods(See) == {"from_config", "regularizers"}
    t = Trainer(tiny_config(tmp_path, SCHED + ["baseline=mindrift", "see=on"]), tmp_path / "run", splits=("train",))
    v0 = t.state.model.deform.v.detach().clone()
    logs = [t.train_step() for _ in range(12)]
    assert "see_pull" in logs[-1]["losses"]  # the plug-in's term, added to the loss from step 0
    assert not torch.equal(t.state.model.deform.v.detach(), v0)  # the baseline's network trains after the warm-up
    ctxs = See.seen
    assert len(ctxs) == 12 and all(isinstance(c, StepContext) for c in ctxs)
    assert [c.step for c in ctxs] == list(range(12))
    assert [c.phase for c in ctxs] == [STATIC] * 8 + [DEFORMING] * 4
    frames = t.scene.frames("train")
    for c in ctxs:
        assert c.params is t.state.model.params and c.warmup_end == 8
        assert c.t in {f.time for f in frames} and c.camera is not None
        assert c.render is not None and c.render.image.shape[-1] == 3
        assert c.deformed is not None and c.deformed.means.shape[0] == c.render.radii.shape[0]
        assert c.cond is None  # no plug-in feeds a conditioning


def test_a_capability_declared_wrongly_fails_at_registration_naming_the_class_and_hook():
    class Mixer(MinDrift):
        capabilities = frozenset({"mixes_rows"})
    with pytest.raises(TypeError, match="Mixer declares 'mixes_rows' but does not override forward_rows"):
        register_baseline("mindrift", Mixer, DriftConfig)


# ------------------------------------------------------------------ loud at registration
@pytest.mark.parametrize("body, says", [
    ({"configure_step": lambda self, params, step: None}, r"Old.configure_step is not part of the interface any "
                                                          r"more: before_step\(ctx\) replaced"),
    ({"gaussian_lr": lambda self, key: None}, r"Old.gaussian_lr is not part of .*param_groups"),
    ({"regularizers": lambda self, params, step: {}}, r"Old.regularizers\(params, step\) must take the step's "
                                                      r"context: def regularizers\(self, ctx\)"),
    ({"conditioning": lambda self, ctx: (None, None)}, r"Old defines conditioning of the Conditioner role but does "
                                                       r"not take the role.*class Old\(Conditioner, Plugin\)"),
    ({"stats": lambda self, params: {}}, r"Old defines stats of the Reporting role"),
])
def test_a_plugin_written_for_another_interface_is_refused_at_registration(body, says):
    old = type("Old", (Plugin,), {"name": "old", "from_config": classmethod(lambda cls, *a: cls()), **body})
    with pytest.raises(TypeError, match=r"^register_plugin\('old'\): " + says):
        register_plugin("old", old, SeeConfig)


def test_a_plugin_that_takes_its_roles_registers():
    class Ok(Conditioner, Densifying, Reporting, Plugin):
        name = "ok"
        from_config = classmethod(lambda cls, *a: cls())

        def conditioning(self, ctx):
            return None, None

        def reset_opacity(self, ctx, value):
            return False
    register_plugin("ok", Ok, SeeConfig)
    unregister_plugin("ok")


@pytest.mark.parametrize("body, says", [
    ({"gaussian_params": lambda self, n: {}}, r"Old.gaussian_params is not part of the interface any more: "
                                              r"init_gaussians\(params\) adds"),
    ({"takes_conditioning": True}, r"Old.takes_conditioning is not .*capabilities = frozenset"),
    ({"before_step": lambda self, params, step, cond=None: None}, r"Old.before_step\(params, step, cond\) must take "
                                                                  r"the step's context"),
])
def test_a_baseline_written_for_another_interface_is_refused_at_registration(body, says):
    old = type("Old", (MinDrift,), body)
    with pytest.raises(TypeError, match=r"^register_baseline\('olddrift'\): " + says):
        register_baseline("olddrift", old, DriftConfig)
