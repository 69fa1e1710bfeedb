"""Temporal culling (render.cull): rows whose opacity at time t cannot reach 1/255 skip the
deformation, projection and rasterizer, with the image and the rendered rows' gradients unchanged."""
import pytest
import torch

from stdr.baselines import BASELINES
from stdr.model import active_rows
from stdr.densify.strategy import DensifyStrategy
from stdr.testing import tiny_config as _tiny
from stdr.tools import identity_check as _ic

# every phase in 60 steps: static warm-up, densification, STDR's three phases, SC-GS's stages
SCHEDULE = [s for s in _ic.SCHEDULE if not s.startswith("optim.iterations=")] + _ic.STDR_PHASES


def _trained(tmp_path, name, steps, extra=()):
    """A +STDR run whose mask still gates opacity after the freeze (stdr.mask_after_freeze=true, the
    former default), so that there is something to cull by the mask in every phase."""
    from stdr.train.trainer import Trainer
    cfg = _tiny(tmp_path, SCHEDULE + [f"experiment=embedded_{name}_stdr", "optim.iterations=60", "render.cull=off",
                                      "train.eval_at_warmup_end=false", "stdr.mask_after_freeze=true", *extra])
    tr = Trainer(cfg, tmp_path / "run", splits=("train", "test"))
    for _ in range(steps):
        tr.train_step()
    return tr


def _switch_off_entries(model, share, seed):
    """A realistic mask: `share` of the (Gaussian, knot) entries off (sigmoid(-12) ~ 6e-6), drawn
    at random, so at any time most Gaussians are masked and some are not."""
    with torch.no_grad():
        m = model.params["stdr_mask"]
        off = torch.rand(m.shape, generator=torch.Generator().manual_seed(seed)) < share
        m[off] = -12.0
    model.plugin("stdr")._p_for = None  # the softmax cache


def _render_and_grads(model, frame, cull, seed=1):
    for p in model.params.values():
        p.grad = None
    model.deform.zero_grad(set_to_none=True)
    for p in model.plugins:
        for mod in p.modules():
            mod.zero_grad(set_to_none=True)
    g, rows = model.deformed_rows(frame.time, model.step, cull=cull)
    out = model.render_gaussians(g, frame.camera)
    w = torch.randn(out.image.shape, generator=torch.Generator().manual_seed(seed))
    ((out.image * w).sum() + out.depth.sum() * 1e-3).backward()
    grads = {k: None if v.grad is None else v.grad.clone() for k, v in model.params.items()}
    nets = {k: v.grad.clone() for k, v in model.deform.named_parameters() if v.grad is not None}
    return out.image.detach(), grads, nets, rows


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(BASELINES))
@pytest.mark.parametrize("steps", [10, 60])  # static warm-up; after STDR's freeze and the baseline's stages
def test_culled_render_equals_the_full_one(tmp_path, name, steps):
    tr = _trained(tmp_path, name, steps)
    model = tr.state.model.eval()  # eval mode: no dropout, so both renders see one network
    _switch_off_entries(model, 0.6, seed=steps)
    for frame in (tr.scene.frames("train")[3], tr.scene.frames("test")[1]):  # a knot and a time between knots
        img_a, ga, na, rows_a = _render_and_grads(model, frame, cull=False)
        img_b, gb, nb, rows = _render_and_grads(model, frame, cull=True)
        n = model.num_gaussians
        assert rows_a is None and rows is not None and 0.2 * n < rows.numel() < 0.8 * n, (n, rows)
        assert (img_a - img_b).abs().max() <= 1e-6
        keep = torch.zeros(n, dtype=torch.bool)
        keep[rows] = True
        for k in model.params:
            if ga[k] is None:
                assert gb[k] is None, k
                continue
            scale = ga[k].abs().max().clamp_min(1e-12)
            assert ((ga[k][keep] - gb[k][keep]).abs().max() / scale) <= 1e-5, k
            assert torch.all(gb[k][~keep] == 0), k  # culled rows: no gradient from the render
            assert torch.all(ga[k][~keep] == 0), k  # ... as without culling
        assert na.keys() == nb.keys()
        for k in na:  # the network's gradients sum over other rows in another order
            scale = na[k].abs().max().clamp_min(1e-12)
            assert ((na[k] - nb[k]).abs().max() / scale) <= 1e-4, k
        # the rows kept are exactly those whose opacity at t reaches 1/255
        eff = torch.sigmoid(model.params["opacities"]) * model.plugin("stdr").opacity_factor(
            model.context(model.step, t=frame.time))
        assert torch.equal(rows, torch.nonzero(eff >= 1 / 255).squeeze(1))


def test_after_the_freeze_the_default_culls_by_the_gaussians_own_opacity_only(tmp_path):
    """stdr.mask_after_freeze=false (the default): past the freeze the mask leaves opacity, so a row
    the mask switches off at t is rendered, and the rows kept are those whose own opacity reaches
    1/255; the culled render still equals the full one."""
    tr = _trained(tmp_path, "deform", 60, ["stdr.mask_after_freeze=false"])
    model = tr.state.model.eval()
    assert model.step >= model.plugin("stdr").freeze_at
    _switch_off_entries(model, 0.6, seed=3)
    with torch.no_grad():
        model.params["opacities"][::3] = -12.0  # a third of the rows under 1/255 by their own opacity
    frame = tr.scene.frames("test")[1]
    assert model.plugin("stdr").opacity_factor(model.context(model.step, t=frame.time)) is None
    img_a, _, _, _ = _render_and_grads(model, frame, cull=False)
    img_b, _, _, rows = _render_and_grads(model, frame, cull=True)
    own = torch.nonzero(torch.sigmoid(model.params["opacities"].detach()) >= 1 / 255).squeeze(1)
    assert torch.equal(rows, own) and own.numel() < model.num_gaussians
    assert (img_a - img_b).abs().max() <= 1e-6


def test_active_rows_compare_in_the_tensor_dtype():
    x = torch.tensor([0.0, 1 / 255 * 0.999, 1 / 255 * 1.001, 0.5])
    assert active_rows(x).tolist() == [2, 3]
    assert active_rows(torch.zeros(0)).numel() == 0


def test_densification_statistics_map_rendered_rows_to_the_model():
    """With rows, the strategy adds each rendered row's gradient and radius to its own
    Gaussian; with count_invisible=false, rows under opacity 1/255 are not counted as seen."""
    n = 6
    s = DensifyStrategy(refine_start=100, refine_stop=1000)
    full = s.initialize_state(n, 1.0)
    sub = s.initialize_state(n, 1.0)
    rows = torch.tensor([1, 3, 4])
    m_full = torch.zeros(n, 2, requires_grad=True)
    m_full.grad = torch.arange(12.0).reshape(n, 2)
    radii_full = torch.tensor([0, 2, 0, 3, 1, 0], dtype=torch.int32)
    m_sub = torch.zeros(3, 2, requires_grad=True)
    m_sub.grad = m_full.grad[rows].clone()
    s.step_post_backward({}, {}, full, 5, m_full, radii_full, 10, 10)
    s.step_post_backward({}, {}, sub, 5, m_sub, radii_full[rows], 10, 10, rows=rows)
    for k in ("grad2d", "count", "max_radii"):
        assert torch.equal(full[k], sub[k]), k
    assert full["count"].tolist() == [0, 1, 0, 1, 1, 0]
    lean = DensifyStrategy(refine_start=100, refine_stop=1000, count_invisible=False)
    st = lean.initialize_state(n, 1.0)
    opac = torch.tensor([0.5, 0.5, 0.001])  # the third rendered row cannot change a pixel
    lean.step_post_backward({}, {}, st, 5, m_sub, radii_full[rows], 10, 10, rows=rows, opacities=opac)
    assert st["count"].tolist() == [0, 1, 0, 1, 0, 0]
    with pytest.raises(ValueError, match="count_invisible=false needs the rendered opacities"):
        lean.step_post_backward({}, {}, st, 5, m_sub, radii_full[rows], 10, 10, rows=rows)


def test_cull_train_needs_densification_that_agrees(tmp_path):
    from stdr.train.trainer import Trainer
    with pytest.raises(ValueError, match="render.cull=train .* densify.count_invisible=false"):
        Trainer(_tiny(tmp_path, ["render.cull=train"]), tmp_path / "a")
    with pytest.raises(ValueError, match="render.cull='sometimes'"):
        Trainer(_tiny(tmp_path, ["render.cull=sometimes"]), tmp_path / "b")


@pytest.mark.slow
def test_training_with_culling_equals_training_without(tmp_path):
    """render.cull=train trains like render.cull=off with densify.count_invisible=false: the
    same Gaussians after STDR's freeze and densification, up to the float order of the
    network's gradient sums (the Gaussians' own gradients are equal)."""
    runs = {}
    for mode in ("off", "train"):
        d = tmp_path / mode
        tr = _trained(d, "deform", 60, ["densify.count_invisible=false", f"render.cull={mode}",
                                        "stdr.freeze_cleanup=0.01"])
        runs[mode] = tr
    a, b = runs["off"].state.model, runs["train"].state.model
    assert a.num_gaussians == b.num_gaussians
    for k in a.params:
        diff = (a.params[k] - b.params[k]).abs().max().item()
        assert diff <= 1e-4, (k, diff)
    # and culling did skip rows in training: after the freeze cleanup some entries are off
    frame = runs["train"].scene.frames("train")[0]
    _, rows = b.deformed_rows(frame.time, b.step, cull=True)
    assert rows is not None and rows.numel() < b.num_gaussians


@pytest.mark.slow
def test_evaluation_reports_the_gaussians_rendered_per_frame(tmp_path):
    from stdr.eval.evaluate import evaluate_model
    tr = _trained(tmp_path, "deform", 60)
    _switch_off_entries(tr.state.model, 0.6, seed=0)
    tr.state.model.cfg.render.cull = "eval"
    res = evaluate_model(tr.state.model, tr.scene.frames("test"))
    tr.state.model.cfg.render.cull = "off"
    ref = evaluate_model(tr.state.model, tr.scene.frames("test"))
    n = tr.state.model.num_gaussians
    assert res["render_cull"] == "eval" and ref["render_cull"] == "off"
    assert ref["active_gaussians_mean"] == ref["active_gaussians_max"] == n
    assert res["active_gaussians_mean"] <= res["active_gaussians_max"] < n
    assert res["psnr"] == pytest.approx(ref["psnr"], abs=1e-4)


