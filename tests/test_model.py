"""The model object (stdr.model) and the plug-in protocol (stdr.plugins), apart from STDR."""
import json

import pytest
import torch

from stdr.testing import tiny_config as _tiny

from dataclasses import dataclass

from stdr.model import load_model
from stdr.plugins import PLUGINS, Conditioner, Densifying, Plugin, Reporting, register_plugin, unregister_plugin

SCHED = ["optim.iterations=40", "baseline.warmup=10", "densify.refine_start=5", "densify.refine_every=5",
         "densify.reset_every=0", "train.checkpoint_every=0", "train.eval_at_warmup_end=false",
         "train.log_every=5"]


class Tagger(Conditioner, Densifying, Reporting, Plugin):
    """A toy plug-in: one per-Gaussian tag (lr 0.01), a conditioning of width 2 from a small net
    on its own lr schedule, an opacity factor of sigmoid(tag), and a loss pulling tags to 1."""

    name = "tagger"
    made: list = []  # every instance, for the tests

    @classmethod
    def from_config(cls, pcfg, cfg, schedule, train_times, device):
        p = cls(cfg.baseline.warmup, cfg.optim.iterations, pcfg.lr)
        cls.made.append(p)
        return p

    def __init__(self, warmup: int, iterations: int, lr: float = 0.01):
        self.net = torch.nn.Linear(1, 2)
        self.warmup, self.iterations, self.lr = warmup, iterations, lr
        self.calls: dict[str, int] = {}

    def _count(self, k):
        self.calls[k] = self.calls.get(k, 0) + 1

    @property
    def cond_dim(self):
        return 2

    def init_gaussians(self, params):
        params["tag"] = torch.nn.Parameter(torch.zeros(params["means"].shape[0], 1))

    def param_groups(self):
        return [{"key": "tag", "lr": self.lr},
                {"params": list(self.net.parameters()), "name": "tagger_net", "lr_init": 1e-2, "lr_final": 1e-4,
                 "lr_max_steps": self.iterations - self.warmup, "lr_delay": self.warmup}]

    def modules(self):
        return [self.net]

    def before_step(self, ctx):
        self._count("before_step")

    def conditioning(self, ctx):
        self._count("conditioning")
        return self.net(ctx.params["tag"]), None

    def opacity_factor(self, ctx):
        return torch.sigmoid(ctx.params["tag"][:, 0])

    def regularizers(self, ctx):
        return {"pull": ((ctx.params["tag"] - 1.0) ** 2).mean()}

    def prune_factor(self, ctx):
        self._count("prune_factor")
        return None

    def state_dict(self):
        return {"net": self.net.state_dict()}

    def load_state_dict(self, state, params):
        self.net.load_state_dict(state["net"])

    def stats(self, params):
        return {"tag_mean": float(params["tag"].detach().mean())}


@dataclass
class TaggerConfig:
    enabled: bool = False
    lr: float = 0.01   # of the per-Gaussian tags


@pytest.fixture
def tagger():
    """Tagger registered for the test (`tagger=on`, experiments `<data>_<baseline>_tagger`)."""
    Tagger.made.clear()
    spec = register_plugin("tagger", Tagger, TaggerConfig, label="+tag",
                           row_tags=lambda pcfg: [f"lr {pcfg['lr']}"] if pcfg["lr"] != 0.01 else [])
    yield spec
    unregister_plugin("tagger")
    from stdr.store import experiment_names
    assert "tagger" not in PLUGINS and not any("tagger" in e for e in experiment_names())


@pytest.mark.slow
def test_a_plugin_trains_through_the_hooks_alone(tmp_path, tagger):
    from stdr.train.trainer import Trainer
    t = Trainer(_tiny(tmp_path, SCHED + ["experiment=embedded_deform", "tagger=on"]), tmp_path / "run",
                splits=("train", "test"))
    p = t.state.model.plugin("tagger")
    assert p is Tagger.made[-1] and t.state.model.deform.cond_dim == 2   # the network is built for its conditioning
    n0 = t.state.model.num_gaussians
    logs = None
    for _ in range(40):
        logs = t.train_step()
    # per-Gaussian state stays aligned through densification, and trains at its own lr
    assert t.state.model.num_gaussians != n0 and t.state.model.params["tag"].shape == (t.state.model.num_gaussians, 1)
    assert t.state.optimizers["tag"].param_groups[0]["lr"] == 0.01
    assert float(t.state.model.params["tag"].detach().mean()) > 0.0  # pulled towards 1
    assert "tagger_pull" in logs["losses"]
    assert p.calls["before_step"] == 40 and p.calls["conditioning"] >= 30 and p.calls["prune_factor"] > 0
    # its network group follows its own schedule from its delay, not the deformation's
    lrs = {g["name"]: g["lr"] for g in t.state.net_opt.param_groups}
    assert lrs["tagger_net"] == pytest.approx(1e-4 * (1e-2 / 1e-4) ** (1 / 30), rel=1e-6)  # step 39 of 10..40
    assert lrs["tagger_net"] != pytest.approx(lrs["deform"])
    from stdr.train.optim import update_lrs
    update_lrs(t.cfg, t.state, t.net_groups, 10)
    assert {g["name"]: g["lr"] for g in t.state.net_opt.param_groups}["tagger_net"] == pytest.approx(1e-2)
    # statistics under its name in metrics.json
    res = t.evaluate_final("test")
    assert json.loads((tmp_path / "run" / "metrics.json").read_text())["test"]["tagger"]["tag_mean"] == \
        res["tagger"]["tag_mean"]


@pytest.mark.slow
def test_the_model_reloads_alone_and_renders_what_training_rendered(tmp_path, tagger):
    from stdr.train.trainer import Trainer
    t = Trainer(_tiny(tmp_path, SCHED + ["experiment=embedded_4dgs_tagger", "baseline.hexplane.base_res=16"]),
                tmp_path / "run", splits=("train", "test"))
    t.train()
    ck = tmp_path / "run" / "checkpoints" / "last.pt"
    m = load_model(ck, device="cpu")   # config, training times and background from the checkpoint
    assert m.step == 40 and m.num_gaussians == t.state.model.num_gaussians and m.plugin("tagger") is not None
    f = t.scene.frames("test")[0]
    t.state.model.eval()
    a = t.state.model.render(f.camera, f.time).image
    b = m.render(f.camera, f.time).image
    assert torch.equal(a, b)
    # the same file after DynamicGaussians.save (no optimizer state)
    m.save(tmp_path / "model.pt")
    assert torch.equal(load_model(tmp_path / "model.pt", device="cpu").render(f.camera, f.time).image, a)
    # a model built without the plug-in refuses the checkpoint, naming why
    from stdr.store import load_config
    off = load_config(t.cfg)
    off.tagger.enabled = False
    with pytest.raises(ValueError, match="saved with plug-ins \\['tagger'\\] but this model has none"):
        load_model(ck, device="cpu", cfg=off)
    # and with the plug-in unregistered, its config section is an error that says what to do
    unregister_plugin("tagger")
    with pytest.raises(ValueError, match=r"unknown config section\(s\) \['tagger'\].*register"):
        load_model(ck, device="cpu")


def test_model_without_training_times_is_refused_for_4dgs(tmp_path):
    from stdr.model import build_model
    cfg = _tiny(tmp_path, ["experiment=embedded_4dgs"])
    with pytest.raises(ValueError, match="time_res"):
        build_model(cfg, None, torch.ones(3), torch.device("cpu"))


@pytest.mark.slow
def test_a_plugin_registered_here_trains_through_stdr_train_shows_in_stdr_eval_and_reloads(
        tmp_path, tagger, monkeypatch, capsys):
    """No edit to stdr: the test registers the plug-in and its config dataclass, and the CLIs
    take it from there (typed keys, derived experiment, label with its row tag, checkpoint)."""
    import sys
    from stdr.cli import eval as eval_cli, train as train_cli
    from stdr.testing import TINY_SCENE
    run = tmp_path / "run"
    monkeypatch.setattr(sys, "argv", ["stdr-train", "experiment=embedded_deform_tagger", "tagger.lr=0.02",
                                      *SCHED, *TINY_SCENE, f"data.cache_dir={tmp_path / 'cache'}", "device=cpu",
                                      "model.init_num=1500", "eval.lpips=false", "train.progress=false",
                                      "eval.save_images=false", "train.image_every=0", f"hydra.run.dir={run}"])
    train_cli.main()
    out = capsys.readouterr().out
    assert "| deform+tag lr 0.02 |" in out  # stdr-train's own one-row table
    m = json.loads((run / "metrics.json").read_text())["test"]
    assert m["tagger"]["tag_mean"] > 0.0  # pulled towards 1 from 0
    assert Tagger.made[0].lr == 0.02  # the typed key reached the plug-in
    monkeypatch.setattr(sys, "argv", ["stdr-eval", str(run), f"out={tmp_path / 'table'}", "eval.lpips=false",
                                      "eval.save_images=false"])
    eval_cli.main()
    out = capsys.readouterr().out
    assert "| deform+tag lr 0.02 |" in out
    table = json.loads((tmp_path / "table" / "table.json").read_text())
    assert table["methods"] == ["deform+tag lr 0.02"]
    assert table["cells"]["deform+tag lr 0.02"]["embedded"]["psnr"] == pytest.approx(m["psnr"], abs=1e-4)
    model = load_model(run / "checkpoints" / "last.pt", device="cpu")
    assert model.plugin("tagger").lr == 0.02 and "tag" in model.params
