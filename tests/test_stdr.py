"""STDR: mask maths against hand computations, phases in the real training loop, the separated
field, config/table plumbing, exact resume, and the ghosting behaviour it exists for."""
import math

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from stdr.plugins.stdr import StdrConfig
from stdr.plugins.stdr import (MASK_KEY, Phase, SeparatedField, interp_weights, knot_times, mask_at,
                           phase_at, resolve_phases, sample_neighbours, spatial_kl, temporal_entropy,
                           temporal_loss)
from stdr.baselines import DeformMLP
from stdr.eval.table import method_name
from stdr.gaussians import init_params
from stdr.densify.strategy import DensifyStrategy
from stdr.store import resolve_schedule

from stdr.testing import TINY_SCENE, make_cfg
from stdr.baselines.base import deform_gaussians
from stdr.context import StepContext


# ----------------------------------------------------------------------------- the mask maths
def test_interpolation_is_exact_at_knots_and_linear_between():
    knots = torch.tensor([0.0, 0.2, 0.5, 1.0], dtype=torch.float64)
    logits = torch.randn(7, 4, generator=torch.Generator().manual_seed(0))
    a = torch.sigmoid(logits)
    for j, t in enumerate(knots.tolist()):
        assert torch.equal(mask_at(logits, t, knots), a[:, j])
    for t, (j0, j1) in ((0.1, (0, 1)), (0.35, (1, 2)), (0.9, (2, 3))):
        w = (t - knots[j0].item()) / (knots[j1] - knots[j0]).item()
        assert interp_weights(t, knots) == (j0, j1, pytest.approx(w))
        torch.testing.assert_close(mask_at(logits, t, knots), (1 - w) * a[:, j0] + w * a[:, j1])
    # outside the knots: the end columns
    assert torch.equal(mask_at(logits, -0.5, knots), a[:, 0])
    assert torch.equal(mask_at(logits, 1.5, knots), a[:, 3])


def test_the_mask_between_two_knots_by_each_rule():
    """stdr.mask_between: at a knot every rule reads its column; between two, linear mixes the
    activated columns, nearest takes the nearer one, logit activates the mixed logits (an entry on
    at one knot and off at the next: linear holds it at half, logit crosses 1/2 at the middle)."""
    from stdr.plugins.stdr.mask import activated, mask_at
    knots = torch.tensor([0.0, 0.5, 1.0], dtype=torch.float64)
    logits = torch.tensor([[6.0, -6.0, 6.0], [0.0, 2.0, -1.0]])
    a = activated(logits)
    for rule in ("linear", "nearest", "logit"):
        assert torch.equal(mask_at(logits, 0.5, knots, rule), a[:, 1])
    w = 0.3  # t = 0.15: 30 % of the way from knot 0 to knot 1
    torch.testing.assert_close(mask_at(logits, 0.15, knots, "linear"), (1 - w) * a[:, 0] + w * a[:, 1])
    assert torch.equal(mask_at(logits, 0.15, knots, "nearest"), a[:, 0])
    assert torch.equal(mask_at(logits, 0.40, knots, "nearest"), a[:, 1])
    torch.testing.assert_close(mask_at(logits, 0.15, knots, "logit"),
                               torch.sigmoid((1 - w) * logits[:, 0] + w * logits[:, 1]))
    mid_linear, mid_logit = mask_at(logits, 0.25, knots, "linear"), mask_at(logits, 0.25, knots, "logit")
    assert abs(float(mid_linear[0]) - 0.5) < 1e-6 and abs(float(mid_logit[0]) - 0.5) < 1e-6
    assert float(mask_at(logits, 0.2, knots, "logit")[0]) > float(mask_at(logits, 0.2, knots, "linear")[0])
    with pytest.raises(ValueError, match="stdr.mask_between"):
        mask_at(logits, 0.15, knots, "cubic")


def test_knots_are_distinct_training_times_or_bins():
    assert knot_times([0.5, 0.0, 0.5, 1.0]).tolist() == [0.0, 0.5, 1.0]
    assert knot_times([0.5, 0.0], time_bins=5).tolist() == [0.0, 0.25, 0.5, 0.75, 1.0]
    with pytest.raises(ValueError, match="time_bins"):
        knot_times([0.0], time_bins=1)
    with pytest.raises(ValueError, match="time_bins"):
        knot_times([0.0], time_bins=-3)  # not silently treated as 0


def test_temporal_loss_equals_hand_computation_for_both_reductions():
    m = torch.tensor([[0.0, 1.0, -2.0], [3.0, 3.0, 0.5]])
    s = 1 / (1 + np.exp(-m.numpy().astype(np.float64)))
    hand = sum((s[i, t] - s[i, t + 1]) ** 2 for i in range(2) for t in range(2))
    assert temporal_loss(m, "sum").item() == pytest.approx(hand, rel=1e-6)
    assert temporal_loss(m, "mean").item() == pytest.approx(hand / 4, rel=1e-6)
    # the paper's sum grows with N; the mean does not
    assert temporal_loss(m.repeat(5, 1), "sum").item() == pytest.approx(5 * hand, rel=1e-6)
    assert temporal_loss(m.repeat(5, 1), "mean").item() == pytest.approx(hand / 4, rel=1e-6)
    with pytest.raises(ValueError, match="temporal_reduction"):
        temporal_loss(m, "max")


def test_temporal_sum_gives_each_entry_a_gradient_independent_of_n():
    """With the sum, an entry's gradient is 2 (a_t - a_t+1) sigmoid'(m_t) (+ the other side),
    whatever the number of Gaussians; with the mean it shrinks as 1 / (N (K - 1))."""
    row = torch.tensor([[0.0, 1.0, -2.0, 0.5]])
    grads = {}
    for n in (1, 1000):
        for red in ("sum", "mean"):
            m = row.repeat(n, 1).requires_grad_(True)
            temporal_loss(m, red).backward()
            grads[n, red] = m.grad[0].clone()
    a = torch.sigmoid(row[0])
    ds = a * (1 - a)
    hand0 = 2 * (a[0] - a[1]) * ds[0]
    assert grads[1, "sum"][0].item() == pytest.approx(hand0.item(), rel=1e-5)
    torch.testing.assert_close(grads[1000, "sum"], grads[1, "sum"])
    torch.testing.assert_close(grads[1000, "mean"] * 1000 * 3, grads[1, "sum"])


def test_spatial_kl_equals_hand_computation():
    g = torch.Generator().manual_seed(1)
    m = torch.randn(6, 4, generator=g, dtype=torch.float64)
    q = torch.tensor([0, 3])
    nbr = torch.tensor([[1, 2], [5, 0]])
    p = np.exp(m.numpy()) / np.exp(m.numpy()).sum(1, keepdims=True)
    hand = np.mean([sum(p[i, t] * math.log(p[i, t] / p[j, t]) for t in range(4))
                    for i, js in zip(q.tolist(), nbr.tolist()) for j in js])
    assert spatial_kl(m, q, nbr).item() == pytest.approx(hand, rel=1e-9)
    assert spatial_kl(m, q, q[:, None].repeat(1, 2)).item() == pytest.approx(0.0, abs=1e-12)


def test_entropy_is_one_for_uniform_and_zero_for_one_hot():
    m = torch.tensor([[0.0, 0.0, 0.0, 0.0], [100.0, -100.0, -100.0, -100.0]])
    e = temporal_entropy(m)
    assert e[0].item() == pytest.approx(1.0) and e[1].item() == pytest.approx(0.0, abs=1e-6)


def test_sampled_neighbours_equal_brute_force():
    g = torch.Generator().manual_seed(2)
    means = torch.rand(300, 3, generator=g)
    q, nbr = sample_neighbours(means, n_query=40, n_candidates=120, k=5, generator=g)
    assert q.shape == (40,) and nbr.shape == (40, 5)
    cand = torch.unique(torch.cat([q, nbr.flatten()]))
    assert cand.numel() <= 120
    # recover the candidate set: the same draw again
    g2 = torch.Generator().manual_seed(2)
    torch.rand(300, 3, generator=g2)
    cands = torch.randperm(300, generator=g2)[:120]
    for i, row in zip(q.tolist(), nbr.tolist()):
        assert i in cands.tolist() and i not in row
        d = (means[cands] - means[i]).norm(dim=1)
        d[cands == i] = float("inf")
        brute = cands[torch.argsort(d)[:5]]
        assert sorted(row) == sorted(brute.tolist())


# ----------------------------------------------------------------------------- phases and the field
def test_phases_default_to_the_baseline_warmup_and_twice_it():
    cfg = OmegaConf.structured(StdrConfig)
    assert resolve_phases(cfg, 3000, 40000) == (3000, 6000)
    cfg.warmup_end, cfg.freeze_at = 100, 50
    with pytest.raises(ValueError, match="stdr.freeze_at"):
        resolve_phases(cfg, 3000, 40000)
    assert [phase_at(s, 3, 6) for s in (0, 2, 3, 5, 6, 100)] == \
        [Phase.WARMUP, Phase.WARMUP, Phase.REGULARIZED, Phase.REGULARIZED, Phase.FROZEN, Phase.FROZEN]


def test_fraction_rule_gives_the_papers_share_of_the_run():
    cfg = OmegaConf.structured(StdrConfig)
    cfg.phase_rule = "fraction"
    assert resolve_phases(cfg, 500, 40000) == (3000, 6000)
    assert resolve_phases(cfg, 500, 2000) == (150, 300)
    cfg.freeze_at = 400  # an explicit step wins
    assert resolve_phases(cfg, 500, 2000) == (150, 400)
    cfg.phase_rule = "halfway"
    with pytest.raises(ValueError, match="stdr.phase_rule"):
        resolve_phases(cfg, 500, 2000)


def test_warmup_end_zero_without_freeze_at_is_an_error_not_a_frozen_initial_mask():
    cfg = OmegaConf.structured(StdrConfig)
    cfg.warmup_end = 0
    with pytest.raises(ValueError, match="freeze_at"):
        resolve_phases(cfg, 500, 2000)
    cfg.freeze_at = 300  # explicit: no warm-up, mask trains with opacity until 300
    assert resolve_phases(cfg, 500, 2000) == (0, 300)
    cfg.freeze_at, cfg.mask = None, False  # no mask: nothing to freeze
    assert resolve_phases(cfg, 500, 2000) == (0, 0)


def test_separated_field_shapes_ranges_and_eval_determinism():
    f = SeparatedField(in_dim=10, width=32, temporal_dim=16, dropout=0.5)
    assert any(isinstance(m, torch.nn.BatchNorm1d) for m in f.modules())
    assert any(isinstance(m, torch.nn.Dropout) for m in f.modules())
    x = torch.softmax(torch.randn(50, 10), -1)
    z, d = f(x)
    assert z.shape == (50, 16) and d.shape == (50, 1)
    assert z.abs().max() < 1 and (d > 0).all() and (d < 1).all()
    f.eval()
    assert torch.equal(f(x)[0], f(x)[0])  # no dropout, running statistics
    f.train()
    assert not torch.equal(f(x)[0], f(x)[0])  # dropout is active in training


def test_cond_inputs_start_at_zero_weight_so_switching_the_field_on_changes_nothing():
    p = init_params(torch.rand(30, 3), sh_degree=1)
    net = DeformMLP(depth=4, width=32, skips=[1], cond_dim=17, head_init_std=None)
    zero = net(p, 0.3, torch.zeros(30, 17))
    cond = net(p, 0.3, torch.randn(30, 17))
    assert torch.equal(zero.means, cond.means) and torch.equal(zero.scales, cond.scales)


def test_delta_scale_zero_means_no_deformation():
    p = init_params(torch.rand(30, 3), sh_degree=1)
    net = DeformMLP(depth=2, width=16, skips=[], head_init_std=None)
    g = deform_gaussians(net, p, 0.5, delta_scale=torch.zeros(30, 1))
    assert torch.equal(g.means, p["means"])
    moved = deform_gaussians(net, p, 0.5, delta_scale=torch.ones(30, 1))
    assert not torch.equal(moved.means, p["means"])


def test_densification_keeps_mask_rows_with_their_gaussians():
    """Clone, split and prune through the strategy: every mask row stays with its Gaussian
    (tagged by its colour), children inherit the parent's row."""
    g = torch.Generator().manual_seed(3)
    n = 40
    p = init_params(torch.rand(n, 3, generator=g), sh_degree=1)
    with torch.no_grad():
        p["sh0"].copy_(torch.arange(n, dtype=torch.float32)[:, None, None].repeat(1, 1, 3))
        p["scales"][: n // 2] = math.log(0.5)  # large: split; the rest small: clone
        p["opacities"][-3:] = -20.0             # pruned
    p[MASK_KEY] = torch.nn.Parameter(torch.arange(n, dtype=torch.float32)[:, None] * 10 + torch.arange(6))
    opts = {k: torch.optim.Adam([v], lr=0.01) for k, v in p.items()}
    strat = DensifyStrategy(grow_grad2d=0.0, refine_start=0, refine_every=1, reset_every=0, prune_big_after=10**6)
    state = strat.initialize_state(n, 1.0)
    state["grad2d"][:] = 1.0
    state["count"][:] = 1.0
    strat._refine(p, opts, state, 1, g)
    tag = p["sh0"][:, 0, 0].detach()
    assert p[MASK_KEY].shape[0] == p["means"].shape[0] > n
    torch.testing.assert_close(p[MASK_KEY].detach(), tag[:, None] * 10 + torch.arange(6.0))
    assert opts[MASK_KEY].param_groups[0]["params"][0] is p[MASK_KEY]
    assert not any(t in tag.tolist() for t in (37.0, 38.0, 39.0))


# ----------------------------------------------------------------------------- the training loop
def _stdr_cfg(tmp_path, extra=()):
    return make_cfg(TINY_SCENE + [
        "experiment=embedded_deform_stdr", f"data.cache_dir={tmp_path / 'cache'}", "model.init_num=800",
        "eval.lpips=false", "train.progress=false", "eval.save_images=false", "train.image_every=0",
        "train.eval_at_warmup_end=false", "train.checkpoint_every=0", "baseline.warmup=6",
        "stdr.knn_samples=50", "stdr.knn_every=4", *extra])


def test_phases_in_the_training_loop(tmp_path):
    """Warm-up with the paper's frozen opacity: opacity untouched while the mask trains. Frozen:
    the mask is bit-identical step to step, p rows sum to 1, the field and the deformation train."""
    from stdr.train.trainer import Trainer
    t = Trainer(_stdr_cfg(tmp_path, ["densify.refine_start=1000", "stdr.freeze_opacity=true"]), tmp_path / "run")
    assert t.state.model.plugin("stdr").warmup_end == 6 and t.state.model.plugin("stdr").freeze_at == 12 and MASK_KEY in t.state.model.params
    assert t.state.model.params[MASK_KEY].shape == (t.state.model.params["means"].shape[0], t.state.model.plugin("stdr").K)
    assert t.state.model.plugin("stdr").K == len(t.scene.frames("train"))
    o0, m0 = t.state.model.params["opacities"].detach().clone(), t.state.model.params[MASK_KEY].detach().clone()
    for _ in range(6):
        logs = t.train_step()
        # both regularizers are on in the warm-up (their values are pinned by the unit tests above)
        assert math.isfinite(logs["losses"]["stdr_temporal"]) and math.isfinite(logs["losses"]["stdr_spatial"])
    assert torch.equal(t.state.model.params["opacities"].detach(), o0)
    assert t.state.optimizers["opacities"].state.get(t.state.model.params["opacities"]) is None  # never stepped
    assert not torch.equal(t.state.model.params[MASK_KEY].detach(), m0)
    for _ in range(6):  # regularized: both train
        o1 = t.state.model.params["opacities"].detach().clone()
        t.train_step()
    assert not torch.equal(t.state.model.params["opacities"].detach(), o1)
    field0 = [q.detach().clone() for q in t.state.model.plugin("stdr").field.parameters()]
    m_frozen = t.state.model.params[MASK_KEY].detach().clone()
    for _ in range(4):
        logs = t.train_step()
        assert "stdr_temporal" not in logs["losses"]
        assert torch.equal(t.state.model.params[MASK_KEY].detach(), m_frozen)
    p = t.state.model.plugin("stdr").probabilities(t.state.model.params)
    torch.testing.assert_close(p.sum(1), torch.ones(p.shape[0]))
    assert any(not torch.equal(a, b.detach()) for a, b in zip(field0, t.state.model.plugin("stdr").field.parameters()))


@pytest.mark.slow
def test_resume_with_stdr_matches_an_uninterrupted_run(tmp_path):
    from stdr.train.trainer import Trainer
    sched = ["optim.iterations=30", "densify.refine_start=4", "densify.refine_every=5"]
    a = Trainer(_stdr_cfg(tmp_path, sched), tmp_path / "a", splits=("train", "test"))
    a.train()
    # what stdr-eval does: the model alone, rebuilt from the checkpoint (no data), renders the same
    from stdr.eval.evaluate import evaluate_model
    from stdr.model import load_model
    e = load_model(tmp_path / "a" / "checkpoints" / "last.pt", device="cpu")
    assert e.plugin("stdr").K == a.state.model.plugin("stdr").K and e.plugin("stdr").field is not None
    assert e.step == a.step and e.num_gaussians == a.state.model.num_gaussians
    assert evaluate_model(e, a.scene.frames("test"))["psnr"] == a.evaluate("test")["psnr"]
    st = a.state.model.plugin("stdr").stats(a.state.model.params)
    n, K = a.state.model.params["means"].shape[0], a.state.model.plugin("stdr").K
    assert st["mask_bytes"] == 4 * n * K and st["mask_adam_bytes"] == 8 * n * K
    assert st["knn_refreshes"] >= 3 and st["knn_seconds"] > 0 and 0 <= st["fraction_time_gated"] <= 1
    assert 0 < st["dynamic_probability_mean"] < 1
    # 9: inside the regularized phase, with a cached neighbour sample; 10: right after a
    # densification replaced the rows the cached sample indexes (the next step must resample)
    for stop in (9, 10):
        b1 = Trainer(_stdr_cfg(tmp_path, sched + [f"train.stop_at={stop}"]), tmp_path / f"b{stop}")
        b1.train()
        b2 = Trainer(_stdr_cfg(tmp_path, sched), tmp_path / f"b{stop}")
        b2.train()
        for k in a.state.model.params:
            assert torch.equal(a.state.model.params[k], b2.state.model.params[k]), (stop, k)
        for (ka, va), (kb, vb) in zip(a.state.model.plugin("stdr").field.state_dict().items(),
                                      b2.state.model.plugin("stdr").field.state_dict().items()):
            assert torch.equal(va, vb), (stop, ka)
    # a checkpoint with STDR cannot be loaded into a run without it
    c = Trainer(make_cfg(TINY_SCENE + [f"data.cache_dir={tmp_path / 'cache'}", "model.init_num=800"]),
                tmp_path / "c")
    with pytest.raises(ValueError, match=r"saved with plug-ins \[.stdr.\] but this model has none"):
        c.load(tmp_path / "a" / "checkpoints" / "last.pt")


def test_configs_and_table_labels():
    cfg = make_cfg(["experiment=dnerf_deform_stdr", "data.path=/x"])
    assert cfg.name == "dnerf_deform_stdr" and cfg.stdr.enabled and cfg.data.format == "dnerf"
    assert not make_cfg(["experiment=dnerf_deform", "data.path=/x"]).stdr.enabled
    assert make_cfg(["stdr=on"]).stdr.enabled
    c = OmegaConf.to_container(make_cfg(["stdr=on", "stdr.spatial_reg=false", "stdr.mask_after_freeze=true"]))
    assert method_name(c) == "deform+STDR w/o spatial_reg, mask after freeze"  # the former default
    assert method_name(OmegaConf.to_container(make_cfg(["stdr=on", "stdr.mask_after_freeze=false"]))) == "deform+STDR"
    assert method_name(OmegaConf.to_container(make_cfg(["stdr=on"]))) == "deform+STDR"
    assert method_name(OmegaConf.to_container(make_cfg([]))) == "deform"
    # a compact run gets its own row beside the full one
    c = OmegaConf.to_container(make_cfg(["stdr=on", "stdr.mask_bits=8", "prune.share=0.3"]))
    assert method_name(c) == "deform+STDR 8-bit mask pruned 0.3x2"
    c = OmegaConf.to_container(make_cfg(["prune.share=0.5", "prune.at=[refine_stop]", "prune.time_weight=1"]))
    assert method_name(c) == "deform pruned 0.5x1 tw1"


@pytest.mark.slow
def test_ghosting_scene_masks_separate_the_two_places(tmp_path):
    """An object that jumps between two places (studies/ghosting.py). With the paper's
    frozen-opacity warm-up the mask alone must do the time-gating: the Gaussians at A are on at
    A's times and off at B's, and the other way round. (With opacity training too, the mask
    separates the two places less sharply, measured: on 0.94, off 0.64 at A.) Whether STDR then
    beats deform's PSNR on this scene is a measurement, not a unit test: `python -m studies.ghosting`
    (its margin differs between CPUs, +0.38 to +0.5 dB)."""
    from studies import ghosting
    from stdr.train.trainer import Trainer
    cfg = make_cfg(ghosting.overrides(600, tmp_path / "cache") + ["experiment=embedded_deform_stdr",
                                                                   "stdr.freeze_opacity=true"])
    t = Trainer(cfg, tmp_path / "stdr_frozen", splits=("train", "test"))
    t.train()
    for place, m in ghosting.mask_by_place(t).items():
        assert m["gaussians_near"] >= 10, place
        on, off = m["mask_at_own_times"], m["mask_at_other_times"]
        assert on > 0.8 and off < 0.6 and on - off > 0.3, (place, m)

def test_tensorboard_shows_phase_losses_histograms_and_mask_image(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    from stdr.train.trainer import Trainer
    t = Trainer(_stdr_cfg(tmp_path, ["optim.iterations=16", "train.log_every=4", "train.image_every=8"]),
                tmp_path / "run")
    t.train()
    t.log.writer.flush()
    ev = EventAccumulator(str(tmp_path / "run" / "tb"), size_guidance={"histograms": 0, "images": 0}).Reload()
    tags = ev.Tags()
    for k in ("stdr/phase", "loss/stdr_temporal", "loss/stdr_spatial", "stdr/mask_mean"):
        assert k in tags["scalars"], k
    assert {"stdr/temporal_entropy", "stdr/dynamic_probability"} <= set(tags["histograms"])
    assert "stdr/mask_over_time" in tags["images"]
    assert [e.value for e in ev.Scalars("stdr/phase")] == [0.0, 1.0, 1.0, 2.0]  # iterations 3, 7, 11, 15


# ----------------------------------------------------------------------------- fidelity fixes (the fidelity study)
def _plugin(**over):
    from stdr.plugins.stdr import STDR
    cfg = OmegaConf.structured(StdrConfig)
    for k, v in over.items():
        setattr(cfg, k, v)
    from stdr.plugins.stdr import resolve_phases
    from stdr.schedule import Schedule
    w, f = resolve_phases(cfg, 10, 100)
    sched = Schedule(iterations=100, static_warmup_end=10, plugins={"stdr": {"warmup_end": w, "freeze_at": f,
                                                                          "freeze_moved": None}})
    return STDR(cfg, sched, knots=torch.linspace(0, 1, 5, dtype=torch.float64), xyz_freqs=2, seed=0,
                init_opacity=0.1)


def test_mask_can_carry_the_opacity_during_the_warmup():
    """opacity_init + mask_init=null: the masked opacity starts at model.init_opacity, and the
    mask can raise it up to opacity_init (the frozen-opacity reading caps it at 0.1)."""
    s = _plugin(opacity_init=0.99, mask_init=None)
    p = init_params(torch.rand(20, 3), sh_degree=1, init_opacity=0.1)
    s.init_gaussians(p)
    eff = torch.sigmoid(p["opacities"])[:, None] * torch.sigmoid(p[MASK_KEY])
    torch.testing.assert_close(eff, torch.full_like(eff, 0.1))
    torch.testing.assert_close(torch.sigmoid(p["opacities"]), torch.full((20,), 0.99))
    with pytest.raises(ValueError, match="opacity_init"):
        _plugin(opacity_init=0.05, mask_init=None)  # the mask can only lower opacity
    with pytest.raises(ValueError, match="opacity_init"):
        _plugin(opacity_init=1.0)
    # defaults: opacity untouched, mask logit 2
    s = _plugin()
    p = init_params(torch.rand(20, 3), sh_degree=1, init_opacity=0.1)
    o = p["opacities"].detach().clone()
    s.init_gaussians(p)
    assert torch.equal(p["opacities"].detach(), o) and torch.all(p[MASK_KEY] == 2.0)


def test_freeze_cleanup_switches_off_faint_entries_only():
    s = _plugin(freeze_cleanup=0.02)
    p = init_params(torch.rand(4, 3), sh_degree=1, init_opacity=0.5)
    s.init_gaussians(p)
    with torch.no_grad():  # masked opacity 0.5 * sigmoid(m): faint (<0.02) where m is -5 (0.0033)
        p[MASK_KEY].copy_(torch.tensor([[-5.0, 0.0, 0.0, 0.0, 0.0]] * 2 + [[0.0, -5.0, -2.0, 3.0, 0.0]] * 2))
    before = p[MASK_KEY].detach().clone()
    s.before_step(StepContext(s.freeze_at - 1, p))  # not yet
    assert torch.equal(p[MASK_KEY].detach(), before)
    s.before_step(StepContext(s.freeze_at, p))
    m = p[MASK_KEY].detach()
    off = before == -5.0
    assert torch.all(m[off] == -30.0) and torch.equal(m[~off], before[~off])
    assert s.cleaned_entries == int(off.sum()) and not p[MASK_KEY].requires_grad
    s.before_step(StepContext(s.freeze_at + 1, p))  # once
    assert s.cleaned_entries == int(off.sum())
    # the statistic that motivates it: entries with masked opacity in [1/255, 0.05]
    from stdr.plugins.stdr.mask import faint_fraction
    assert faint_fraction(torch.tensor([0.5, 0.5]), torch.tensor([[-5.0, -3.0], [0.0, -2.5]])) == 0.5


def test_opacity_reset_during_the_warmup_caps_the_masked_opacity_not_the_frozen_opacity():
    s = _plugin(opacity_init=0.99, mask_init=None, freeze_opacity=True)
    p = init_params(torch.rand(6, 3), sh_degree=1, init_opacity=0.1)
    s.init_gaussians(p)
    with torch.no_grad():
        p[MASK_KEY][:3] = 4.0  # masked opacity ~0.97
    o = p["opacities"].detach().clone()
    assert s.reset_opacity(StepContext(s.warmup_end - 1, p), 0.01)
    assert torch.equal(p["opacities"].detach(), o)
    eff = torch.sigmoid(p["opacities"])[:, None] * torch.sigmoid(p[MASK_KEY])
    assert eff.max() <= 0.01 + 1e-6
    assert not s.reset_opacity(StepContext(s.warmup_end, p), 0.01)  # afterwards: the usual reset


def test_freeze_opacity_false_trains_opacity_in_the_warmup_as_an_empty_warmup_does():
    """stdr.freeze_opacity=false: opacity trains from step 0 and the opacity reset is the usual
    one; the phases themselves (regularized until the freeze) do not move."""
    held, free = _plugin(freeze_opacity=True), _plugin()
    assert not OmegaConf.structured(StdrConfig).freeze_opacity  # the measured default (research/notes/2026-11-24-stdr-measurements.md, fidelity study)
    assert (held.warmup_end, held.freeze_at) == (free.warmup_end, free.freeze_at) == (10, 20)
    p = init_params(torch.rand(6, 3), sh_degree=1, init_opacity=0.1)
    held.init_gaussians(p)
    held.before_step(StepContext(0, p))
    assert not p["opacities"].requires_grad and p[MASK_KEY].requires_grad
    free.before_step(StepContext(0, p))
    assert p["opacities"].requires_grad and p[MASK_KEY].requires_grad
    assert free.phase(0) == Phase.WARMUP and set(free.regularizers(StepContext(0, p))) == {"temporal", "spatial"}
    assert not free.reset_opacity(StepContext(0, p), 0.01)  # opacity trains: the strategy's own reset
    cfg = make_cfg(["experiment=dnerf_deform_stdr", "data.path=/x"])
    assert "(opacity trains)" in resolve_schedule(cfg).describe()
    cfg.stdr.freeze_opacity = True
    assert "(opacity frozen)" in resolve_schedule(cfg).describe()


@pytest.mark.slow
def test_freeze_opacity_false_trains_like_an_empty_warmup_with_the_same_freeze(tmp_path):
    """For a baseline without stage switches, stdr.freeze_opacity=false is the run with
    warmup_end=0 and the default freeze: the same training, bit for bit."""
    from stdr.train.trainer import Trainer
    sched = ["optim.iterations=30", "densify.refine_start=4", "densify.refine_every=4", "densify.reset_every=10"]
    a = Trainer(_stdr_cfg(tmp_path, sched), tmp_path / "a")  # the default, stdr.freeze_opacity=false
    a.train()  # (a trainer seeds the global generator when it is built: build, then train, one at a time)
    b = Trainer(_stdr_cfg(tmp_path, sched + ["stdr.warmup_end=0", "stdr.freeze_at=12", "stdr.freeze_opacity=true"]),
                tmp_path / "b")
    b.train()
    assert (a.state.model.plugin("stdr").warmup_end, a.state.model.plugin("stdr").freeze_at, b.state.model.plugin("stdr").freeze_at) == (6, 12, 12)
    for k in a.state.model.params:
        assert torch.equal(a.state.model.params[k], b.state.model.params[k]), k


def test_white_background_reset_at_refine_start():
    st = DensifyStrategy(refine_start=50, reset_every=3000, reset_white_at_start=True)
    white, black = st.initialize_state(3, 1.0, white_background=True), st.initialize_state(3, 1.0)
    assert st.reset_due(50, white) and not st.reset_due(50, black) and not st.reset_due(51, white)
    assert st.reset_due(3000, black)
    assert not DensifyStrategy(refine_start=50, reset_every=0).reset_due(50, white)
    paper = make_cfg(["experiment=dnerf_deform", "budget=paper", "data.path=/x"])
    cpu = make_cfg(["experiment=dnerf_deform", "budget=cpu", "data.path=/x"])
    assert paper.densify.reset_white_at_start and not cpu.densify.reset_white_at_start


def test_training_loop_hands_the_rendered_conditioning_to_the_deformation_hooks(tmp_path, monkeypatch):
    """The cond that before_step and regularizers see is the tensor the render used (SC-GS
    resamples its nodes and computes ARAP from them)."""
    from stdr.train.trainer import Trainer
    t = Trainer(_stdr_cfg(tmp_path, ["densify.refine_start=1000"]), tmp_path / "run")
    seen = {}
    orig_fwd, orig_before, orig_reg = t.state.model.deform.forward, t.state.model.deform.before_step, t.state.model.deform.regularizers
    monkeypatch.setattr(t.state.model.deform, "forward", lambda p, tt, c=None: (seen.__setitem__("fwd", c), orig_fwd(p, tt, c))[1])
    monkeypatch.setattr(t.state.model.deform, "before_step",
                        lambda ctx: (seen.__setitem__("before", ctx.cond), orig_before(ctx))[1])
    monkeypatch.setattr(t.state.model.deform, "regularizers",
                        lambda ctx: (seen.__setitem__("reg", ctx.cond), orig_reg(ctx))[1])
    while t.step <= t.state.model.plugin("stdr").freeze_at:
        t.train_step()
    assert seen["fwd"] is seen["before"] is seen["reg"]
    assert seen["fwd"].shape == (t.state.model.params["means"].shape[0], t.state.model.plugin("stdr").cond_dim) and seen["fwd"].abs().sum() > 0


def test_freeze_colliding_with_a_stage_switch_is_moved_by_rule_or_rejected_when_explicit():
    """SC-GS at budget=cpu: static to 500, node->skinning switch at 1000 (+100 detached steps).
    The default freeze (2 x 500 = 1000) lands on it and moves to the midpoint 750; an explicit
    freeze_at inside the window is an error; one outside is kept."""
    from stdr.baselines.scgs import ControlNodeDeformation
    from stdr.schedule import keep_out_of_windows

    def place_freeze(step, floor, windows, explicit):
        return keep_out_of_windows(step, floor, windows, "stdr.freeze_at", explicit)
    base = make_cfg(["experiment=dnerf_scgs_stdr", "budget=cpu", "data.path=/x"]).baseline
    _, switches = ControlNodeDeformation.stages(base)
    assert [(a, b) for _, a, b in switches] == [(1000, 1100)]
    f, moved = place_freeze(1000, 500, switches, explicit=False)
    assert f == 750 and "1000 -> 750" in moved
    assert place_freeze(1200, 500, switches, explicit=False) == (1200, None)
    with pytest.raises(ValueError, match="stdr.freeze_at=1050"):
        place_freeze(1050, 500, switches, explicit=True)
    # the same through the run's schedule, which the plug-in reads
    s = resolve_schedule(make_cfg(["experiment=dnerf_scgs_stdr", "budget=cpu", "data.path=/x"]))
    ph = s.plugins["stdr"]
    assert (ph["warmup_end"], ph["freeze_at"]) == (500, 750) and "1000 -> 750" in ph["freeze_moved"]
    with pytest.raises(ValueError, match="stdr.freeze_at=1050"):
        resolve_schedule(make_cfg(["experiment=dnerf_scgs_stdr", "budget=cpu", "data.path=/x", "stdr.freeze_at=1050"]))
    cfg = make_cfg(["experiment=dnerf_scgs_stdr", "budget=cpu", "data.path=/x"])
    assert cfg.stdr.freeze_at is None  # no magic number in the baseline's budget file


def test_a_size_prune_that_would_remove_most_of_the_model_warns_and_names_the_keys():
    """Measured on a half-length schedule: the first size prune removed 11,245 of 11,254
    Gaussians. The strategy still prunes (results do not change) but says so."""
    g = torch.Generator().manual_seed(5)
    p = init_params(torch.rand(20, 3, generator=g), sh_degree=1)
    opts = {k: torch.optim.Adam([v], lr=0.01) for k, v in p.items()}
    strat = DensifyStrategy(grow_grad2d=1e9, refine_start=0, refine_every=1, reset_every=0, prune_big_after=0,
                            prune_scale2d=20.0)
    state = strat.initialize_state(20, 100.0)  # a large scene: no Gaussian is big in 3D
    state["max_radii"][:15] = 30.0  # 15 of 20 are big on screen
    with pytest.warns(RuntimeWarning, match="densify.prune_big_after"):
        strat._refine(p, opts, state, 1, g)
    assert p["means"].shape[0] == 5
    state = strat.initialize_state(5, 100.0)
    state["max_radii"][:2] = 30.0  # a minority: no warning
    import warnings as w
    with w.catch_warnings():
        w.simplefilter("error")
        strat._refine(p, opts, state, 2, g)
    assert p["means"].shape[0] == 3


def test_separated_field_has_its_own_group_and_optional_schedule(tmp_path):
    """stdr.field_lr_init=null: the field's group follows the deformation network's lr; a value:
    log-linear from it at the freeze (where the field starts training) to field_lr_final."""
    from stdr.train.optim import update_lrs
    from stdr.train.trainer import Trainer
    sched = ["optim.iterations=30", "baseline.lr_init=1e-3", "baseline.lr_final=1e-5", "baseline.lr_max_steps=30"]
    t = Trainer(_stdr_cfg(tmp_path, sched), tmp_path / "a")
    names = [g["name"] for g in t.state.net_opt.param_groups]
    assert names.count("stdr_field") == 1
    for step in (0, 12, 29):
        update_lrs(t.cfg, t.state, t.net_groups, step)
        lr = {g["name"]: g["lr"] for g in t.state.net_opt.param_groups}
        assert lr["stdr_field"] == lr["deform"]
    t = Trainer(_stdr_cfg(tmp_path, sched + ["stdr.field_lr_init=4e-3", "stdr.field_lr_final=4e-5"]), tmp_path / "b")
    s = t.state.model.plugin("stdr")
    assert s.freeze_at == 12
    expect = {0: 4e-3, 12: 4e-3, 21: 4e-4, 30: 4e-5}  # halfway from the freeze (12) to the end (30)
    for step, want in expect.items():
        update_lrs(t.cfg, t.state, t.net_groups, step)
        lr = {g["name"]: g["lr"] for g in t.state.net_opt.param_groups}
        assert lr["stdr_field"] == pytest.approx(want, rel=1e-9), step
    assert lr["deform"] == pytest.approx(1e-5)


def test_conditioning_is_computed_once_outside_training_and_follows_every_change():
    """After the freeze, outside training (eval mode, no autograd), the separated field's output is
    the same for every frame: one computation serves them all, and any change of what it depends
    on (the mask, the means under the xyz encoding, a field weight) computes it afresh."""
    st = _plugin(field_pe_xyz=True)
    params = init_params(torch.rand(40, 3), sh_degree=1)
    st.init_gaussians(params)
    with torch.no_grad():
        params["stdr_mask"].normal_()
    step = st.freeze_at
    assert st.xyz_freqs == 2
    st.field.eval()

    def fresh():
        st._cond_cache = None
        return st.conditioning_at(params, step)[0]
    with torch.no_grad():
        a = st.conditioning_at(params, step)[0]
        assert st.conditioning_at(params, step)[0] is a  # reused
        assert torch.equal(a, fresh())
        for change in (lambda: params["stdr_mask"][:, 0].add_(2.0),  # the mask
                       lambda: params["means"].add_(0.1),        # the xyz encoding's input (xyz_freqs=2)
                       lambda: st.field.shared[0].weight.mul_(1.5)):
            before = st.conditioning_at(params, step)[0]
            change()
            after = st.conditioning_at(params, step)[0]
            assert after is not before and not torch.equal(after, before)
            assert torch.equal(after, fresh())
        # without the xyz encoding the means are no input: moving them keeps the result
        st_plain = _plugin()
        st_plain.init_gaussians(params)
        st_plain.field.eval()
        c = st_plain.conditioning_at(params, step)[0]
        params["means"].add_(0.1)
        assert st_plain.conditioning_at(params, step)[0] is c
    # in training (the field trains after the freeze) nothing is reused
    st.field.train()
    x, y = st.conditioning_at(params, step)[0], st.conditioning_at(params, step)[0]
    assert x is not y and x.requires_grad


def test_8bit_mask_round_trip():
    from stdr.plugins.stdr.mask import OFF_LOGIT, activated, logits_of, quantize
    m = torch.cat([torch.linspace(-12, 12, 1001), torch.tensor([OFF_LOGIT, -30.0, 30.0])])[:, None]
    q = quantize(m)
    assert q.dtype == torch.uint8
    assert (activated(q) - torch.sigmoid(m)).abs().max() <= 0.5 / 255 + 1e-7  # rounding to the nearest level
    assert activated(q)[-3:, 0].tolist() == [0.0, 0.0, 1.0]  # switched-off entries read back as exactly 0
    lg = logits_of(q)
    assert torch.isfinite(lg).all() and lg.min() == OFF_LOGIT and lg.max() == -OFF_LOGIT  # both ends finite
    assert torch.isfinite(torch.softmax(lg.reshape(1, -1), -1)).all()  # what the separated field reads
    assert torch.equal(quantize(logits_of(q)), q)  # logits_of reads back the stored levels
    assert torch.equal(activated(logits_of(q)) > 0.5, activated(q) > 0.5)


def test_mask_bits_8_stores_the_frozen_mask_in_8_bits_and_resumes_exactly(tmp_path):
    from stdr.testing import tiny_config
    """After the freeze: uint8 in the parameter dict, no optimizer, a quarter of the bytes in
    model_mb; densification after the freeze keeps its rows; resume across the freeze and
    load_model give exactly what the uninterrupted run has."""
    from stdr.plugins.stdr.mask import logits_of
    from stdr.model import model_bytes
    from stdr.model import load_model
    from stdr.train.trainer import Trainer
    sched = ["stdr=on", "optim.iterations=60", "baseline.warmup=10", "stdr.freeze_at=25", "densify.refine_start=10",
             "densify.refine_every=10", "densify.refine_stop=50", "densify.reset_every=0", "densify.prune_big_after=30",
             "train.checkpoint_every=0", "train.eval_at_warmup_end=false"]
    a = Trainer(tiny_config(tmp_path, sched + ["stdr.mask_bits=8"]), tmp_path / "a", splits=("train", "test"))
    a.train()
    m = a.state.model.params["stdr_mask"]
    assert m.dtype == torch.uint8 and not m.requires_grad and "stdr_mask" not in a.state.optimizers
    assert m.shape[0] == a.state.model.num_gaussians  # rows kept through the densification at 30 and 40
    st = a.state.model.plugins[0].stats(a.state.model.params)
    assert st["mask_bits"] == 8 and st["mask_bytes"] == m.numel() and st["mask_adam_bytes"] == 0
    n8 = model_bytes(a.state.model)
    a.state.model.params["stdr_mask"] = torch.nn.Parameter(logits_of(m), requires_grad=False)  # the same, as float32
    assert n8 == model_bytes(a.state.model) - 3 * m.numel()
    a.state.model.params["stdr_mask"] = m
    b1 = Trainer(tiny_config(tmp_path, sched + ["stdr.mask_bits=8", "train.stop_at=20"]), tmp_path / "b")
    b1.train()
    assert b1.state.model.params["stdr_mask"].dtype == torch.float32  # before the freeze
    b2 = Trainer(tiny_config(tmp_path, sched + ["stdr.mask_bits=8", "train.stop_at=40"]), tmp_path / "b")
    b2.train()
    b3 = Trainer(tiny_config(tmp_path, sched + ["stdr.mask_bits=8"]), tmp_path / "b")
    b3.train()  # resumed from a checkpoint holding the 8-bit mask
    for k in a.state.model.params:
        assert torch.equal(a.state.model.params[k], b3.state.model.params[k]), k
    loaded = load_model(tmp_path / "a" / "checkpoints" / "last.pt", device="cpu")
    assert loaded.params["stdr_mask"].dtype == torch.uint8
    fr = a.scene.frames("test")[0]
    with torch.no_grad():
        a.state.model.eval()
        want = a.state.model.render(fr.camera, fr.time).image
        got = loaded.eval().render(fr.camera, fr.time).image
    assert torch.equal(want, got)


# ----------------------------------------------------------------------------- the field in bf16
def _norm_relu_dropout_composed(x, bn, gate):
    """What norm_relu_dropout computes, as the plain composition autograd differentiates."""
    mean = x.mean(0)
    d = x - mean
    y = d * torch.rsqrt(d.square().mean(0) + bn.eps) * bn.weight + bn.bias
    return torch.relu(y) * gate


def test_norm_relu_dropout_has_the_gradient_of_its_composition(monkeypatch):
    """Its hand-written backward against autograd through batch norm, ReLU and dropout, in float64
    with the same kept entries; and gradcheck with dropout off."""
    from stdr import ops
    g = torch.Generator().manual_seed(0)
    x = (torch.randn(300, 8, generator=g, dtype=torch.float64) * 2 + 0.5).requires_grad_(True)
    bn = ops.BatchNorm1d(8).double()
    with torch.no_grad():
        bn.weight.uniform_(0.5, 1.5, generator=g)
        bn.bias.uniform_(-0.5, 0.5, generator=g)
    keep = torch.rand(300 * 8, generator=g) > 0.25
    monkeypatch.setattr(ops, "dropout_keep", lambda n, p, device: (keep, 0.75))
    out = ops.norm_relu_dropout(x, bn, 0.25)
    ref = _norm_relu_dropout_composed(x, bn, keep.view(300, 8).double() / 0.75)
    assert torch.allclose(out, ref, rtol=1e-12, atol=1e-12)
    gy = torch.randn(300, 8, generator=g, dtype=torch.float64)
    got = torch.autograd.grad(out, (x, bn.weight, bn.bias), gy)
    want = torch.autograd.grad(ref, (x, bn.weight, bn.bias), gy)
    for a, b, name in zip(got, want, ("x", "weight", "bias")):
        assert torch.allclose(a, b, rtol=1e-10, atol=1e-12), name
    bn0 = ops.BatchNorm1d(8).double()
    assert torch.autograd.gradcheck(lambda xx, w, b: ops._NormReluDropout.apply(xx, w, b, None, bn0.eps)[0],
                                    (x[:20].detach().requires_grad_(True), bn.weight, bn.bias))


def test_norm_relu_dropout_updates_running_statistics_as_batch_norm_does_and_evaluates_as_torch():
    from stdr.ops import BatchNorm1d, norm_relu_dropout
    x = torch.randn(500, 16, generator=torch.Generator().manual_seed(1)) * 3 + 2
    a, b = BatchNorm1d(16), BatchNorm1d(16)
    norm_relu_dropout(x, a, 0.1)
    b(x)
    for k in ("running_mean", "running_var", "num_batches_tracked"):
        assert torch.equal(getattr(a, k), getattr(b, k)), k
    a.eval()
    assert torch.equal(norm_relu_dropout(x, a, 0.1), torch.relu(a(x)))  # eval: no dropout, running stats


def test_dropout_keep_keeps_the_asked_fraction_in_every_lane_and_follows_the_seed():
    from stdr.ops import dropout_keep
    torch.manual_seed(3)
    keep, q = dropout_keep(4 * 250_000 + 3, 0.1, "cpu")
    assert keep.shape == (1_000_003,) and keep.dtype == torch.bool
    assert q == 1 - round(0.1 * 32768) / 32768
    # each of the four 16-bit lanes of a draw (the top one has 15 random bits) keeps q of its entries:
    # 250,000 draws each, binomial sd 0.0006
    per_lane = keep[:1_000_000].view(-1, 4).float().mean(0)
    assert (per_lane - q).abs().max() < 0.003, per_lane
    torch.manual_seed(3)
    assert torch.equal(dropout_keep(1_000_003, 0.1, "cpu")[0], keep)
    assert dropout_keep(10, 0.0, "cpu")[0].all()
    with pytest.raises(ValueError, match="dropout probability"):
        dropout_keep(10, 1.0, "cpu")


def test_the_bf16_field_computes_the_fp32_fields_function():
    """Same weights, eval mode: the bf16 field's outputs (fp32) within bfloat16 rounding of the fp32
    field's; in training it draws its own dropout and still gives outputs in range."""
    torch.manual_seed(0)
    f32 = SeparatedField(in_dim=40, width=64, temporal_dim=16, dropout=0.1)
    f16 = SeparatedField(in_dim=40, width=64, temporal_dim=16, dropout=0.1, precision="bf16")
    f16.load_state_dict(f32.state_dict())
    x = torch.softmax(torch.randn(2000, 40) * 3, -1)
    f32.train(), f16.train()
    f32(x), f16(x)  # one training batch each: the running statistics move alike
    f32.eval(), f16.eval()
    (z32, d32), (z16, d16) = f32(x), f16(x)
    assert z16.dtype == torch.float32 and d16.dtype == torch.float32
    assert (z16 - z32).abs().max() < 0.05 and (d16 - d32).abs().max() < 0.02
    assert not torch.equal(z16, z32)  # it does take bf16 products
    f16.train()
    z, d = f16(x)
    assert z.abs().max() < 1 and (d > 0).all() and (d < 1).all()
    with pytest.raises(ValueError, match="stdr.field_precision='fp16'"):
        SeparatedField(in_dim=4, precision="fp16")


@pytest.mark.parametrize("network, requested, verified, want", [
    ("bf16", "auto", True, "bf16"), ("fp32", "auto", True, "fp32"), ("bf16", "auto", False, "fp32"),
    ("bf16", "fp32", True, "fp32"), ("fp32", "bf16", False, "bf16")])
def test_field_precision_auto_follows_the_deformation_networks(tmp_path, monkeypatch, network, requested, verified, want):
    """auto: the network's precision once the field's bf16 is verified (FIELD_BF16_DEFAULT), fp32
    before; an explicit value wins."""
    from stdr.plugins.stdr import plugin
    from stdr.train.trainer import Trainer
    monkeypatch.setattr(plugin, "FIELD_BF16_DEFAULT", verified)
    t = Trainer(_stdr_cfg(tmp_path, ["optim.iterations=30", f"baseline.precision={network}",
                                     f"stdr.field_precision={requested}"]), tmp_path / "a")
    s = t.state.model.plugin("stdr")
    assert s.field_precision == want and s.field.precision == want
    assert s.state_dict()["field_precision"] == want
    assert s.stats(t.state.model.params)["field_precision"] == want


@pytest.mark.parametrize("baseline, network, device, flags, want", [
    ("scgs", "fp32", "cpu", ("avx512_bf16",), "bf16"),   # verified beside its fp32 network
    ("scgs", "fp32", "cpu", (), "fp32"),                 # no bf16 instructions: emulated, slower
    ("scgs", "fp32", "cuda", ("avx512_bf16",), "fp32"),  # not verified on a GPU
    ("spgs", "fp32", "cpu", ("avx512_bf16",), "bf16"),
    ("4dgs", "fp32", "cpu", ("avx512_bf16",), "bf16"),
    ("4dgs", "fp32", "cpu", (), "fp32"),  # a CPU without bf16 matrix instructions
    ("deform", "fp32", "cpu", ("avx512_bf16",), "fp32"),  # deform's field was checked beside its bf16 network only
    ("deform", "bf16", "cpu", ("avx512_bf16",), "bf16")])
def test_field_precision_auto_beside_an_fp32_network_is_bf16_only_where_verified(baseline, network, device, flags, want):
    from stdr.plugins.stdr.plugin import FIELD_BF16_BESIDE_FP32, field_precision
    assert field_precision("auto", network, device, baseline, cpu_flags=flags) == want
    assert field_precision("fp32", network, device, baseline, cpu_flags=flags) == "fp32"  # an explicit value wins
    assert FIELD_BF16_BESIDE_FP32 == {"scgs", "spgs", "4dgs"}  # deform's network is bf16 itself there


def test_a_checkpoint_from_before_the_field_precision_key_resumes_in_fp32(tmp_path):
    """A run trained before stdr.field_precision existed trained its field in fp32: with auto, its
    state resumes in fp32 whatever the deformation network's precision; an explicit value wins."""
    from stdr.train.trainer import Trainer
    t = Trainer(_stdr_cfg(tmp_path, ["optim.iterations=30", "baseline.precision=bf16", "stdr.field_precision=bf16"]),
                tmp_path / "a")
    s = t.state.model.plugin("stdr")
    old = {k: v for k, v in s.state_dict().items() if k != "field_precision"}
    s.cfg.field_precision = "auto"  # the resumed run's config: auto
    s.load_state_dict(old, t.state.model.params)
    assert s.field_precision == "fp32" and s.field.precision == "fp32"
    t = Trainer(_stdr_cfg(tmp_path, ["optim.iterations=30", "stdr.field_precision=bf16"]), tmp_path / "b")
    s = t.state.model.plugin("stdr")
    s.load_state_dict(old, t.state.model.params)
    assert s.field_precision == "bf16"
    with pytest.raises(ValueError, match="stdr.field_precision='half'"):
        Trainer(_stdr_cfg(tmp_path, ["optim.iterations=30", "stdr.field_precision=half"]), tmp_path / "c")
