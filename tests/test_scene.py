import pytest
import torch
from torch import nn

from stdr.gaussians import init_params
from stdr.knn import knn
from stdr.io.ply import load_ply, save_ply
from stdr.densify.strategy import DensifyStrategy, duplicate, remove, split


def _params(n=20, seed=0):
    g = torch.Generator().manual_seed(seed)
    p = init_params(torch.rand(n, 3, generator=g), torch.rand(n, 3, generator=g), sh_degree=3)
    with torch.no_grad():
        p["shN"].normal_(generator=g)
        p["quats"].normal_(generator=g)
    # an extra per-Gaussian attribute, like STDR's N x K mask: each row tagged with its identity
    p["mask"] = nn.Parameter(torch.arange(n, dtype=torch.float32)[:, None].repeat(1, 5))
    return p


def test_ply_roundtrip_with_extra_attribute(tmp_path):
    p = _params()
    save_ply(p, tmp_path / "a.ply")
    q = load_ply(tmp_path / "a.ply", extra_keys={"mask": (5,)})
    for k in p:
        assert torch.equal(p[k].detach(), q[k].detach()), k
    text = (tmp_path / "a.ply").read_bytes()[:2000].decode("latin-1")
    for prop in ("property float x", "property float f_dc_0", "property float f_rest_44",
                 "property float opacity", "property float scale_2", "property float rot_3"):
        assert prop in text


def test_ply_rejects_non_3dgs(tmp_path):
    from plyfile import PlyData, PlyElement
    import numpy as np
    import pytest
    arr = np.zeros(3, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(tmp_path / "b.ply"))
    with pytest.raises(ValueError, match="missing properties"):
        load_ply(tmp_path / "b.ply")


def _optimizers(p):
    return {k: torch.optim.Adam([v], lr=1e-3) for k, v in p.items()}


def _step(p, opts):
    loss = sum((v.float() ** 2).sum() * (i + 1) for i, v in enumerate(p.values()))
    loss.backward()
    for o in opts.values():
        o.step()
        o.zero_grad()


def _check_aligned(p, opts, state):
    n = p["means"].shape[0]
    for k, v in p.items():
        assert v.shape[0] == n, k
        st = opts[k].state[v]
        assert opts[k].param_groups[0]["params"][0] is v
        assert st["exp_avg"].shape == v.shape and st["exp_avg_sq"].shape == v.shape
    for k, v in state.items():
        if torch.is_tensor(v):
            assert v.shape[0] == n, k


def test_duplicate_split_remove_keep_rows_and_adam_state_aligned():
    p = _params(12)
    opts = _optimizers(p)
    _step(p, opts)
    state = {"grad2d": torch.arange(12.0), "count": torch.ones(12)}
    avg_before = {k: opts[k].state[p[k]]["exp_avg"].clone() for k in p}
    sh_before = p["sh0"].detach().clone()
    mask_before = p["mask"].detach().clone()

    dup = torch.zeros(12, dtype=torch.bool)
    dup[[1, 5]] = True
    duplicate(p, opts, state, dup)
    _check_aligned(p, opts, state)
    assert torch.equal(p["mask"][12:], mask_before[[1, 5]])  # children inherit parent rows
    assert torch.equal(p["mask"][:12], mask_before)
    assert torch.equal(opts["sh0"].state[p["sh0"]]["exp_avg"][:12], avg_before["sh0"])
    assert (opts["sh0"].state[p["sh0"]]["exp_avg"][12:] == 0).all()

    spl = torch.zeros(14, dtype=torch.bool)
    spl[[0, 13]] = True  # an original and a clone
    split(p, opts, state, spl, generator=torch.Generator().manual_seed(0))
    _check_aligned(p, opts, state)
    assert p["means"].shape[0] == 16
    assert torch.equal(p["mask"][-4:], mask_before[[0, 5, 0, 5]])
    assert torch.allclose(p["sh0"][-4:-2], torch.stack([sh_before[0], sh_before[5]]))
    parent_scale = torch.exp(p["scales"][-1]).detach()
    assert torch.allclose(torch.exp(p["scales"][-3]).detach(), parent_scale)

    rm = torch.zeros(16, dtype=torch.bool)
    rm[:3] = True
    kept_mask = p["mask"][3:, 0].detach().clone()
    remove(p, opts, state, rm)
    _check_aligned(p, opts, state)
    assert torch.equal(p["mask"][:, 0], kept_mask)
    _step(p, opts)  # the optimizer still runs on the edited tensors


def test_strategy_refine_grows_prunes_and_caps():
    torch.manual_seed(0)
    p = _params(50)
    opts = _optimizers(p)
    _step(p, opts)
    strat = DensifyStrategy(grow_grad2d=1e-3, grow_scale3d=0.05, refine_start=0, refine_every=1,
                            reset_every=0, max_gaussians=60, prune_opa=0.0)
    state = strat.initialize_state(50, scene_extent=1.0)
    with torch.no_grad():
        p["scales"][:25] = -6.0   # small: cloned
        p["scales"][25:] = -1.0   # large: split
    means2d = torch.zeros(50, 2, requires_grad=True)
    means2d.grad = torch.zeros(50, 2)
    means2d.grad[:, 0] = torch.linspace(0, 1e-3, 50)  # NDC grad = 0.5 * W * g
    radii = torch.full((50,), 3, dtype=torch.int32)
    info = strat.step_post_backward(p, opts, state, 1, means2d, radii, width=10, height=10)
    _check_aligned(p, opts, state)
    # gradients above threshold: 0.5*10*g > 1e-3 -> g > 2e-4: 40 candidates, but the cap allows 10
    assert info["cloned"] + info["split"] == 10
    assert p["means"].shape[0] == 60
    assert info["split"] == 10  # the largest gradients are the large Gaussians


def test_strategy_target_count_grows_on_its_schedule():
    # lean densification: no gradient threshold, the count follows n0 + (target - n0) * p exactly
    torch.manual_seed(0)
    p = _params(40)
    opts = _optimizers(p)
    _step(p, opts)
    strat = DensifyStrategy(grow_grad2d=1.0, refine_start=0, refine_stop=401, refine_every=100,
                            reset_every=0, prune_opa=0.0, target_gaussians=100)
    state = strat.initialize_state(40, scene_extent=1.0)
    assert [strat.target_at(s, 40) for s in (100, 200, 300, 400)] == [55, 70, 85, 100]
    counts = []
    for step in (100, 200, 300, 400, 500):
        n = p["means"].shape[0]
        means2d = torch.zeros(n, 2, requires_grad=True)
        means2d.grad = torch.rand(n, 2) * 1e-6  # far below grow_grad2d: only the schedule grows it
        radii = torch.full((n,), 3, dtype=torch.int32)
        radii[:5] = 0  # never seen: never chosen
        strat.step_post_backward(p, opts, state, step, means2d, radii, width=10, height=10)
        _check_aligned(p, opts, state)
        counts.append(p["means"].shape[0])
    assert counts == [55, 70, 85, 100, 100]  # step 500 is past refine_stop
    # a model above its schedule does not grow, and pruning is left as it was
    strat2 = DensifyStrategy(refine_start=0, refine_stop=401, refine_every=100, reset_every=0, prune_opa=0.0,
                             target_gaussians=30)
    st2 = strat2.initialize_state(100, scene_extent=1.0)
    means2d = torch.zeros(100, 2, requires_grad=True)
    means2d.grad = torch.ones(100, 2)
    info = strat2.step_post_backward(p, opts, st2, 100, means2d, torch.full((100,), 3, dtype=torch.int32), 10, 10)
    assert info["cloned"] + info["split"] == 0 and p["means"].shape[0] == 100
    with pytest.raises(ValueError, match="densify.target_gaussians=50 is above densify.max_gaussians=40"):
        DensifyStrategy(target_gaussians=50, max_gaussians=40)


def test_knn_matches_brute_force():
    x = torch.rand(300, 3, generator=torch.Generator().manual_seed(0))
    d, i = knn(x, x, 4, exclude_self=True, chunk=64)
    full = torch.cdist(x, x).square()
    full.fill_diagonal_(float("inf"))
    dd, ii = torch.topk(full, 4, largest=False)
    assert torch.equal(i, ii) and torch.allclose(d, dd, atol=1e-6)


def test_the_size_prune_warns_when_it_would_remove_most_of_the_model_and_the_probe_reads_it():
    """After prune_big_after a densification that would remove more than half the model for size
    warns (what budget=gpu does at step 1600); studies/size_prune.py parses that very message."""
    import warnings

    from helpers import load_script
    from pathlib import Path
    probe = load_script(Path(__file__).resolve().parents[1] / "studies" / "size_prune.py", "size_prune")
    for big_rows, warns in ((30, True), (20, False)):
        torch.manual_seed(0)
        p = _params(50)
        opts = _optimizers(p)
        _step(p, opts)
        strat = DensifyStrategy(grow_grad2d=1.0, refine_start=0, refine_every=100, reset_every=0, prune_opa=0.0,
                                prune_big_after=100)
        state = strat.initialize_state(50, scene_extent=1.0)
        with torch.no_grad():
            p["scales"][:] = -6.0
            p["scales"][:big_rows] = 0.0  # exp(0) = 1 > 0.1 x extent
        means2d = torch.zeros(50, 2, requires_grad=True)
        means2d.grad = torch.zeros(50, 2)
        with warnings.catch_warnings(record=True) as got:
            warnings.simplefilter("always")
            info = strat.step_post_backward(p, opts, state, 200, means2d, torch.full((50,), 3, dtype=torch.int32), 10, 10)
        assert info["pruned"] == big_rows and p["means"].shape[0] == 50 - big_rows
        msgs = [str(w.message) for w in got if issubclass(w.category, RuntimeWarning)]
        assert bool(msgs) == warns, msgs
        if warns:
            assert probe.WARNING.findall("\n".join(msgs)) == [("200", str(big_rows), "50")]


def test_prune_scale2d_null_turns_the_screen_size_prune_off_and_keeps_the_world_size_prune():
    """densify.prune_scale2d=null (budget=gpu and budget=paper): a Gaussian big on screen only is
    kept, one big in the world is still pruned; with 20 px the screen-big one goes too."""
    for scale2d, pruned in ((None, 1), (20.0, 2)):
        torch.manual_seed(0)
        p = _params(10)
        opts = _optimizers(p)
        _step(p, opts)
        strat = DensifyStrategy(grow_grad2d=1.0, refine_start=0, refine_every=100, reset_every=0, prune_opa=0.0,
                                prune_big_after=100, prune_scale2d=scale2d)
        state = strat.initialize_state(10, scene_extent=1.0)
        with torch.no_grad():
            p["scales"][:] = -6.0
            p["scales"][0] = 0.0  # row 0: big in the world (exp(0) = 1 > 0.1 x extent)
        means2d = torch.zeros(10, 2, requires_grad=True)
        means2d.grad = torch.zeros(10, 2)
        radii = torch.full((10,), 3, dtype=torch.int32)
        radii[1] = 50  # row 1: small in the world, 50 px on screen
        kept_row1 = p["means"][1].detach().clone()
        info = strat.step_post_backward(p, opts, state, 200, means2d, radii, 400, 400)
        assert info["pruned"] == pruned
        assert any(torch.equal(m, kept_row1) for m in p["means"].detach()) == (scale2d is None)


def test_budget_gpu_has_no_screen_size_prune_and_the_other_budgets_keep_theirs():
    """budget=gpu takes size_prune_val's decision (no screen-size prune, every baseline); the other
    budgets keep 20 px (their tables used it; budget=paper's is not measured)."""
    from stdr.store import compose_config
    from pathlib import Path
    dec = (Path(__file__).resolve().parents[1] / "research" / "measurements" / "size_prune_val" / "table.md").read_text()
    assert "Decision: **ws_1500**" in dec  # the preset follows the generated decision
    for budget, expected in (("gpu", None), ("paper", 20.0), ("cpu", 20.0), ("cpu_long", 20.0), ("demo", 20.0)):
        for exp in ("dnerf_deform", "dnerf_scgs", "dnerf_spgs", "dnerf_4dgs"):
            cfg = compose_config([f"experiment={exp}", f"budget={budget}"])
            assert cfg.densify.prune_scale2d == expected, (budget, exp)
