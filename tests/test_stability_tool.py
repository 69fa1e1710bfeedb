"""studies/stability.py: the degradation table and chart from fixture runs (config.yaml +
metrics.json, a failures.jsonl), and the sweep that produces such runs composes."""
import csv
import json
import math
import shutil
import sys
from pathlib import Path

import pytest
import yaml
from studies.stability import main as stability
from studies.stability import study_grid


TIMES = [0.1, 0.4, 0.6, 0.9]  # evaluation frames' times in the fixture; window [0.3, 0.7] holds two


def _run(root, method, scene, stress, level, seed=0, psnr=30.0, peak=900, cap=1000, metrics=True, recoveries=0,
         best=None, per_frame=None, window=None, machine=None, memory=None):
    base, stdr = method.split("+")[0], method.endswith("+STDR")
    d = root / method / scene / f"{stress}_{level}" / f"s{seed}"
    d.mkdir(parents=True)
    st = {"label": stress, "level": level, **({"drop_times": window} if window else {})}
    cfg = {"seed": seed, "data": {"name": scene, "stress": st},
           "baseline": {"name": base}, "render": {"backend": "cpu"}, "stdr": {"enabled": stdr}}
    (d / "config.yaml").write_text(yaml.safe_dump(cfg))
    if metrics:
        m = {"psnr": psnr, "ssim": 0.9, "lpips": 0.1, "num_gaussians": peak - 10,
             "guard": {"n_recoveries": recoveries, "peak_gaussians": peak, "max_gaussians": cap,
                       **({"peak_memory_mb": memory} if memory else {})},
             "best": {"step": 1000 if best else 2000, "psnr": best or psnr}, "last": {"step": 2000, "psnr": psnr}}
        if per_frame is not None:
            m.update(per_frame_psnr=per_frame, per_frame_time=TIMES)
        if machine:
            m.update(conventions={"machine": machine}, code={"commit": "444c090334e30bdd", "dirty": True})
        (d / "metrics.json").write_text(json.dumps({"val": m}))
    return d


def _fixture(root):
    for scene, ref in (("a", 30.0), ("b", 26.0)):
        _run(root, "deform", scene, "none", 0, psnr=ref, per_frame=[ref] * 4)
        _run(root, "deform+STDR", scene, "none", 0, psnr=ref + 0.5, machine="AMD EPYC, 2 logical CPUs")
        for seed, off in ((1, 0.4), (2, -0.2)):
            _run(root, "deform", scene, "none", 0, seed=seed, psnr=ref + off)
        # 1 dB lower on average, 2 dB lower on the two frames inside the dropped window
        _run(root, "deform", scene, "window", 1, psnr=ref - 1.0, per_frame=[ref, ref - 2, ref - 2, ref],
             window=[0.3, 0.7])
        _run(root, "deform", scene, "window", 2, psnr=ref - 3.0, recoveries=1,
             best=ref - 1.5 if scene == "a" else ref - 2.5,  # fell 1.5 dB (a), 0.5 dB (b) from its best
             memory=800.0 if scene == "a" else 950.0)
        _run(root, "deform+STDR", scene, "window", 1, psnr=ref + 0.5 - 0.5)
    # deform+STDR at window 2: one scene crashed (recorded), one run over the cap, one NaN
    crashed = _run(root, "deform+STDR", "a", "window", 2, metrics=False)
    _run(root, "deform+STDR", "b", "window", 2, psnr=float("nan"), peak=1200)
    _run(root, "deform", "c", "window", 1, psnr=20.0)  # no unstressed reference on scene c
    _run(root, "deform", "a", "pose", 1, metrics=False)  # unfinished, no failure recorded
    (root / "failures.jsonl").write_text(json.dumps({"overrides": ["experiment=dnerf_deform_stdr"],
                                                     "run_dir": str(crashed), "log": "x.log",
                                                     "error": "TrainingDiverged: too many"}) + "\n")


def test_degradation_table_and_chart(tmp_path, capsys):
    _fixture(tmp_path / "runs")
    stability([str(tmp_path / "runs"), "--out", str(tmp_path / "out")])
    t = json.loads((tmp_path / "out" / "table.json").read_text())
    rows = {(r["method"], r["stress"], r["level"]): r for r in t["rows"]}
    w1 = rows[("deform", "window", 1)]
    assert w1["psnr_drop"] == pytest.approx(1.0) and w1["scenes"] == ["a", "b"]
    assert w1["scenes_without_reference"] == ["c"] and w1["psnr"] == pytest.approx((29.0 + 25.0) / 2)
    assert w1["window_drop"] == pytest.approx(2.0) and w1["window_frames"] == 4
    w2 = rows[("deform", "window", 2)]
    assert w2["window_drop"] is None and w2["window_frames"] == 0  # no per-frame numbers in these runs
    assert w2["psnr_drop"] == pytest.approx(3.0) and w2["recoveries"] == 2 and w2["cap_held"] is True
    assert w2["fall_max"] == pytest.approx(1.5) and w1["fall_max"] == pytest.approx(0.0)
    assert w2["memory_max_mb"] == 950.0 and w1["memory_max_mb"] is None  # not recorded in those runs
    s2 = rows[("deform+STDR", "window", 2)]
    assert s2["crashes"] == 1 and s2["nonfinite"] == 1 and s2["psnr_drop"] is None and s2["cap_held"] is False
    assert rows[("deform+STDR", "window", 1)]["psnr_drop"] == pytest.approx(0.5)
    assert t["unfinished"] and t["unfinished"][0].endswith("pose_1/s0")
    crashed = [r for r in t["runs"] if r["crashed"]]
    assert len(crashed) == 1 and crashed[0]["error"].startswith("TrainingDiverged")
    spread = {s["method"]: s for s in t["seed_spread"]}
    per_seed = [28.0, 28.4, 27.8]  # scene means of seeds 0, 1, 2
    assert spread["deform"]["seeds"] == [0, 1, 2]
    assert spread["deform"]["psnr_mean"] == pytest.approx(sum(per_seed) / 3)
    m = sum(per_seed) / 3
    assert spread["deform"]["psnr_std"] == pytest.approx(math.sqrt(sum((x - m) ** 2 for x in per_seed) / 2))
    assert spread["deform+STDR"]["psnr_std"] is None  # one seed
    md = (tmp_path / "out" / "table.md").read_text()
    assert "| deform | window | 2 | 25.00 | +3.00 | – |" in md and "**no**" in md and "| 2 | 1.50 |" in md
    assert "| yes | 950 | a, b |" in md
    assert "| deform | window | 1 | 27.00 | +1.00 | +2.00 (4 fr.) |" in md
    finished = sum(not r["crashed"] for r in t["runs"])
    assert ("AMD EPYC, 2 logical CPUs, code 444c090+dirty: 2 runs; machine not recorded, code commit not recorded: "
            f"{finished - 2} runs") in md
    for ext in ("png", "svg", "csv"):
        assert (tmp_path / "out" / f"degradation_psnr.{ext}").stat().st_size > 0
    with open(tmp_path / "out" / "degradation_psnr.csv") as f:
        data = list(csv.DictReader(f))
    def curve(stress, frames, method="deform"):
        return [(int(r["level"]), float(r["psnr_drop_db"])) for r in data
                if (r["stress"], r["frames"], r["method"]) == (stress, frames, method)]
    assert curve("window", "all") == [(0, 0.0), (1, 1.0), (2, 3.0)]
    # the window's own panel: only deform's level 1 has per-frame times, so only it is drawn there
    assert curve("window", "in window") == [(0, 0.0), (1, 2.0)]
    assert curve("window", "in window", "deform+STDR") == [] and curve("window", "all", "deform+STDR")


def test_bad_input_is_named(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit, match="no run folders"):
        stability([str(tmp_path / "empty"), "--out", str(tmp_path / "o")])
    with pytest.raises(SystemExit, match="does not exist"):
        stability([str(tmp_path / "nope"), "--out", str(tmp_path / "o")])
    _run(tmp_path / "r", "deform", "a", "none", 0)
    with pytest.raises(SystemExit, match="no stressed runs"):
        stability([str(tmp_path / "r"), "--out", str(tmp_path / "o")])


def _table(tmp_path, name, *inputs, split="val"):
    stability([*map(str, inputs), "--split", split, "--out", str(tmp_path / name), "--no-chart"])
    return json.loads((tmp_path / name / "table.json").read_text())


def test_a_committed_table_resumes_the_study_without_its_run_folders(tmp_path):
    """A study spread over machines: the first part's table.json plus the second part's folders
    give the table of all runs in one place, though the first part's folders are gone."""
    runs = tmp_path / "runs"
    _fixture(runs)
    full = _table(tmp_path, "full", runs)
    stdr_part = runs / "deform+STDR"
    (stdr_part / "failures.jsonl").write_text((runs / "failures.jsonl").read_text())  # its crash, recorded
    first = _table(tmp_path, "first", runs / "deform")
    assert first["unfinished"] and {r["method"] for r in first["runs"]} == {"deform"}
    shutil.rmtree(runs / "deform")  # the first machine is lost; its table.json was kept
    resumed = _table(tmp_path, "resumed", tmp_path / "first" / "table.json", stdr_part)
    assert resumed["rows"] == full["rows"] and resumed["seed_spread"] == full["seed_spread"]
    assert sorted(r["run"] for r in resumed["runs"]) == sorted(r["run"] for r in full["runs"])
    assert resumed["unfinished"] == []  # a table's unfinished runs are not carried (their folders decide)
    crashed = [r for r in resumed["runs"] if r["crashed"]]
    assert len(crashed) == 1 and crashed[0]["error"].startswith("TrainingDiverged")


def test_a_run_folder_replaces_its_record_in_a_table(tmp_path):
    runs = tmp_path / "runs"
    _fixture(runs)
    table = tmp_path / "full" / "table.json"
    full = _table(tmp_path, "full", runs)
    assert _table(tmp_path, "same", table, runs)["runs"] == full["runs"]  # every record replaced by itself
    d = runs / "deform+STDR" / "a" / "window_1" / "s0"
    m = json.loads((d / "metrics.json").read_text())
    m["val"]["psnr"] = 10.0  # re-run since the table was written
    (d / "metrics.json").write_text(json.dumps(m))
    rows = {(r["method"], r["stress"], r["level"]): r for r in _table(tmp_path, "new", table, runs)["rows"]}
    assert rows[("deform+STDR", "window", 1)]["psnr"] == pytest.approx((10.0 + 26.0) / 2)
    (d / "metrics.json").unlink()  # being re-run now: unfinished, its old record left out
    t = _table(tmp_path, "rerun", table, runs)
    assert str(d.resolve()) in t["unfinished"] and str(d.resolve()) not in [r["run"] for r in t["runs"]]


def test_the_same_run_from_two_sources_or_a_foreign_table_is_named(tmp_path):
    runs = tmp_path / "runs"
    _fixture(runs)
    table = tmp_path / "full" / "table.json"
    _table(tmp_path, "full", runs)
    copy = tmp_path / "elsewhere" / "s0"
    shutil.copytree(runs / "deform" / "b" / "window_1" / "s0", copy)
    with pytest.raises(SystemExit, match=r"method=deform, scene=b, seed=0, stress=window, level=1 comes twice: "
                                         r".*window_1/s0 \(.*table.json\) and .*elsewhere/s0 \(run folder\)"):
        _table(tmp_path, "o", table, copy)
    with pytest.raises(SystemExit, match=r"holds the 'val' split, not 'test'; pass --split val"):
        _table(tmp_path, "o", table, split="test")
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"split": "val", "rows": []}))
    with pytest.raises(SystemExit, match=r"bad.json has no 'runs' list"):
        _table(tmp_path, "o", bad)
    t = json.loads(table.read_text())
    del t["runs"][3]["psnr"]
    bad.write_text(json.dumps(t))
    with pytest.raises(SystemExit, match=r"bad.json: runs\[3\] lacks psnr"):
        _table(tmp_path, "o", bad)
    bad.write_text("{not json")
    with pytest.raises(SystemExit, match=r"bad.json is not a readable table.json"):
        _table(tmp_path, "o", bad)
    other = json.loads(table.read_text())
    other["runs"][0]["psnr"] += 1.0
    bad.write_text(json.dumps(other))
    with pytest.raises(SystemExit, match=r"differs between .*table.json and .*bad.json"):
        _table(tmp_path, "o", table, bad)


def test_the_stability_sweep_composes_every_preset():
    from stdr.testing import make_cfg
    from stdr.config import CONFIG_DIR
    sweep = yaml.safe_load((CONFIG_DIR / "sweep" / "stability.yaml").read_text())
    presets = sweep["hydra"]["sweeper"]["params"]["stress"].split(",")
    assert sorted(presets) == sorted(p.stem for p in (CONFIG_DIR / "stress").glob("*.yaml"))
    seen = set()
    for p in presets:
        c = make_cfg(["+sweep=stability", "data.root=/d", "data.name=standup", "experiment=dnerf_deform_stdr",
                      f"stress={p}"])
        st = c.data.stress
        assert c.data.eval_split == "val" and c.data.path == "/d/standup"
        assert (st.label, st.level) == (("none", 0) if p == "none" else (p.split("_")[0], int(p.split("_")[1])))
        seen.add((st.label, st.level))
    assert len(seen) == len(presets)


def _study_table(tmp_path, lacking=()):
    """A committed table.json of the study grid (every method of the sweep on its scenes) that holds
    `none:0`, `window_1:0` and `fraction_1:0`, less the (method, scene) pairs of fraction_1 in `lacking`."""
    from studies.stability import study_grid
    exps, scenes = study_grid()
    runs = tmp_path / "study_runs"
    for stress, level in (("none", 0), ("window", 1), ("fraction", 1)):
        for _, method in exps:
            for scene in scenes:
                if stress != "fraction" or (method, scene) not in lacking:
                    _run(runs, method, scene, stress, level, psnr=28.0 - level)
    _table(tmp_path, "out", runs)
    return tmp_path / "out" / "table.json", exps, scenes


def test_todo_names_what_a_committed_table_lacks(tmp_path, capsys):
    table, exps, scenes = _study_table(tmp_path, lacking={("spgs", "standup"), ("spgs+STDR", "standup"),
                                                          ("deform", "jumpingjacks")})
    assert [e for e, _ in exps][:2] == ["dnerf_4dgs", "dnerf_4dgs_stdr"] and len(exps) == 8  # study_grid's pairs
    assert scenes == ["jumpingjacks", "standup"]
    capsys.readouterr()  # the table's own print
    stability(["--todo", "none:0", "--todo", "window_1:0", "--todo", "fraction_1:0", "--todo", "pose_1:0",
               str(table)])
    lines = capsys.readouterr().out.splitlines()
    assert lines == ["fraction_1:0 experiment=dnerf_deform data.name=jumpingjacks",
                     "fraction_1:0 experiment=dnerf_spgs,dnerf_spgs_stdr data.name=standup",
                     f"pose_1:0 experiment={','.join(e for e, _ in exps)} data.name=jumpingjacks,standup"]
    stability(["--todo", "none:1", str(table)])  # another seed: nothing of it is recorded
    assert capsys.readouterr().out.split()[1:] == [f"experiment={','.join(e for e, _ in exps)}",
                                                   "data.name=jumpingjacks,standup"]
    with pytest.raises(SystemExit, match="no stress preset"):
        stability(["--todo", "windw_1:0", str(table)])
    with pytest.raises(SystemExit, match="2"):  # argparse: a malformed word, a folder instead of a table
        stability(["--todo", "window_1", str(table)])
    with pytest.raises(SystemExit, match="2"):
        stability(["--todo", "window_1:0", str(tmp_path)])


def test_the_study_plans_the_grid_breadth_first_through_the_queue_and_keeps_the_committed_table(tmp_path, capsys):
    """studies/stability_study.py: the presets in GRID's order, each planned with only the runs the
    committed table lacks, every run a job of the one run queue with the sweep's keys."""
    import studies.stability_study as st
    from stdr.config import CONFIG_DIR
    table, exps, scenes = _study_table(tmp_path, lacking={("spgs", "standup"), ("spgs+STDR", "standup")})
    work = tmp_path / "work"
    q = st.plan(Path("/data/dnerf"), list(st.GRID), table, work, ["train.threads=2"])
    assert "window_1 seed 0: every run is in" in capsys.readouterr().out
    presets = sorted(p.stem for p in (CONFIG_DIR / "stress").glob("*.yaml"))
    assert sorted(st.GRID) == sorted([f"{p}:0" for p in presets] + ["none:1", "none:2"])
    order = list(dict.fromkeys(tuple(r.id.split("/")[2:]) for r in q.runs))
    # breadth first: (unstressed seed 0: recorded), level 3 of each stress, unstressed seeds 1-2,
    # level 1 (window_1: recorded), level 2
    assert order == [(p, "s0") for p in ("window_3", "fraction_3", "sparse_3", "pose_3", "jitter_3")] + \
        [("none", "s1"), ("none", "s2")] + [(p, "s0") for p in ("fraction_1", "sparse_1", "pose_1", "jitter_1")] + \
        [(p, "s0") for p in ("window_2", "fraction_2", "sparse_2", "pose_2", "jitter_2")]
    # fraction_1 plans only what the table lacks; a preset with nothing recorded, the whole grid
    assert sorted(r.id for r in q.runs if "/fraction_1/" in r.id) == \
        ["dnerf_spgs/standup/fraction_1/s0", "dnerf_spgs_stdr/standup/fraction_1/s0"]
    assert sorted(r.id for r in q.runs if "/pose_1/" in r.id) == \
        sorted(f"{e}/{s}/pose_1/s0" for e, _ in exps for s in scenes)
    r = next(r for r in q.runs if r.id == "dnerf_spgs/standup/fraction_1/s0")
    assert r.overrides[:6] == ["experiment=dnerf_spgs", "budget=cpu", "stress=fraction_1", "seed=0",
                               "data.path=/data/dnerf/standup", "data.name=standup"]
    assert {"data.eval_split=val", "train.eval_every=500", "train.progress=false"} <= set(r.overrides)
    assert r.overrides[-1] == "train.threads=2" and all(r.state == "pending" for r in q.runs)
    # a run whose folder holds its metrics.json is done; a bad preset is named
    (work / r.id).mkdir(parents=True)
    (work / r.id / "metrics.json").write_text("{}")
    assert [x.state for x in st.plan(Path("/data/dnerf"), ["fraction_1:0"], table, work, []).runs] == ["done", "pending"]
    with pytest.raises(SystemExit, match="bad preset 'windw_1:0'"):
        st.plan(Path("/data/dnerf"), ["none:0", "windw_1:0"], table, work, [])
    with pytest.raises(SystemExit, match="no scripts/run.sh there"):
        st.main(["/data/dnerf", "--code", str(tmp_path / "nowhere"), "--dry-run"])


def test_the_study_trains_its_runs_on_the_queue_and_tabulates_them(tmp_path, monkeypatch):
    """One preset of the study on the run queue with a stand-in for stdr-train that writes a
    finished run: every run ends done in WORK, and the table is written from them."""
    import studies.stability_study as st
    fake = tmp_path / "fake_run.py"
    fake.write_text("import json, sys\nfrom pathlib import Path\n"
                    "run = Path(next(a for a in sys.argv if a.startswith('hydra.run.dir=')).split('=', 1)[1])\n"
                    "run.mkdir(parents=True, exist_ok=True)\n(run / 'metrics.json').write_text('{}')\n")
    monkeypatch.setattr(st, "command", lambda code: [sys.executable, str(fake)])
    tables = []
    monkeypatch.setattr(st, "stability_table", lambda argv: tables.append(argv))
    work, out = tmp_path / "work", tmp_path / "out"
    assert st.main(["/data/dnerf", "--presets", "jitter_2:3", "--work", str(work), "--out", str(out)]) == 0
    exps, scenes = study_grid()
    assert sorted(p.parent.relative_to(work).as_posix() for p in work.rglob("metrics.json")) == \
        sorted(f"{e}/{s}/jitter_2/s3" for e, _ in exps for s in scenes)
    assert tables == [[str(work.resolve()), "--split", "val", "--out", str(out)]]
    q = json.loads((work / "queue.json").read_text())
    assert {r["state"] for r in q["runs"]} == {"done"}


def test_frame_times_come_from_the_scene_for_runs_that_did_not_record_them(tmp_path):
    """Runs written before metrics.json had per_frame_time: the tool loads the evaluation split
    as the trainer does and takes its frames' times, in the same order."""
    from omegaconf import OmegaConf
    from stdr.data.load import load_scene
    from stdr.testing import tiny_config
    from studies.stability import _frame_times
    cfg = tiny_config(tmp_path, ["stress=window_2"])
    want = [f.time for f in load_scene(cfg.data, ["val"]).splits["val"]]
    container = OmegaConf.to_container(cfg, resolve=True)
    cache = {}
    assert _frame_times(container, "val", {"per_frame_psnr": [1.0] * len(want)}, cache) == want
    assert _frame_times(container, "val", {"per_frame_time": [0.5]}, cache) == [0.5]  # recorded wins
    container["data"].update(format="dnerf", path=str(tmp_path / "nowhere"), name="gone")
    assert _frame_times(container, "val", {}, {}) is None  # unreadable data: no in-window drop, no crash
