"""scripts/gpu_table.py: the budget=gpu D-NeRF table from a GPU queue's archives."""
import io
import json
import tarfile
from pathlib import Path

import pytest
from helpers import load_script

ROOT = Path(__file__).resolve().parents[1]


def _module():
    return load_script(ROOT / "scripts" / "gpu_table.py", "gpu_table")


def _archive(path: Path, runs: dict, extra=()):
    with tarfile.open(path, "w:gz") as tar:
        for rid, (exp, scene, psnr, budget, *seed) in runs.items():
            files = {"metrics.json": json.dumps({"test": {"psnr": psnr, "ssim": 0.98, "lpips": 0.02, "train_seconds": 80.0,
                                                          "conventions": {"device_name": "NVIDIA H100"},
                                                          "code": {"commit": "abc1234"}}}),
                     "config.yaml": f"experiment: {exp}\nbudget: {budget}\nseed: {seed[0] if seed else 0}\ndata:\n  name: {scene}\n"}
            for name, text in files.items():
                b = text.encode()
                info = tarfile.TarInfo(f"{rid}/{name}")
                info.size = len(b)
                tar.addfile(info, io.BytesIO(b))
        for name in extra:
            info = tarfile.TarInfo(name)
            info.size = 1
            tar.addfile(info, io.BytesIO(b"x"))


def test_runs_from_archives_make_the_stamped_table_with_the_paper_beside(tmp_path):
    gt = _module()
    _archive(tmp_path / "a.tgz", {"dnerf_deform__jumpingjacks__s0": ("dnerf_deform", "jumpingjacks", 36.0, "gpu"),
                                  "dnerf_deform__standup__s0": ("dnerf_deform", "standup", 38.0, "gpu")})
    _archive(tmp_path / "b.tgz", {"dnerf_deform_stdr__jumpingjacks__s0": ("dnerf_deform_stdr", "jumpingjacks", 36.5, "gpu")})
    for a in ("a.tgz", "b.tgz"):
        gt.add(tmp_path / a, tmp_path / "t")
    text, data = gt.table(tmp_path / "t")
    assert "| method | jumpingjacks | standup | mean PSNR |" in text
    assert "| deform | 36.00 | 38.00 | 37.00 | 0.9800 | 0.0200 | 80 |" in text
    assert "| deform_stdr | 36.50 | – | 36.50 |" in text
    # context where transcribed: the paper's D-NeRF table (../shared/reference/paper-dnerf-table.md)
    assert "| ↳ paper | 37.72 | 44.62 | 41.17 | | | |" in text
    assert "GPU NVIDIA H100" in text and "code abc1234" in text
    assert data["deform"]["scenes"] == {"jumpingjacks": 36.0, "standup": 38.0}


def test_other_budgets_and_escaping_members_are_refused(tmp_path):
    gt = _module()
    _archive(tmp_path / "c.tgz", {"x__y__s0": ("dnerf_deform", "y", 30.0, "cpu")})
    gt.add(tmp_path / "c.tgz", tmp_path / "t")
    with pytest.raises(SystemExit, match="budget=gpu only"):
        gt.table(tmp_path / "t")
    _archive(tmp_path / "d.tgz", {}, extra=["../evil.txt"])
    with pytest.raises(SystemExit, match="refused"):
        gt.add(tmp_path / "d.tgz", tmp_path / "u")
    assert not (tmp_path / "evil.txt").exists()


def test_the_rule_pairs_variant_runs_by_seed_and_reads_the_mean_gap(tmp_path):
    """`rule`: runs whose ids end in __fast / __torch (a queue's --variants), paired by seed; the
    verdict is stdr.verified's mean over its seeds, and a missing seed is no verdict."""
    gt = _module()
    from stdr.verified import CUDA_RUN_SEEDS
    gaps = dict(zip(CUDA_RUN_SEEDS, (-0.30, 0.10, 0.02)))
    runs = {}
    for sd in CUDA_RUN_SEEDS:
        runs[f"dnerf_deform__jumpingjacks__s{sd}__torch"] = ("dnerf_deform", "jumpingjacks", 36.5, "gpu", sd)
        runs[f"dnerf_deform__jumpingjacks__s{sd}__fast"] = ("dnerf_deform", "jumpingjacks", 36.5 + gaps[sd], "gpu", sd)
    runs["dnerf_4dgs__jumpingjacks__s0__torch"] = ("dnerf_4dgs", "jumpingjacks", 33.0, "gpu", 0)
    runs["dnerf_4dgs__jumpingjacks__s0__fast"] = ("dnerf_4dgs", "jumpingjacks", 33.0, "gpu", 0)
    _archive(tmp_path / "a.tgz", runs)
    gt.add(tmp_path / "a.tgz", tmp_path / "t")
    v = gt.rule(tmp_path / "t", "fast", "torch")
    assert set(v) == {"deform jumpingjacks", "4dgs jumpingjacks"}
    d = v["deform jumpingjacks"]
    assert d["passes"] and abs(d["gap_db"] - sum(gaps.values()) / len(gaps)) < 1e-6
    assert not v["4dgs jumpingjacks"]["passes"] and v["4dgs jumpingjacks"]["missing"] == list(CUDA_RUN_SEEDS[1:])
    with pytest.raises(SystemExit, match="__slow"):
        gt.rule(tmp_path / "t", "slow", "twin")


def test_the_committed_table_queue_composes_for_every_run(tmp_path):
    """research/measurements/dnerf_gpu/queue.json (what the next GPU machine runs, as many at once as
    its first job's calibration chooses): 32
    runs, deform +- STDR first on all four scenes, and every run's command passes stdr-train's
    checks (a scene folder stands in for build/gpucarry), so no typo costs a GPU window."""
    from stdr.store import compose_config
    from stdr.tools.runqueue import Queue
    from stdr.validate import check_run_config
    q = Queue.load(gt_folder() / "queue.json")
    assert len(q.runs) == 32 and len({r.id for r in q.runs}) == 32
    assert [r.id.split("__")[0] for r in q.runs[:8]] == ["dnerf_deform"] * 4 + ["dnerf_deform_stdr"] * 4
    seen = set()
    for r in q.runs:  # runs differ by their scene only: one composition per experiment
        exp = r.overrides[0]
        assert exp.startswith("experiment=") and [o.split("=")[0] for o in r.overrides] == \
            [o.split("=")[0] for o in q.runs[0].overrides]
        if exp in seen:
            continue
        seen.add(exp)
        ov = [o if not o.startswith("data.path=") else f"data.path={tmp_path}" for o in r.overrides]
        cfg = compose_config(ov)
        assert cfg.budget == "gpu" and cfg.device == "cuda"
        check_run_config(cfg)
    assert len(seen) == 8


def test_the_queue_commands_of_the_open_gpu_work_parse(tmp_path):
    """Every `stdr-tool queue plan|run` of docs/install.md's "The open GPU work" is taken by the
    queue's own parser, with the levels, slice and budget it names: a typo there costs a GPU window."""
    import re
    import shlex

    from stdr.tools.concurrency import MARGIN
    from stdr.tools.queue_tool import _parser
    text = (Path(__file__).resolve().parents[1] / "docs" / "install.md").read_text()
    work = text[text.index("The open GPU work"):]
    cmds = [" ".join(c.split()) for c in re.findall(r"`([^`]*stdr-tool queue (?:run|plan)[^`]*)`", work, flags=re.S)]
    assert len(cmds) >= 3
    parsed = []
    for c in cmds:
        argv = shlex.split(c.split("stdr-tool queue ", 1)[1].replace("$OUT", str(tmp_path)).rstrip("&").strip())
        parsed.append(_parser().parse_args(argv[:argv.index("--")] if "--" in argv else argv))
    first = parsed[0]
    assert first.cmd == "run" and first.queue == Path("research/measurements/dnerf_gpu/queue.json")
    assert first.calibrate == [1, 4, 8, 16] and first.concurrent is None
    # after the slices (each some seconds longer than --slice: the sweep's start, the checkpoint at the
    # deadline) the chunk still has the time of one run alone, with the estimates' margin
    assert first.budget - len(first.calibrate) * (first.slice + 5) >= first.alone_seconds * MARGIN
    assert first.budget <= 570  # a job is at most 600 s, and the sweep's grace follows the deadline


def gt_folder():
    return _module().FOLDER
