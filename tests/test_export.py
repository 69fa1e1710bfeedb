"""stdr-export: the model at a time as a standard 3DGS PLY; read back, it renders what the model
renders at that time (deformation, STDR's mask on opacity, the active SH degree)."""
import pytest
import torch

from stdr.testing import tiny_config


@pytest.mark.slow
@pytest.mark.parametrize("name", ["deform_stdr", "4dgs"])
def test_an_exported_time_renders_like_the_model(tmp_path, name):
    from stdr.cli.view import export_main
    from stdr.model import load_model
    from stdr.gaussians import activate
    from stdr.io.ply import load_ply
    from stdr.train.trainer import Trainer
    sched = [f"experiment=embedded_{name}", "optim.iterations=30", "baseline.warmup=10", "densify.refine_start=5",
             "densify.refine_every=5", "train.checkpoint_every=0", "train.eval_at_warmup_end=false",
             "stdr.warmup_end=10", "stdr.freeze_at=20", "baseline.hexplane.base_res=16", "model.sh_interval=15",
             "stdr.mask_after_freeze=true"]  # the mask still gates opacity after the freeze: exported per time
    t = Trainer(tiny_config(tmp_path, [o for o in sched if not (o.startswith("stdr.") and "stdr" not in name)]),
                tmp_path / "run", splits=("train", "test"))
    t.train()
    export_main([str(tmp_path / "run"), "--times", "0", "0.37", "1", "--out", str(tmp_path / "ply")])
    model = load_model(tmp_path / "run" / "checkpoints" / "last.pt", device="cpu").eval()
    assert model.sh_degree(model.step) == 2  # 30 steps at one band per 15: bands of degree 3 are unused
    frame = t.scene.frames("test")[1]
    for time, file in ((0.0, "t_0.0000.ply"), (0.37, "t_0.3700.ply"), (1.0, "t_1.0000.ply")):
        p = load_ply(tmp_path / "ply" / file)
        assert p["means"].shape[0] == model.num_gaussians and torch.all(p["shN"][:, 8:] == 0)
        with torch.no_grad():
            want = model.render(frame.camera, time).image
            got = model.render_gaussians(activate(p), frame.camera).image
        # the file stores opacity as a logit, so a Gaussian whose alpha lies within float rounding of the
        # rasterizer's 1/255 cutoff may land on the other side of it (seen on an AMD EPYC: one pixel of
        # 4,096 by 8e-4). Such a crossing moves a few pixels by at most that Gaussian's alpha (< 2/255);
        # a wrong time, mask or SH band moves most of the image
        d = (got - want).abs().amax(-1)
        assert int((d > 1e-5).sum()) <= max(2, d.numel() // 1000) and d.max().item() < 2 / 255, \
            (time, int((d > 1e-5).sum()), d.max().item())
    if "stdr" in name:  # the mask is in the exported opacity: it differs between times
        a, b = load_ply(tmp_path / "ply" / "t_0.0000.ply"), load_ply(tmp_path / "ply" / "t_1.0000.ply")
        assert not torch.equal(a["opacities"], b["opacities"])


def test_a_time_outside_the_run_is_an_error(tmp_path):
    from stdr.io.export import export_times
    with pytest.raises(ValueError, match=r"--times 1.5: the model.s times run over \[0, 1\]"):
        export_times(object(), [1.5], tmp_path)


def test_times_that_round_alike_get_names_of_their_own_and_a_repeated_time_is_refused(tmp_path):
    from stdr.io.export import export_times, time_names
    assert time_names([0, 0.5, 1]) == ["t_0.0000.ply", "t_0.5000.ply", "t_1.0000.ply"]
    assert time_names([0.12341, 0.12344, 0.9]) == ["t_0.12341.ply", "t_0.12344.ply", "t_0.90000.ply"]
    a, b = 0.1, 0.1 + 1e-16 * 3  # differ in the last bits only
    assert a != b and len(set(time_names([a, b]))) == 2
    with pytest.raises(ValueError, match=r"--times 0.5: given more than once"):
        export_times(object(), [0.5, 0.25, 0.5], tmp_path)
