import pytest

from stdr.eval.table import collect, latex, markdown


def _row(method, scene, psnr, seed=0, width=128, lpips=0.1):
    return {"method": method, "scene": scene, "split": "test", "run_dir": f"{method}/{scene}/{seed}",
            "metrics": {"psnr": psnr, "ssim": 0.9, "lpips": lpips, "fps": 10.0, "num_gaussians": 1000,
                        "train_seconds": 60.0},
            "config": {"seed": seed, "baseline": {"width": width}}}


def test_table_means_and_seed_averaging():
    t = collect([_row("deform", "a", 30.0), _row("deform", "b", 20.0), _row("deform", "a", 32.0, seed=1),
                 _row("deform+STDR", "a", 31.0), _row("deform+STDR", "b", 21.0, lpips=None)])
    assert t["cells"]["deform"]["a"]["psnr"] == pytest.approx(31.0)   # two seeds averaged
    assert t["cells"]["deform"]["a"]["n_runs"] == 2
    assert t["means"]["deform"]["psnr"] == pytest.approx(25.5)        # mean over scenes
    assert t["means"]["deform+STDR"]["lpips"] is None                 # incomplete -> no mean
    md = markdown(t)
    assert "| deform | 31.00 |" in md and "| deform+STDR | 31.00 |" in md
    assert "\\multicolumn{3}{c}{mean}" in latex(t)


def test_table_refuses_to_mix_different_configs():
    with pytest.raises(ValueError, match=r"differ in \['baseline.width'\]"):
        collect([_row("deform", "a", 30.0), _row("deform", "a", 31.0, seed=1, width=256)])
