"""SC-GS, SP-GS and 4DGS deformation modules: maths against direct computations, identity starts,
alignment through densification, STDR conditioning, and end-to-end training."""
import json
import math

import pytest
import torch

from stdr.baselines.scgs import (FEATURE_KEY, ControlNodeDeformation, arap_energy, blend_translation,
                                       log_interp_schedule, skinning_weights)
from stdr.geometry import farthest_point_sampling, quat_multiply, quat_to_rotmat, so3_exp, so3_exp_quat, so3_log
from stdr.baselines.fourdgs import PAIRS, HexPlaneDeformation, HexPlaneField, sample_plane
from stdr.baselines.spgs import ASSOC_KEY, SuperpointDeformation
from stdr.baselines import BASELINES
from stdr.gaussians import init_params
from stdr.densify.strategy import duplicate, split
from stdr.baselines.base import deform_gaussians
from stdr.context import StepContext

torch.manual_seed(0)


def gaussians(n=400, seed=0):
    g = torch.Generator().manual_seed(seed)
    return init_params(torch.rand(n, 3, generator=g) * 2 - 1, sh_degree=1)


def random_rotations(n, seed=0):
    g = torch.Generator().manual_seed(seed)
    w = torch.randn(n, 3, generator=g, dtype=torch.float64)
    return so3_exp(w / w.norm(dim=-1, keepdim=True) * torch.rand(n, 1, generator=g, dtype=torch.float64) * 3.0)


# ----------------------------------------------------------------------------- SO(3), quaternions, FPS
def test_so3_exp_log_round_trip_and_properties():
    g = torch.Generator().manual_seed(1)
    w = torch.randn(500, 3, generator=g, dtype=torch.float64)
    w = w / w.norm(dim=-1, keepdim=True) * torch.rand(500, 1, generator=g, dtype=torch.float64) * 3.1
    w[:5] *= 1e-9  # the small-angle branch
    R = so3_exp(w)
    eye = torch.eye(3, dtype=torch.float64).expand_as(R)
    torch.testing.assert_close(R @ R.transpose(1, 2), eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(500, dtype=torch.float64))
    torch.testing.assert_close(so3_log(R), w, atol=1e-9, rtol=1e-7)
    # exp(w) rotates about w by |w| (Rodrigues, checked against the matrix exponential)
    from stdr.geometry import hat
    torch.testing.assert_close(R, torch.linalg.matrix_exp(hat(w)), atol=1e-12, rtol=0)
    # the quaternion of exp(w) gives the same matrix, and products compose
    torch.testing.assert_close(quat_to_rotmat(so3_exp_quat(w)), R, atol=1e-12, rtol=0)
    q1, q2 = so3_exp_quat(w[:100]), so3_exp_quat(w[100:200])
    torch.testing.assert_close(quat_to_rotmat(quat_multiply(q1, q2)), R[:100] @ R[100:200], atol=1e-12, rtol=0)


def test_farthest_point_sampling_is_greedy_max_min():
    x = torch.rand(300, 3, generator=torch.Generator().manual_seed(2))
    idx = farthest_point_sampling(x, 20, start=0)
    assert len(set(idx.tolist())) == 20 and idx[0] == 0
    for i in range(1, 20):  # each pick is the point farthest from those before it
        d = torch.cdist(x, x[idx[:i]]).min(1).values
        assert d[idx[i]] == d.max()


# ----------------------------------------------------------------------------- SC-GS
def test_skinning_weights_sum_to_one_and_match_the_formula():
    g = torch.Generator().manual_seed(3)
    d2, r, w = torch.rand(50, 3, generator=g), torch.rand(50, 3, generator=g) + 0.1, torch.randn(50, 3, generator=g)
    out = skinning_weights(d2, r, w)
    torch.testing.assert_close(out.sum(-1), torch.ones(50))
    raw = torch.exp(-d2 / (2 * r * r)) * torch.sigmoid(w) + 1e-7
    torch.testing.assert_close(out, raw / raw.sum(-1, keepdim=True))


def test_blend_skinning_reproduces_a_rigid_motion_exactly():
    """Every node with the same rotation R and translation T about their own positions, as
    blended in local frames, moves every point by exactly x -> R x + t for the matching t."""
    g = torch.Generator().manual_seed(4)
    N, K = 200, 3
    x = torch.randn(N, 3, generator=g, dtype=torch.float64)
    p = torch.randn(N, K, 3, generator=g, dtype=torch.float64)
    w = torch.rand(N, K, generator=g, dtype=torch.float64)
    w = w / w.sum(-1, keepdim=True)
    R = random_rotations(1, seed=5)[0]
    t = torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64)
    # node k moves to R p_k + t, i.e. T_k = R p_k + t - p_k, rotation R about itself
    T = (p @ R.T) + t - p
    out = blend_translation(x, p, R.expand(N, K, 3, 3), T, w)
    torch.testing.assert_close(out, x @ R.T + t, atol=1e-12, rtol=0)


def test_arap_energy_zero_for_rigid_and_positive_for_stretch():
    p = torch.rand(40, 3, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    from stdr.knn import knn
    _, nbr = knn(p, p, 6, exclude_self=True)
    R = random_rotations(1, seed=7)[0]
    assert arap_energy(p, p @ R.T + 1.0, nbr) < 1e-20
    stretch = p * torch.tensor([1.3, 1.0, 1.0], dtype=torch.float64)
    assert arap_energy(p, stretch, nbr) > 1e-4
    # by hand: the origin and the three unit points, each the others' neighbours, doubled in size.
    # The best rotation of a pure scaling is the identity, so each edge leaves a residual equal to
    # itself: squared lengths 1, 1, 1 (from the origin) and 1, 2, 2 (from each unit point), mean 18 / 12
    q = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64)
    full = torch.tensor([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
    assert arap_energy(q, 2 * q, full).item() == pytest.approx(1.5, abs=1e-12)


def test_arap_schedule_is_log_interpolated():
    steps, vals = [0, 5000, 10000, 20000, 20001], [1e-4, 1e-4, 1e-5, 1e-5, 0.0]
    assert log_interp_schedule(2000, steps, vals) == pytest.approx(1e-4)
    assert log_interp_schedule(7500, steps, vals) == pytest.approx(math.sqrt(1e-4 * 1e-5))
    assert log_interp_schedule(30000, steps, vals) == 0.0


def _scgs(**kw):
    args = dict(num_nodes=32, depth=3, width=32, skips=(1,), start_step=0, node_stage_end=5, main_warmup=0)
    args.update(kw)
    return ControlNodeDeformation(**args)


def test_scgs_starts_near_identity_and_switches_to_skinning():
    params = gaussians()
    m = _scgs()
    m.init_gaussians(params)
    m.before_step(StepContext(1, params))
    assert int(m.stage) == 1
    d = m(params, 0.3)
    assert d.means.abs().max() < 1e-3  # published small-init heads
    g = deform_gaussians(m, params, 0.3)  # node stage: isotropic, unrotated
    assert torch.allclose(g.scales[:, 0], g.scales[:, 1]) and torch.all(g.quats[:, 0] == 1)
    m.before_step(StepContext(5, params))  # resample nodes by FPS over trajectories
    assert int(m.stage) == 2
    nodes = m.nodes[:, :3]
    # nodes sit on Gaussians, radii are positive, weights start at 0.5
    gap = (nodes.detach()[:, None] - params["means"].detach()[None]).norm(dim=-1).min(1).values
    assert gap.max() == 0
    assert torch.all(m.node_log_radius.exp() > 0) and torch.all(m.node_weight == 0)
    g = deform_gaussians(m, params, 0.7)
    assert (g.means - params["means"]).abs().max() < 1e-3
    torch.testing.assert_close(g.scales, params["scales"].exp(), atol=1e-6, rtol=0)


def test_scgs_hyper_coordinates_and_radii_get_gradients():
    params = gaussians()
    m = _scgs(head_init_std=0.1)
    m.init_gaussians(params)
    m.before_step(StepContext(5, params))
    g = deform_gaussians(m, params, 0.4)
    g.means.square().sum().backward()
    assert params[FEATURE_KEY].grad.abs().sum() > 0
    assert m.node_log_radius.grad.abs().sum() > 0 and m.node_weight.grad.abs().sum() > 0
    assert m.regularizers(StepContext(6, params, t=0.4))["scgs_arap"] > 0  # random heads: the nodes do not move rigidly


# ----------------------------------------------------------------------------- SP-GS
def _spgs(**kw):
    args = dict(num_superpoints=20, depth=3, width=32, skips=(1,), start_step=0, head_init_std=1e-5)
    args.update(kw)
    return SuperpointDeformation(**args)


def test_spgs_superpoints_assignment_and_identity_start():
    params = gaussians()
    m = _spgs()
    m.init_gaussians(params)
    m.before_step(StepContext(0, params))  # FPS init
    assert bool(m.ready)
    idx, G, hard = m.assignment(params)
    torch.testing.assert_close(G.sum(-1), torch.ones(400))
    assert idx.shape == (400, 5)
    # logits start one-hot(nearest) * 0.9 + 0.1: the hard superpoint is the nearest
    nearest = torch.cdist(params["means"].detach(), m.centers).argmin(1)
    assert torch.equal(hard, nearest)
    g = deform_gaussians(m, params, 0.5)
    assert (g.means - params["means"]).abs().max() < 1e-3
    # each step the centres become the G-weighted means of their members' canonical means
    from stdr.ops import scatter_mean
    with torch.no_grad():
        params["means"].add_(0.05 * torch.randn(400, 3))
    idx, G, _ = m.assignment(params)
    expected, w = scatter_mean(params["means"].detach()[:, None].expand(-1, 5, -1), idx, G.detach(), 20)
    m.before_step(StepContext(1, params))
    keep = w > 1e-8
    assert keep.sum() > 10
    torch.testing.assert_close(m.centers[keep], expected[keep])


def test_spgs_rigid_transform_per_superpoint():
    """With nonzero heads, each Gaussian moves by its hard superpoint's exp(w) x + d exactly."""
    params = gaussians()
    m = _spgs(head_init_std=0.3)
    m.init_gaussians(params)
    m.before_step(StepContext(0, params))
    g = deform_gaussians(m, params, 0.25)
    d, w = m.superpoint_motion(0.25)
    _, _, hard = m.assignment(params)
    R = so3_exp(w)[hard]
    torch.testing.assert_close(g.means, (R @ params["means"][..., None])[..., 0] + d[hard], atol=1e-5, rtol=0)
    q = params["quats"] / params["quats"].norm(dim=-1, keepdim=True)
    torch.testing.assert_close(quat_to_rotmat(g.quats), R @ quat_to_rotmat(q), atol=1e-5, rtol=0)
    regs = m.regularizers(StepContext(1, params, t=0.25))
    assert set(regs) == {"spgs_re_xyz", "spgs_re_rot", "spgs_re_off"}
    sum(regs.values()).backward()
    assert params[ASSOC_KEY].grad.abs().sum() > 0  # the logits learn through the reconstruction terms


def test_per_gaussian_baseline_state_stays_aligned_through_densification():
    """SP-GS's association rows and SC-GS's hyper-coordinates follow their Gaussian through the
    strategy's duplicate and split (each row carries its Gaussian's id, as does the opacity)."""
    params = gaussians(100)
    ids = torch.arange(100.0)
    with torch.no_grad():
        params["opacities"].copy_(ids)
    params[ASSOC_KEY] = torch.nn.Parameter(ids[:, None].repeat(1, 10))
    params[FEATURE_KEY] = torch.nn.Parameter(ids[:, None].repeat(1, 8))
    opts = {k: torch.optim.Adam([p], lr=1e-3) for k, p in params.items()}
    mask = torch.zeros(100, dtype=torch.bool)
    mask[[3, 50]] = True
    duplicate(params, opts, {}, mask)
    split(params, opts, {}, torch.cat([mask, torch.zeros(2, dtype=torch.bool)]))
    n = params["means"].shape[0]
    assert n == 104
    for key in (ASSOC_KEY, FEATURE_KEY):
        assert params[key].shape[0] == n
        assert torch.equal(params[key][:, 0], params["opacities"].detach())
        assert torch.equal(params[key][:, -1], params["opacities"].detach())
    assert params[ASSOC_KEY][:, 0].tolist().count(3.0) == 3  # the kept copy and two children


# ----------------------------------------------------------------------------- 4DGS
def test_hexplane_sampling_equals_direct_bilinear():
    g = torch.Generator().manual_seed(8)
    plane = torch.rand(4, 5, 7, generator=g, dtype=torch.float64)  # C, H, W
    uv = torch.rand(100, 2, generator=g, dtype=torch.float64) * 2 - 1
    out = sample_plane(plane, uv)
    # align_corners: u = -1 is column 0, u = 1 is column W-1
    fx = (uv[:, 0] + 1) / 2 * (7 - 1)
    fy = (uv[:, 1] + 1) / 2 * (5 - 1)
    x0, y0 = fx.floor().long().clamp(max=5), fy.floor().long().clamp(max=3)
    ax, ay = fx - x0, fy - y0
    P = plane.permute(1, 2, 0)  # H, W, C
    ref = (P[y0, x0] * ((1 - ax) * (1 - ay))[:, None] + P[y0, x0 + 1] * (ax * (1 - ay))[:, None]
           + P[y0 + 1, x0] * ((1 - ax) * ay)[:, None] + P[y0 + 1, x0 + 1] * (ax * ay)[:, None])
    torch.testing.assert_close(out, ref, atol=1e-12, rtol=0)


def test_hexplane_feature_is_the_product_over_six_planes_and_time_spans_the_grid():
    f = HexPlaneField(base_res=4, multires=(1, 2), channels=3, time_res=6)
    pts = torch.rand(30, 3) * 2 - 1
    f.set_bounds(torch.tensor([[-1.0, -1, -1], [1.0, 1, 1]]))
    out = f(pts, 0.75)
    c = f.normalize(pts, 0.75)
    assert torch.allclose(c[:, 3], torch.full((30,), 0.5))  # t in [0, 1] -> 2t - 1 (full axis)
    assert torch.allclose(f.normalize(pts, 0.0)[:, 3], torch.full((30,), -1.0))
    for s, planes in enumerate(f.grids):
        ref = torch.ones(30, 3)
        for (i, j), plane in zip(PAIRS, planes):
            ref = ref * sample_plane(plane, c[:, [i, j]])
        torch.testing.assert_close(out[:, 3 * s:3 * s + 3], ref)
    # time planes start at 1, so at init the feature does not depend on t
    torch.testing.assert_close(f(pts, 0.1), f(pts, 0.9))


def test_hexplane_regularizers_match_their_definitions():
    f = HexPlaneField(base_res=4, multires=(1,), channels=2, time_res=5)
    regs = f.regularizers()
    assert regs["time_smooth"] == 0 and regs["l1_time"] == 0  # time planes start at 1
    with torch.no_grad():
        f.grids[0][2].copy_(torch.arange(5.0)[None, :, None].square().expand(2, 5, 4))  # xt plane: t^2 along H
    regs = f.regularizers()
    assert regs["time_smooth"].item() == pytest.approx(4.0)  # second difference of t^2 is 2
    assert regs["plane_tv"] > 0


def test_4dgs_starts_at_identity_and_applies_before_activation():
    params = gaussians()
    m = HexPlaneDeformation(base_res=8, channels=4, time_res=5, head_init_std=1e-5)
    m.init_gaussians(params)
    assert torch.all(m.grid.aabb[0] <= params["means"].min(0).values)
    g = deform_gaussians(m, params, 0.3)
    torch.testing.assert_close(g.means, params["means"], atol=1e-3, rtol=0)
    m2 = HexPlaneDeformation(base_res=8, channels=4, time_res=5, head_init_std=0.5)
    m2.init_gaussians(params)
    d = m2(params, 0.3)
    g2 = m2.apply_rule(params, d)
    torch.testing.assert_close(g2.scales, torch.exp(params["scales"] + d.scales))  # pre-activation
    groups = {gr["name"]: gr for gr in m2.param_groups()}
    assert groups["hexplane"]["lr_mult"] == 10.0
    n_grid = sum(p.numel() for p in groups["hexplane"]["params"])
    assert n_grid == sum(p.numel() for p in m2.grid.parameters())


def test_4dgs_time_resolution_follows_the_training_frames():
    from omegaconf import OmegaConf

    from stdr.baselines import HexPlaneBaselineConfig
    b = OmegaConf.structured(HexPlaneBaselineConfig)
    import numpy as np
    kw = HexPlaneDeformation.config_kwargs(b, 0, np.linspace(0, 1, 150))
    assert kw["time_res"] == 75  # bouncingballs: 150 frames -> 75, the published value
    b.hexplane.time_res = 33
    assert HexPlaneDeformation.config_kwargs(b, 0, np.linspace(0, 1, 150))["time_res"] == 33


@pytest.mark.parametrize("name", ["scgs", "spgs", "4dgs"])
def test_stdr_conditioning_starts_without_effect(name):
    """Cond columns start at zero weight: the separated field switching on changes nothing."""
    params = gaussians()
    if name == "scgs":
        m = _scgs(cond_dim=5, head_init_std=0.3)
    elif name == "spgs":
        m = _spgs(cond_dim=5, head_init_std=0.3)
    else:
        m = HexPlaneDeformation(base_res=8, channels=4, time_res=5, cond_dim=5, head_init_std=0.3)
    m.init_gaussians(params)
    m.before_step(StepContext(5, params))
    a = deform_gaussians(m, params, 0.4, torch.zeros(400, 5))
    b = deform_gaussians(m, params, 0.4, torch.randn(400, 5))
    torch.testing.assert_close(a.means, b.means)
    with pytest.raises(ValueError, match="cond"):
        deform_gaussians(m, params, 0.4, None)


# ----------------------------------------------------------------------------- end to end
# every registered baseline but deform, which tests/test_train.py trains and resumes
STAGED = sorted(set(BASELINES) - {"deform"})

@pytest.mark.slow
@pytest.mark.parametrize("name", STAGED)
def test_baseline_trains_on_the_embedded_scene_and_beats_its_static_warmup(tmp_path, name):
    from stdr.testing import tiny_config as _tiny

    from stdr.train.run import run_training as run
    cfg = _tiny(tmp_path, [f"experiment=embedded_{name}", "optim.iterations=900", "baseline.warmup=300",
                           "densify.refine_stop=700", "densify.grow_grad2d=1e-4", "optim.means_lr_max_steps=900",
                           "baseline.lr_max_steps=900", "baseline.scgs.node_stage_end=500",
                           "baseline.scgs.num_nodes=128", "baseline.spgs.num_superpoints=100",
                           "baseline.hexplane.base_res=32", "eval.lpips=false"])
    res = run(cfg, tmp_path / "run")
    hist = json.loads((tmp_path / "run" / "history.json").read_text())
    warm = [h for h in hist if h["tag"] == "static_warmup"][0]
    print(f"{name}: static warm-up {warm['psnr']:.2f} dB -> {res['psnr']:.2f} dB")
    assert res["psnr"] > warm["psnr"] + 1.5, (warm["psnr"], res["psnr"])
    # the model alone reloads from the checkpoint (no training data: HexPlane's time resolution,
    # STDR's knots and the bounds come from it) and reproduces its numbers
    from stdr.data.load import load_scene
    from stdr.eval.evaluate import evaluate_model
    from stdr.model import load_model
    model = load_model(tmp_path / "run" / "checkpoints" / "last.pt", device="cpu")
    again = evaluate_model(model, load_scene(cfg.data, ("test",)).frames("test"))
    assert again["psnr"] == pytest.approx(res["psnr"], abs=1e-4)


@pytest.mark.slow
@pytest.mark.parametrize("name", STAGED)
def test_resume_is_exact_across_the_baseline_stages(tmp_path, name):
    """Stopped after the warm-up (SP-GS superpoints placed, SC-GS in its node stage) and resumed
    past SC-GS's switch to skinning, a run ends bit-identical to an uninterrupted one."""
    from stdr.testing import tiny_config as _tiny

    from stdr.train.trainer import Trainer
    sched = [f"experiment=embedded_{name}", "baseline.warmup=20", "densify.refine_start=10",
             "densify.refine_every=10", "densify.prune_big_after=30", "train.checkpoint_every=0",
             "train.eval_at_warmup_end=false", "baseline.scgs.node_stage_end=40", "baseline.scgs.main_warmup=5",
             "baseline.scgs.num_nodes=64", "baseline.scgs.arap_steps=[0,10,20,30,31]",
             "baseline.spgs.num_superpoints=50", "baseline.hexplane.base_res=16"]
    a = Trainer(_tiny(tmp_path, sched + ["optim.iterations=60"]), tmp_path / "a")
    a.train()
    Trainer(_tiny(tmp_path, sched + ["optim.iterations=60", "train.stop_at=30"]), tmp_path / "b").train()
    b = Trainer(_tiny(tmp_path, sched + ["optim.iterations=60"]), tmp_path / "b")
    b.train()  # resumes at 30
    assert a.step == b.step == 60
    for k in a.state.model.params:
        assert torch.equal(a.state.model.params[k], b.state.model.params[k]), k
    for (ka, va), (kb, vb) in zip(a.state.model.deform.state_dict().items(), b.state.model.deform.state_dict().items()):
        assert torch.equal(va, vb), ka


def test_scgs_resampling_and_arap_use_the_given_conditioning():
    """With STDR's cond, node resampling follows the conditioned trajectories and ARAP regularizes
    the conditioned node motion (not the zero-cond one that is never rendered)."""
    params = gaussians()
    m = _scgs(cond_dim=4, head_init_std=0.1)
    m.init_gaussians(params)
    with torch.no_grad():  # make the cond inputs matter (they start at zero weight)
        for lin in m.net.modules():
            if isinstance(lin, torch.nn.Linear):
                lin.weight.normal_(0, 0.5, generator=torch.Generator().manual_seed(3))
    cond = torch.randn(400, 4, generator=torch.Generator().manual_seed(4))
    m.before_step(StepContext(1, params, cond=cond))
    m.resample_nodes(params, None)
    zero_nodes = m.nodes.detach().clone()
    m.resample_nodes(params, cond)
    assert not torch.equal(zero_nodes, m.nodes.detach())
    # by hand: FPS over the cond trajectories, with the module's generator state
    m2 = _scgs(cond_dim=4, head_init_std=0.1)
    m2.load_state_dict(m.state_dict())
    x = params["means"].detach()
    with torch.no_grad():
        traj = torch.cat([x + m2.node_deltas(x, t, cond)[0] for t in torch.linspace(0, 1, m2.trajectory_samples).tolist()], -1)
    g = torch.Generator().manual_seed(m.seed)
    farthest_point_sampling(torch.zeros(400, 3), m.m, g)  # the draw of the first (zero-cond) resampling
    idx = farthest_point_sampling(traj, m.m, g)
    torch.testing.assert_close(m.nodes.detach()[:, :3], x[idx])
    m.before_step(StepContext(5, params, cond=cond))  # skinning
    a_cond = m.regularizers(StepContext(6, params, t=0.4, cond=cond))["scgs_arap"]
    a_zero = m.regularizers(StepContext(6, params, t=0.4, cond=None))["scgs_arap"]
    assert a_cond.item() != pytest.approx(a_zero.item(), rel=1e-3)
    # by hand with the node conditioning the render uses
    idx, w = m.skinning(params)
    cond_n = m.node_conditioning(cond, idx, w)
    gen = torch.Generator().manual_seed(m.seed * 1_000_003 + 6)
    t1 = float(torch.rand((), generator=gen)) * (1.0 - m.arap_dt)
    p = m.nodes[:, :3].detach()
    from stdr.knn import knn
    _, nbr = knn(p, p, min(m.arap_k, m.m - 1), exclude_self=True)
    lam = log_interp_schedule(6 - m.node_stage_end, m.arap_steps, m.arap_weights)
    hand = lam * arap_energy(p + m.node_deltas(p, t1, cond_n)[0], p + m.node_deltas(p, t1 + m.arap_dt, cond_n)[0], nbr)
    torch.testing.assert_close(a_cond, hand)


def test_hexplane_sampling_equals_grid_sample_with_gradients():
    """The HexPlane field's gather / index_add sampling (and the time planes' row-blended line)
    equal F.grid_sample(align_corners=True, zeros padding), values and plane gradients,
    including points outside the plane and on its edges."""
    from stdr.baselines.fourdgs import _grid_sample, sample_plane, sample_plane_row
    g = torch.Generator().manual_seed(0)
    plane = torch.randn(8, 13, 17, generator=g, dtype=torch.float64, requires_grad=True)
    uv = torch.rand(500, 2, generator=g, dtype=torch.float64) * 2.6 - 1.3
    uv[:4] = torch.tensor([[-1.0, -1.0], [1.0, 1.0], [1.0, -1.0], [-1.0, 1.0]], dtype=torch.float64)
    w = torch.randn(500, 8, generator=g, dtype=torch.float64)
    for got, ref in ((sample_plane(plane, uv), _grid_sample(plane, uv)),) + tuple(
            (sample_plane_row(plane, uv[:, 0], v), _grid_sample(plane, torch.stack([uv[:, 0], torch.full_like(uv[:, 0], v)], -1)))
            for v in (-1.0, -0.41, 0.0, 1.0)):
        assert float((got - ref).abs().max()) <= 1e-12
        ga, = torch.autograd.grad((got * w).sum(), plane)
        gb, = torch.autograd.grad((ref * w).sum(), plane)
        assert float((ga - gb).abs().max()) <= 1e-12
    # the plane gradient is a serial index_add_ on the CPU: the same bits every time
    g1, = torch.autograd.grad((sample_plane(plane, uv) * w).sum(), plane)
    g2, = torch.autograd.grad((sample_plane(plane, uv) * w).sum(), plane)
    assert torch.equal(g1, g2)
    # a position that needs a gradient takes grid_sample itself
    uv_g = uv.clone().requires_grad_(True)
    assert sample_plane(plane, uv_g).grad_fn.name() != "_PlaneSampleBackward"
    assert sample_plane(plane, uv).grad_fn.name() == "_PlaneSampleBackward"
