"""stdr-tool commands on synthetic run folders."""
import json

import torch


def _fake_run(folder, fmt: int, stdr: bool):
    """A run folder as training leaves it: TensorBoard scalars and a final checkpoint."""
    from torch.utils.tensorboard import SummaryWriter
    w = SummaryWriter(str(folder / "tb"))
    for step, (n, c, s, pr) in {100: (50, 5, 2, 0), 200: (60, 8, 4, 2), 300: (58, 0, 0, 2)}.items():
        w.add_scalar("gaussians/count", n, step)
        w.add_scalar("densify/cloned", c, step)
        w.add_scalar("densify/split", s, step)
        w.add_scalar("densify/pruned", pr, step)
    w.close()
    # peak opacities: 0.001 (never reaches 1/255), 0.003, 0.01, 0.5 x 14
    peak = torch.tensor([0.001, 0.003, 0.01] + [0.5] * 14)
    params = {"opacities": torch.logit(peak)}
    if stdr:  # the same peaks reached through a mask whose largest column is 1 - 1e-6
        params["opacities"] = torch.logit(peak / (1 - 1e-6))
        params["stdr_mask"] = torch.full((17, 4), -5.0)
        params["stdr_mask"][:, 2] = torch.logit(torch.tensor(1 - 1e-6))
    (folder / "checkpoints").mkdir(parents=True)
    torch.save({"model": {"params": params}} if fmt == 2 else {"params": params}, folder / "checkpoints" / "last.pt")


def test_densify_trace_reads_both_checkpoint_formats_and_counts_invisible_gaussians(tmp_path, capsys):
    from stdr.tools.densify_trace import main
    runs = []
    for fmt, stdr in ((1, False), (2, True)):
        r = tmp_path / f"f{fmt}" / "scene"
        _fake_run(r, fmt, stdr)
        runs.append(str(r))
    main([*runs, "--windows", "0,150,300", "--out", str(tmp_path / "trace")])
    data = json.loads((tmp_path / "trace.json").read_text())
    for label in ("f1/scene", "f2/scene"):
        r = data["runs"][label]
        assert [(w["count"], w["cloned"], w["split"], w["pruned"]) for w in r["windows"]] == [(50, 5, 2, 0), (58, 8, 4, 4)]
        assert r["peak_opacity"]["n"] == 17 and r["peak_opacity"]["invisible"] == 2  # 0.001 and 0.003 < 1/255
        assert abs(r["peak_opacity"]["fraction_below"] - 3 / 17) < 1e-6  # a float32 mean
    assert "never ≥ 1/255" in (tmp_path / "trace.md").read_text()
