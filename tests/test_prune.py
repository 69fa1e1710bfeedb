"""Contribution pruning (stdr/densify/prune.py): the schedule keys, the ranking, the significance
matrix against the rendered opacity, state kept aligned through an event, and exact resume."""
import pytest
import torch
from omegaconf import OmegaConf

from stdr.densify.prune import (PruneConfig, prune_steps, ranking, seen_per_frame, select_pruned,
                              significance)
from stdr.testing import tiny_config

SCHED = ["optim.iterations=60", "baseline.warmup=20", "densify.refine_start=10", "densify.refine_every=10",
         "densify.reset_every=0", "densify.refine_stop=40", "densify.prune_big_after=30",
         "train.checkpoint_every=0", "train.eval_at_warmup_end=false"]


def _cfg(**kw):
    return OmegaConf.structured(PruneConfig(**kw))


def test_prune_steps_from_steps_fractions_and_refine_stop():
    assert prune_steps(_cfg(share=0.0), 2000, 1500) == []  # off
    assert prune_steps(_cfg(share=0.3), 2000, 1500) == [1500, 1800]  # the default at: refine_stop, 0.9
    assert prune_steps(_cfg(share=0.3, at=["0.5", "700", "700", "refine_stop"]), 2000, 1500) == [700, 1000, 1500]


@pytest.mark.parametrize("kw, match", [
    ({"share": 1.0}, r"prune.share=1.0: use a fraction in \[0, 1\)"),
    ({"share": -0.1}, "prune.share"),
    ({"share": 0.2, "time_weight": -1.0}, "prune.time_weight"),
    ({"share": 0.2, "at": ["soon"]}, "prune.at entry 'soon'"),
    ({"share": 0.2, "at": ["2000"]}, r"resolves to step 2000, outside \[1, optim.iterations=2000\)"),
    ({"share": 0.2, "at": ["1.5"]}, "prune.at entry '1.5'"),
])
def test_bad_prune_keys_are_named(kw, match):
    with pytest.raises(ValueError, match=match):
        prune_steps(_cfg(**kw), 2000, 1500)


def test_ranking_and_selection():
    # rows: 0 strong everywhere, 1 weak everywhere, 2 as weak in total as 1 but seen at one time only,
    # 3 never seen, 4 strong at one time only
    S = torch.tensor([[5.0, 5.0, 5.0, 5.0],
                      [0.5, 0.5, 0.5, 0.5],
                      [2.0, 0.0, 0.0, 0.0],
                      [0.0, 0.0, 0.0, 0.0],
                      [9.0, 0.0, 0.0, 0.0]])
    total = S.sum(1)
    assert torch.equal(ranking(S), total)
    assert select_pruned(ranking(S), 0.4).nonzero().flatten().tolist() == [1, 3]  # the two smallest totals
    # seen at one time of four, and weakly: row 2 now goes before row 1 (seen at every time)
    assert select_pruned(ranking(S, time_weight=1.0), 0.4).nonzero().flatten().tolist() == [2, 3]
    assert not select_pruned(ranking(S), 0.0).any()
    assert select_pruned(ranking(S[:1]), 0.99).sum() == 0  # never the whole model
    assert seen_per_frame(S) == pytest.approx((4 / 5 + 2 / 5 + 2 / 5 + 2 / 5) / 4)  # rows seen per column


@pytest.mark.parametrize("backend", ["cpu", "reference"])
def test_significance_sums_to_the_rendered_opacity(tmp_path, backend):
    """Per frame, the scores of all Gaussians add up to the image's accumulated opacity (blending
    weights sum to 1 - T per pixel): S checked against the model's own render."""
    from stdr.train.trainer import Trainer
    tr = Trainer(tiny_config(tmp_path, SCHED + [f"render.backend={backend}", "train.stop_at=25"]), tmp_path / "r")
    tr.train()
    frames = tr.scene.frames("train")[:3]
    S, times = significance(tr.state.model, frames)
    assert S.shape == (tr.state.model.num_gaussians, 3) and times.numel() == 3
    for f in frames:
        col = int((times == f.time).nonzero())
        out = tr.state.model.render(f.camera, f.time, cull=False)
        want = float(out.alpha.detach().sum())
        assert want > 1.0
        assert float(S[:, col].sum()) == pytest.approx(want, rel=1e-4)
    assert (S >= 0).all()


def test_an_event_removes_the_least_significant_rows_and_keeps_state_aligned(tmp_path, monkeypatch):
    import stdr.densify.prune as prune_mod
    import stdr.densify.strategy as strategy_mod
    from stdr.train.trainer import Trainer
    seen = {}
    score, remove = prune_mod.significance, strategy_mod.remove

    def spy_score(*a, **k):
        S, times = score(*a, **k)
        seen["S"] = S.clone()
        return S, times

    def spy_remove(params, optimizers, state, mask):
        seen["params"] = {k: v.detach().clone() for k, v in params.items()}
        seen["mask"] = mask.clone()
        return remove(params, optimizers, state, mask)
    monkeypatch.setattr(prune_mod, "significance", spy_score)
    monkeypatch.setattr(prune_mod, "remove", spy_remove)  # where the prune event looks it up
    tr = Trainer(tiny_config(tmp_path, SCHED + ["prune.share=0.25", "prune.at=[30]", "train.stop_at=30"]),
                 tmp_path / "r")
    tr.train()
    assert tr.state.model.schedule.prune_steps == [30] and not tr.state.prune_log  # due once 30 steps are done
    ev = prune_mod.prune_event(tr.state.model, tr.scene.frames("train"), tr.state.optimizers, tr.state.strategy_state, tr.cfg.prune, 30)
    assert ev["step"] == 30
    assert ev["after"] == ev["before"] - int(0.25 * ev["before"])
    S, mask = seen["S"], seen["mask"]
    total = S.sum(1)
    assert int(mask.sum()) == ev["before"] - ev["after"]
    assert total[mask].max() <= total[~mask].min()  # the least significant went
    n = tr.state.model.num_gaussians
    assert n == ev["after"]
    for k, p in tr.state.model.params.items():  # the kept rows, unchanged and in order
        assert torch.equal(p.detach(), seen["params"][k][~mask]), k
        st = tr.state.optimizers[k].state.get(p) if k in tr.state.optimizers else None
        for sk, sv in (st or {}).items():
            if torch.is_tensor(sv) and sv.dim() > 0:
                assert sv.shape[0] == n, (k, sk)
    for k in ("grad2d", "count", "max_radii"):
        assert tr.state.strategy_state[k].shape[0] == n, k
    assert ev["seen_after"] == pytest.approx(seen_per_frame(S[~mask]))


def test_the_loop_prunes_once_the_steps_are_done_and_logs_it(tmp_path):
    from stdr.train.trainer import Trainer
    tr = Trainer(tiny_config(tmp_path, SCHED + ["prune.share=0.25", "prune.at=[30]", "train.stop_at=30"]),
                 tmp_path / "r")
    tr.train()
    n = tr.state.model.num_gaussians
    logs = tr.train_step()  # the 31st step: the event first, then the step on the smaller model
    assert [e["step"] for e in tr.state.prune_log] == [30] and tr.state.prune_log[0]["before"] == n
    assert logs["densify"]["pruned_by_score"] == n - tr.state.prune_log[0]["after"]
    assert tr.state.model.num_gaussians == tr.state.prune_log[0]["after"]  # (no refinement at step 31)
    assert "prune" in tr.profile_summary()["seconds"]
    tr.train_step()
    assert len(tr.state.prune_log) == 1  # once


def test_resume_across_a_pruning_event_is_exact(tmp_path):
    from stdr.train.trainer import Trainer
    extra = ["prune.share=0.2", "prune.at=[refine_stop,50]"]
    a = Trainer(tiny_config(tmp_path, SCHED + extra), tmp_path / "a")
    a.train()
    assert [e["step"] for e in a.state.prune_log] == [40, 50]
    b1 = Trainer(tiny_config(tmp_path, SCHED + extra + ["train.stop_at=45"]), tmp_path / "b")
    b1.train()
    b2 = Trainer(tiny_config(tmp_path, SCHED + extra), tmp_path / "b")
    b2.train()
    assert [e["step"] for e in b2.state.prune_log] == [40, 50]
    assert a.state.model.num_gaussians == b2.state.model.num_gaussians
    for k in a.state.model.params:
        assert torch.equal(a.state.model.params[k], b2.state.model.params[k]), k


def test_a_run_branched_from_a_checkpoint_at_the_event_prunes_as_an_uninterrupted_one(tmp_path):
    """The compactness study's shortcut: a run without pruning, checkpointed at the event's step,
    continued with prune.* keys, gives the run trained with them from the start."""
    import shutil

    from stdr.train.trainer import Trainer
    extra = ["prune.share=0.3", "prune.at=[40]"]
    a = Trainer(tiny_config(tmp_path, SCHED + extra), tmp_path / "a")
    a.train()
    base = Trainer(tiny_config(tmp_path, SCHED + ["train.stop_at=40"]), tmp_path / "base")
    base.train()
    shutil.copytree(tmp_path / "base" / "checkpoints", tmp_path / "b" / "checkpoints")
    b = Trainer(tiny_config(tmp_path, SCHED + extra), tmp_path / "b")
    b.train()
    assert [e["step"] for e in b.state.prune_log] == [40] and a.state.model.num_gaussians == b.state.model.num_gaussians
    for k in a.state.model.params:
        assert torch.equal(a.state.model.params[k], b.state.model.params[k]), k


def test_stdr_tool_compact_prunes_a_trained_run_into_a_new_one(tmp_path):
    import json

    from stdr.train.run import run_training as run
    from stdr.tools.compact_run import compact, main
    cfg = tiny_config(tmp_path, SCHED + ["stdr=on", "eval.fps_repeats=1"])
    run(cfg, tmp_path / "run")
    before = json.loads((tmp_path / "run" / "metrics.json").read_text())["test"]
    res = compact(tmp_path / "run", share=0.4, steps=10, mask_bits=8)
    out = tmp_path / "run_compact"
    m = json.loads((out / "metrics.json").read_text())["test"]
    assert m["iterations"] == 70 and m["prune"][0]["step"] == 60
    assert m["num_gaussians"] == before["num_gaussians"] - int(0.4 * before["num_gaussians"]) == res["num_gaussians"]
    assert m["seen_per_frame"] is not None and 0 < m["seen_per_frame"] <= 1
    saved = (out / "config.yaml").read_text()
    # the run is deform+STDR (stdr=on): named embedded_deform_stdr, its compact copy after it
    assert "prune:" in saved and "share: 0.4" in saved and "name: embedded_deform_stdr_compact" in saved
    # the original run is untouched, and the phases it crossed stayed where they were
    assert json.loads((tmp_path / "run" / "metrics.json").read_text())["test"] == before
    assert m["stdr"]["freeze_at"] == before["stdr"]["freeze_at"]
    assert before["stdr"]["mask_bits"] == 32 and m["stdr"]["mask_bits"] == 8  # quantized at the first fine-tuning step
    # and its compact model file, measured against the full model on the run's split, opens in the viewer's loader
    packed = json.loads((out / "pack.json").read_text())
    assert (out / "model.stdrc").is_file() and packed["bytes"] < packed["full_bytes"] and packed["split"] == "test"
    assert packed["spec"]["stdr_mask"] == "raw" and abs(packed["delta_psnr"]) < 0.05
    from stdr.view.core import open_run
    view = open_run(out, device="cpu", model_file=out / "model.stdrc")
    assert view.model.num_gaussians == m["num_gaussians"] and view.model.params["stdr_mask"].dtype == torch.uint8
    with pytest.raises(FileExistsError, match="run_compact exists"):
        compact(tmp_path / "run", share=0.4, steps=10)
    with pytest.raises(SystemExit, match="--share 1.5"):
        main([str(tmp_path / "run"), "--share", "1.5"])
