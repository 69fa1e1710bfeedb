"""Contribution pruning study (docs/measurements/compact_prune/protocol.md): branch each headline
run (one seed, the trunk) at its step-1500 checkpoint into the protocol's variants, train the last
500 steps, evaluate on val; then tabulate and apply the protocol's rule.

    python studies/compact_prune.py run DNERF_ROOT --headline WORK --seed 2 [--follow] [--work DIR] [--code CHECKOUT]
    python studies/compact_prune.py table [--records DIR]

`run` is a resumable queue: a (method, scene, variant) whose records are committed is skipped, and
a cell whose trunk (WORK/<experiment>/<scene>/s<seed>, a finished headline run with its
checkpoints) is not there yet waits; `--follow` keeps polling for new trunks while the headline
queue trains them (scripts/idle_run.py's machine lock makes the two queues take turns), until
every cell is recorded; `--hold` pauses the headline queue between its runs while branches are
runnable (WORK/pause.compact), so the trunks trained so far are branched before the next one starts. `touch <--work>/pause` makes it wait between runs.
`--scratch` adds the +STDR methods' `stdr.time_bins` variants (protocol.md, amendment 2): trained
from scratch with the same seed and code, one at a time whenever no trunk waits for its branches.
Records (config.yaml,
metrics.json, history.json, train_profile.json, load.json, branch.json; `identity.json` for the
control) go to docs/measurements/compact_prune/runs/<experiment>/<scene>/<variant>/.
"""
from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from studies.common import gmean  # noqa: E402

RECORDS = ROOT / "docs" / "measurements" / "compact_prune" / "runs"
SCENES = ("bouncingballs", "hellwarrior", "jumpingjacks", "standup")
EXPERIMENTS = tuple(f"dnerf_{b}{s}" for b in ("deform", "scgs", "spgs", "4dgs") for s in ("", "_stdr"))
VARIANTS = {  # name: prune.* overrides (the protocol's table)
    "control": ["prune.share=0"],
    "s30": ["prune.share=0.3", "prune.time_weight=0"],
    "s30_tw1": ["prune.share=0.3", "prune.time_weight=1"],
    "s50": ["prune.share=0.5", "prune.time_weight=0"],
    "s50_tw1": ["prune.share=0.5", "prune.time_weight=1"],
}
#: variants only for the +STDR methods
STDR_VARIANTS = {"m8": ["prune.share=0", "stdr.mask_bits=8"]}
#: +STDR variants trained from scratch (no trunk: the mask's time columns are fixed at the start),
#: with --scratch only; compared with the control branch of the same seed (protocol.md, amendment 2)
SCRATCH_VARIANTS = {"tb50": ["prune.share=0", "stdr.time_bins=50"], "tb25": ["prune.share=0", "stdr.time_bins=25"]}
AT = "prune.at=[refine_stop,0.9]"
BRANCH_STEP = 1500
KEEP = ("config.yaml", "metrics.json", "history.json", "train_profile.json")


def same_parameters(a: Path, b: Path) -> dict:
    """Whether two checkpoints hold bit-identical model parameters and deformation weights."""
    import torch

    from stdr.io.checkpoint import load_checkpoint
    ma, mb = load_checkpoint(a)["model"], load_checkpoint(b)["model"]
    diff = [k for k in ma["params"] if k not in mb["params"] or not torch.equal(ma["params"][k], mb["params"][k])]
    diff += [f"deform.{k}" for k, v in ma["deform"].items() if not torch.equal(v, mb["deform"][k])]
    return {"identical": not diff and ma["step"] == mb["step"], "differing": diff, "steps": [ma["step"], mb["step"]]}


def branch_point(ckpt: Path) -> dict:
    """The step and training seconds of the checkpoint a branch starts from (the headline run's; its
    seconds were measured there, so the table reports the branch's own seconds separately)."""
    from stdr.io.checkpoint import load_checkpoint
    ck = load_checkpoint(ckpt)
    return {"from_step": int(ck["model"]["step"]), "train_seconds_at_branch": float(ck["train_seconds"])}


def trunk_dir(headline: Path, exp: str, scene: str, seed: int) -> Path:
    return Path(headline) / exp / scene / f"s{seed}" / "checkpoints"


def branch_once(args, code: Path, exp: str, scene: str, name: str, keys: list[str], src: Path, point: dict) -> str:
    """Train one branch and record it: "recorded", "failed" or "shared" (not recorded: other jobs
    used the machine)."""
    rec = Path(args.records) / exp / scene / name
    while (Path(args.work) / "pause").exists():
        time.sleep(10)
    run = Path(args.work) / exp / scene / name
    if run.exists():
        shutil.rmtree(run)  # a branch killed midway starts again from the checkpoint
    (run / "checkpoints").mkdir(parents=True)
    if src is not None:  # None: trained from scratch (SCRATCH_VARIANTS)
        shutil.copy2(src / "last.previous.pt", run / "checkpoints" / "last.pt")
        # the trunk's final state, for the control's check: the headline queue may retrain the trunk
        # (a run that shared the machine) while this branch runs
        shutil.copy2(src / "last.pt", run / "trunk_last.pt")
    # `python -m` from the checkout imports its own stdr, whatever the environment's install
    cmd = [str(code / "scripts" / "run.sh"), "python", "-m", "stdr.cli.train", f"experiment={exp}",
           "budget=cpu", f"seed={args.seed}",
           f"data.path={Path(args.dnerf) / scene}", f"data.name={scene}", "data.eval_split=val",
           "train.progress=false", f"hydra.run.dir={run}", AT, *keys]
    print(f"[compact] {time.strftime('%T')} {exp} {scene} {name} "
          f"({'from scratch, seed' if src is None else 'trunk seed'} {args.seed})", flush=True)
    load = Path(str(run) + ".load.json")  # scripts/idle_run.py: did it have the machine to itself?
    with open(str(run) + ".log", "w") as log:
        rc = subprocess.run([sys.executable, str(ROOT / "scripts" / "idle_run.py"), "--out", str(load),
                             "--", *cmd], stdout=log, stderr=subprocess.STDOUT, cwd=code).returncode
    if rc != 0 or not (run / "metrics.json").is_file():
        print(f"[compact] FAILED {exp} {scene} {name} (log: {run}.log)", file=sys.stderr, flush=True)
        return "failed"
    if not json.loads(load.read_text())["idle"]:
        print(f"[compact] SHARED {exp} {scene} {name}: other jobs used the machine ({load}); not "
              "recorded, redone later", file=sys.stderr, flush=True)
        return "shared"
    rec.mkdir(parents=True, exist_ok=True)
    (rec / "branch.json").write_text(json.dumps({**point, "trunk_seed": args.seed, "scratch": src is None}, indent=1))
    shutil.copy2(load, rec / "load.json")
    for f in KEEP:
        if (run / f).is_file():
            shutil.copy2(run / f, rec / f)
    if name == "control":
        ident = same_parameters(run / "checkpoints" / "last.pt", run / "trunk_last.pt")
        (rec / "identity.json").write_text(json.dumps(ident, indent=1))
    return "recorded"


def _account(status: str, cell: tuple, failed: set, shared: dict) -> int:
    """Book one branch's outcome: a failure is not retried in this process, a run that shared the
    machine up to three times. Returns 1 when it was recorded."""
    if status == "failed":
        failed.add(cell)
    elif status == "shared":
        shared[cell] = shared.get(cell, 0) + 1
    return int(status == "recorded")


def run_queue(args) -> int:
    """Every (method, scene, variant) without records whose trunk is there; with --follow, again
    every --poll seconds until all are recorded. A branch that fails is not retried in this
    process, one that shared the machine up to three times. With --hold, WORK/pause.compact
    (WORK: the headline queue's folder) is kept while branches are runnable, so the headline
    queue waits between its runs and a trunk's branches run before the next trunk is trained."""
    import signal
    code = Path(args.code).resolve()
    hold = Path(args.headline) / "pause.compact" if args.hold else None
    prev = signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # run the `finally` below: never leave the hold
    failed, shared, warned = set(), {}, set()
    try:
        while True:
            todo, ran = 0, 0
            for exp in (args.experiments or EXPERIMENTS):
                variants = {**VARIANTS, **(STDR_VARIANTS if exp.endswith("_stdr") else {})}
                for scene in (args.scenes or SCENES):
                    src = trunk_dir(args.headline, exp, scene, args.seed)
                    for name, keys in variants.items():
                        if args.variants and name not in args.variants:
                            continue
                        cell = (exp, scene, name)
                        if (Path(args.records) / exp / scene / name / "metrics.json").is_file() or cell in failed \
                                or shared.get(cell, 0) >= 3:
                            continue
                        todo += 1
                        if not (src.parent / "metrics.json").is_file() or not (src / "last.previous.pt").is_file():
                            continue  # the headline run is not there yet, or still training
                        point = branch_point(src / "last.previous.pt")
                        if point["from_step"] != BRANCH_STEP:
                            if (exp, scene) not in warned:
                                print(f"[compact] {src / 'last.previous.pt'}: step {point['from_step']}, not "
                                      f"{BRANCH_STEP}; {exp} {scene} is skipped (protocol.md)", file=sys.stderr,
                                      flush=True)
                                warned.add((exp, scene))
                            failed.add(cell)
                            continue
                        if hold is not None:
                            hold.touch()
                        ran += 1
                        todo -= _account(branch_once(args, code, exp, scene, name, keys, src, point), cell, failed,
                                         shared)
            if not ran and hold is not None:
                hold.unlink(missing_ok=True)  # nothing to branch: the headline queue goes on
            scratch_ran = False
            if args.scratch:  # once no trunk waits for branches: one from-scratch run, then look again
                for exp in (e for e in (args.experiments or EXPERIMENTS) if e.endswith("_stdr")):
                    for scene in SCENES:
                        for name, keys in SCRATCH_VARIANTS.items():
                            cell = (exp, scene, name)
                            if (args.variants and name not in args.variants) or cell in failed or \
                                    shared.get(cell, 0) >= 3 or \
                                    (Path(args.records) / exp / scene / name / "metrics.json").is_file():
                                continue
                            todo += 1
                            if ran:
                                continue
                            ran, scratch_ran = ran + 1, True
                            todo -= _account(branch_once(args, code, exp, scene, name, keys, None, {"from_step": 0}),
                                             cell, failed, shared)
            if (not args.follow and not scratch_ran) or todo == 0:
                break
            if not ran:
                time.sleep(args.poll)
    finally:
        if hold is not None:
            hold.unlink(missing_ok=True)
        signal.signal(signal.SIGTERM, prev)
    print(f"[compact] done; {len(failed)} failed, {todo} not recorded")
    return 1 if failed or todo else 0


def load_records(root: Path) -> dict:
    """{(experiment, scene, variant): the val entry of metrics.json, with train_profile seconds}."""
    out = {}
    for m in sorted(root.glob("*/*/*/metrics.json")):
        variant, scene, exp = m.parent.name, m.parent.parent.name, m.parent.parent.parent.name
        entry = json.loads(m.read_text())["val"]
        ident = m.parent / "identity.json"
        entry["identity"] = json.loads(ident.read_text()) if ident.is_file() else None
        br = json.loads((m.parent / "branch.json").read_text()) if (m.parent / "branch.json").is_file() else {}
        entry["branch_seconds"] = (entry["train_seconds"] - br["train_seconds_at_branch"]
                                   if "train_seconds_at_branch" in br else None)
        entry["trunk_seed"] = br.get("trunk_seed", 0)  # records from before the key branched seed 0
        entry["scratch"] = bool(br.get("scratch", False))
        out[(exp, scene, variant)] = entry
    return out


def _mean(xs):
    xs = [x for x in xs if x is not None]
    return sum(xs) / len(xs) if xs else None


def decide(recs: dict) -> dict:
    """The protocol's rule over complete records: per variant, each method's mean ΔPSNR against its
    control, admissibility (every method >= -0.1 dB), and the choice."""
    delta = {}
    for v in VARIANTS:
        if v == "control":
            continue
        per = {}
        for exp in EXPERIMENTS:
            ds = [recs[(exp, s, v)]["psnr"] - recs[(exp, s, "control")]["psnr"]
                  for s in SCENES if (exp, s, v) in recs and (exp, s, "control") in recs]
            per[exp] = sum(ds) / len(ds) if len(ds) == len(SCENES) else None
        delta[v] = per
    complete = {v: all(x is not None for x in per.values()) for v, per in delta.items()}
    if not all(complete.values()):
        return {"delta_psnr": delta, "complete": False, "choice": None}
    admissible = {v: min(per.values()) >= -0.1 for v, per in delta.items()}
    avg = {v: _mean(per.values()) for v, per in delta.items()}
    choice, why = None, ""
    for share in ("s50", "s30"):
        if admissible[share] or admissible[f"{share}_tw1"]:
            tw1 = admissible[f"{share}_tw1"] and (not admissible[share] or avg[f"{share}_tw1"] > avg[share] + 0.05)
            choice = f"{share}_tw1" if tw1 else share
            why = f"rule 2: the largest admissible share ({share})"
            break
    if choice is None:
        choice = "s30_tw1" if avg["s30_tw1"] > avg["s30"] else "s30"
        why = "rule 3: no variant admissible; the better of s30 / s30_tw1 on the eight-method mean"
    m8 = {}
    for exp in (e for e in EXPERIMENTS if e.endswith("_stdr")):
        ds = [recs[(exp, s, "m8")]["psnr"] - recs[(exp, s, "control")]["psnr"]
              for s in SCENES if (exp, s, "m8") in recs and (exp, s, "control") in recs]
        m8[exp] = sum(ds) / len(ds) if len(ds) == len(SCENES) else None
    mask8 = None if None in m8.values() else min(m8.values()) >= -0.05  # rule 5
    return {"delta_psnr": delta, "admissible": admissible, "mean_delta_psnr": avg, "complete": True,
            "choice": choice, "why": why, "m8_delta_psnr": m8, "mask_bits_8": mask8, **decide_time_bins(recs)}


def decide_time_bins(recs: dict) -> dict:
    """Rule 6 (protocol.md, amendment 2): each from-scratch time_bins variant's mean ΔPSNR against the
    control of each +STDR method; the preset's time_bins is the fewest columns whose ΔPSNR is >= -0.1 dB
    for all four methods (tb25 before tb50), else none. None while records are missing."""
    per = {}
    for v in SCRATCH_VARIANTS:
        per[v] = {}
        for exp in (e for e in EXPERIMENTS if e.endswith("_stdr")):
            ds = [recs[(exp, s, v)]["psnr"] - recs[(exp, s, "control")]["psnr"]
                  for s in SCENES if (exp, s, v) in recs and (exp, s, "control") in recs]
            per[v][exp] = sum(ds) / len(ds) if len(ds) == len(SCENES) else None
    # a variant is out once one method's complete mean is below the bar (the missing ones cannot
    # bring it back), in once every method's is at or above it; the rule decides as soon as that
    # settles it: the fewest admitted columns with every variant of fewer columns out, else none
    state = {v: "out" if any(x is not None and x < -0.1 for x in d.values()) else
             "in" if all(x is not None for x in d.values()) else None for v, d in per.items()}
    decided = None
    for v in ("tb25", "tb50"):
        if state[v] == "in":
            decided = int(v[2:])
            break
        if state[v] is None:
            break
    else:
        decided = 0
    return {"time_bins_delta_psnr": per, "time_bins_state": state, "time_bins": decided}


def _machines(recs: dict) -> str:
    n: dict = {}
    for r in recs.values():
        m = (r.get("conventions") or {}).get("machine", "not recorded")
        n[m] = n.get(m, 0) + 1
    return "; ".join(f"{k} ({v} runs)" for k, v in sorted(n.items())) or "–"


def table(args) -> int:
    from stdr.eval.evaluate import code_version, machine_name
    recs = load_records(Path(args.records))
    seeds = sorted({r["trunk_seed"] for r in recs.values()})
    lines = [f"# Contribution pruning on val (budget=cpu, trunk seed {', '.join(map(str, seeds)) or '–'}, "
             "four shared D-NeRF scenes)", "",
             f"Generated by `python studies/compact_prune.py table` from {len(recs)} records at commit "
             f"{code_version().get('commit', '?')[:10]} on {machine_name()}, {time.strftime('%Y-%m-%d')}. "
             f"Runs' machines: {_machines(recs)}. "
             "Rule: protocol.md. Means over the scenes present (n).", "",
             "Train s: the branch's own seconds (steps 1500-2000, the pruning events included); the first "
             "1500 steps are the headline run's, timed there.", "",
             "| method | variant | n | PSNR | SSIM | LPIPS | FPS | Gaussians | seen/frame | model MB | train s (1500-2000) | "
             "score pass s/event | identical control |", "|" + "---|" * 13]
    for exp in EXPERIMENTS:
        # `preset`: amendment 4's compact run where no variant has its keys (val numbers shown, not used)
        for v in [*VARIANTS, *(dict(STDR_VARIANTS, **SCRATCH_VARIANTS) if exp.endswith("_stdr") else {}), "preset"]:
            rows = [recs[(exp, s, v)] for s in SCENES if (exp, s, v) in recs]
            if not rows:
                continue
            ev = [e["score_seconds"] for r in rows for e in r.get("prune", [])]
            ident = "" if v != "control" else "/".join("yes" if (r["identity"] or {}).get("identical") else "NO"
                                                       for r in rows)

            if v in SCRATCH_VARIANTS:  # whole runs: their seconds are all theirs
                rows = [dict(r, branch_seconds=r.get("train_seconds")) for r in rows]

            def f(k, fmt, rows=rows):
                x = _mean(r.get(k) for r in rows)
                return "–" if x is None else format(x, fmt)
            lines.append(f"| {exp} | {v} | {len(rows)} | {f('psnr', '.2f')} | {f('ssim', '.4f')} | {f('lpips', '.4f')} | "
                         f"{f('fps', '.1f')} | {f('num_gaussians', ',.0f')} | {f('seen_per_frame', '.1%')} | "
                         f"{f('model_mb', '.2f')} | {f('branch_seconds', '.0f')} | "
                         f"{(sum(ev) / len(ev)) if ev else 0:.2f} | {ident} |")
    d = decide(recs)
    lines += ["", f"Decision: {d['choice'] or 'not yet (records incomplete)'}" + (f" ({d['why']})" if d.get('why') else "")]
    tb = d.get("time_bins", decide_time_bins(recs)["time_bins"])
    lines += ["", "`tb50` / `tb25` are trained from scratch with `stdr.time_bins` (their train s is the whole run's, "
              "not the branch's); rule 6: "
              + ("not yet (records incomplete)" if tb is None else
                 (f"stdr.time_bins={tb} joins the compact preset" if tb else "no time_bins variant is admissible"))]
    out = Path(args.records).parent
    (out / "table_val.md").write_text("\n".join(lines) + "\n")
    (out / "table_val.json").write_text(json.dumps({"decision": d, "records": {"/".join(k): v for k, v in recs.items()}},
                                                   indent=1, default=str))
    print("\n".join(lines))
    return 0


TEST_RECORDS = RECORDS.parent / "test"
ROLES = ("full", "compact")


def preset_of(d: dict, exp: str) -> tuple[str, list[str]]:
    """(branch name, keys) of method `exp`'s compact run under decision `d` (protocol.md, amendment 4):
    the chosen variant's branch, or `preset` (the chosen keys + stdr.mask_bits=8) for a +STDR method
    when rule 5 admits 8 bits, which no val variant combines with a share."""
    keys = list(VARIANTS[d["choice"]])
    if exp.endswith("_stdr") and d["mask_bits_8"]:  # m8's mask key (its prune.share=0 is the choice's here)
        return "preset", [*keys, *(k for k in STDR_VARIANTS["m8"] if not k.startswith("prune."))]
    return d["choice"], keys


def evaluate_once(args, code: Path, run: Path, out: Path, meta: dict) -> str:
    """Evaluate one run folder's final checkpoint on the test split with the frozen code's stdr-eval,
    alone on the machine, and record it in `out`: "recorded", "failed" or "shared"."""
    while (Path(args.work) / "pause").exists():
        time.sleep(10)
    if not (run / "checkpoints" / "last.pt").is_file():
        print(f"[compact] FAILED test {run}: no checkpoints/last.pt (the branch's work folder is gone)",
              file=sys.stderr, flush=True)
        return "failed"
    cmd = [str(code / "scripts" / "run.sh"), "python", "-m", "stdr.cli.eval", str(run), "split=test",
           f"out={run}/test_table"]
    print(f"[compact] {time.strftime('%T')} test {meta['experiment']} {meta['scene']} {meta['role']} "
          f"({meta['branch']})", flush=True)
    load = Path(str(run) + ".test_load.json")
    with open(str(run) + ".test.log", "w") as log:
        rc = subprocess.run([sys.executable, str(ROOT / "scripts" / "idle_run.py"), "--out", str(load),
                             "--", *cmd], stdout=log, stderr=subprocess.STDOUT, cwd=code).returncode
    m = run / "metrics.json"
    if rc != 0 or not m.is_file() or "test" not in json.loads(m.read_text()):
        print(f"[compact] FAILED test {run} (log: {run}.test.log)", file=sys.stderr, flush=True)
        return "failed"
    if not json.loads(load.read_text())["idle"]:
        print(f"[compact] SHARED test {run}: other jobs used the machine; evaluated again", file=sys.stderr, flush=True)
        return "shared"
    out.mkdir(parents=True, exist_ok=True)
    for f in ("metrics.json", "config.yaml"):  # a run folder stdr-eval / stdr-chart can tabulate
        shutil.copy2(run / f, out / f)
    shutil.copy2(load, out / "load.json")
    (out / "source.json").write_text(json.dumps(meta, indent=1))
    return "recorded"


def run_test(args) -> int:
    """Amendment 4: train the `preset` branches the decision needs, then evaluate each method and
    scene's full (control) and compact run once on test. Resumable: recorded cells are skipped."""
    d = decide(load_records(Path(args.records)))
    if not d["complete"] or d["mask_bits_8"] is None:
        raise SystemExit("studies/compact_prune.py test: the val records are incomplete (every variant of every method "
                         "and scene, m8 included, is needed for rules 1-5); run `studies/compact_prune.py run` first")
    code = Path(args.code).resolve()
    failed, shared = set(), {}
    for exp in (args.experiments or EXPERIMENTS):
        branch, keys = preset_of(d, exp)
        for scene in SCENES:
            cell = (exp, scene, branch)
            while branch == "preset" and cell not in failed and shared.get(cell, 0) < 3 and \
                    not (Path(args.records) / exp / scene / branch / "metrics.json").is_file():
                src = trunk_dir(args.headline, exp, scene, args.seed)
                if not (src / "last.previous.pt").is_file():
                    print(f"[compact] FAILED {exp} {scene} preset: no trunk {src / 'last.previous.pt'} (protocol.md, "
                          "amendment 3 retrains it)", file=sys.stderr, flush=True)
                    failed.add(cell)
                    break
                _account(branch_once(args, code, exp, scene, branch, keys, src, branch_point(src / "last.previous.pt")),
                         cell, failed, shared)
            for role, name in (("full", "control"), ("compact", branch)):
                if role == "compact" and cell in failed:
                    continue  # its branch could not be trained
                out = Path(args.test_records) / exp / scene / role
                tcell = (exp, scene, role)
                meta = {"experiment": exp, "scene": scene, "role": role, "branch": name,
                        "keys": VARIANTS["control"] if role == "full" else keys, "decision": d["choice"],
                        "mask_bits_8": d["mask_bits_8"]}
                while tcell not in failed and shared.get(tcell, 0) < 3 and not (out / "metrics.json").is_file():
                    _account(evaluate_once(args, code, Path(args.work) / exp / scene / name, out, meta),
                             tcell, failed, shared)
    todo = sum(not (Path(args.test_records) / e / s / r / "metrics.json").is_file()
               for e in (args.experiments or EXPERIMENTS) for s in SCENES for r in ROLES)
    print(f"[compact] test done; {len(failed)} failed, {todo} not recorded")
    return 1 if failed or todo else 0


#: the compactness targets (full vs compact per method; +STDR vs plain, both compact): (key, what, test, bound)
TARGETS = (("psnr", "mean PSNR, compact - full (dB)", ">=", -0.1),
           ("num_gaussians", "Gaussians, compact / full", "<=", 0.5),
           ("fps", "render FPS, compact / full", ">=", 1.6),
           ("model_mb", "model bytes, compact / full", "<=", 0.4))
STDR_TARGETS = (("fps", "render FPS, +STDR / plain (both compact)", ">=", 1.0),
                ("model_mb", "model bytes, +STDR / plain (both compact)", "<=", 1.25),
                ("train_seconds", "train s, +STDR / plain (both compact)", "<=", 1.1))


def _compare(a: dict, b: dict, key: str):
    """Mean over scenes of a - b (PSNR) or geometric mean over scenes of a / b (the others)."""
    pairs = [(a[s][key], b[s][key]) for s in SCENES if s in a and s in b]
    if len(pairs) != len(SCENES):
        return None
    return _mean(x - y for x, y in pairs) if key == "psnr" else gmean(x / y for x, y in pairs)


def _meets(value, op: str, bound: float):
    return None if value is None else (value >= bound if op == ">=" else value <= bound)


def bytes_split(recs: dict) -> dict:
    """Per method, from each scene's full and compact run (the same deformation module, other
    Gaussian counts): the fixed MiB and the bytes per Gaussian of model_mb without STDR's mask,
    and the mask's MiB in each; means over the scenes that have both runs."""
    out = {}
    for exp in EXPERIMENTS:
        full, comp = recs.get((exp, "full"), {}), recs.get((exp, "compact"), {})
        rows = []
        for s in SCENES:
            if s not in full or s not in comp or full[s]["num_gaussians"] == comp[s]["num_gaussians"]:
                continue
            mf, mc = ((r.get("stdr") or {}).get("mask_bytes", 0) / 2 ** 20 for r in (full[s], comp[s]))
            bf, bc = full[s]["model_mb"] - mf, comp[s]["model_mb"] - mc
            per = (bf - bc) / (full[s]["num_gaussians"] - comp[s]["num_gaussians"])
            rows.append((bf - per * full[s]["num_gaussians"], per * 2 ** 20, mf, mc))
        if rows:
            out[exp] = dict(zip(("fixed_mib", "bytes_per_gaussian", "mask_mib_full", "mask_mib_compact"),
                                (_mean(col) for col in zip(*rows))))
    return out


def test_table(args) -> int:
    """table_test.md / .json: per baseline, plain and +STDR, full and compact on test, and the targets."""
    from stdr.eval.evaluate import code_version, machine_name
    root = Path(args.test_records)
    recs: dict = {}
    for m in sorted(root.glob("*/*/*/metrics.json")):
        role, scene, exp = m.parent.name, m.parent.parent.name, m.parent.parent.parent.name
        entry = json.loads(m.read_text())["test"]
        entry["source"] = json.loads((m.parent / "source.json").read_text())
        recs.setdefault((exp, role), {})[scene] = entry
    if not recs:
        raise SystemExit(f"studies/compact_prune.py test-table: no records under {root}; run `studies/compact_prune.py test` first")
    src = next(iter(next(iter(recs.values())).values()))["source"]
    lines = ["# Full and compact on test (budget=cpu, trunk seed 2, four shared D-NeRF scenes)", "",
             f"Generated by `python studies/compact_prune.py test-table` from {sum(map(len, recs.values()))} records at "
             f"commit {code_version().get('commit', '?')[:10]} on {machine_name()}, {time.strftime('%Y-%m-%d')}. "
             f"Runs' machines: {_machines({(k, s): v for k, d in recs.items() for s, v in d.items()})}. "
             f"Compact: the preset chosen on val (`{src['decision']}`"
             + (", + `stdr.mask_bits=8` for +STDR" if src["mask_bits_8"] else "") +
             "; protocol.md, amendment 4). Means over the scenes present (n); train s: the trunk's first "
             "1500 steps + the branch's 500.", "",
             "| baseline | method | n | PSNR | SSIM | LPIPS | FPS | Gaussians | seen/frame | model MB | train s |",
             "|" + "---|" * 11]
    for b in ("deform", "scgs", "spgs", "4dgs"):
        for exp in (f"dnerf_{b}", f"dnerf_{b}_stdr"):
            for role in ROLES:
                rows = list(recs.get((exp, role), {}).values())
                if not rows:
                    continue

                def f(k, fmt, rows=rows):
                    x = _mean(r.get(k) for r in rows)
                    return "–" if x is None else format(x, fmt)
                label = ("+STDR" if exp.endswith("_stdr") else "plain") + f" {role}"
                lines.append(f"| {b} | {label} | {len(rows)} | {f('psnr', '.2f')} | {f('ssim', '.4f')} | "
                             f"{f('lpips', '.4f')} | {f('fps', '.1f')} | {f('num_gaussians', ',.0f')} | "
                             f"{f('seen_per_frame', '.1%')} | {f('model_mb', '.2f')} | {f('train_seconds', '.0f')} |")
    targets = []
    for exp in EXPERIMENTS:
        full, comp = recs.get((exp, "full"), {}), recs.get((exp, "compact"), {})
        for key, what, op, bound in TARGETS:
            v = _compare(comp, full, key)
            targets.append({"method": exp, "target": what, "bound": f"{op} {bound}", "value": v,
                            "met": _meets(v, op, bound)})
    for b in ("deform", "scgs", "spgs", "4dgs"):
        st, pl = recs.get((f"dnerf_{b}_stdr", "compact"), {}), recs.get((f"dnerf_{b}", "compact"), {})
        for key, what, op, bound in STDR_TARGETS:
            v = _compare(st, pl, key)
            targets.append({"method": f"dnerf_{b}_stdr", "target": what, "bound": f"{op} {bound}", "value": v,
                            "met": _meets(v, op, bound)})
    lines += ["", "Compactness targets (ratios: geometric mean over the scenes of the per-scene ratio):", "",
              "| method | target | bound | measured | met |", "|---|---|---|---|---|"]
    for t in targets:
        v = "–" if t["value"] is None else f"{t['value']:+.2f}" if "PSNR" in t["target"] else f"{t['value']:.2f}"
        met = "–" if t["met"] is None else "yes" if t["met"] else "**no**"
        lines.append(f"| {t['method']} | {t['target']} | {t['bound']} | {v} | {met} |")
    split = bytes_split(recs)
    lines += ["", "Where the bytes are: model MiB = fixed part (deformation network, fields) + per-Gaussian bytes x N "
              "(+ STDR's mask), solved per scene from the full and the compact run (same method: the fixed part is "
              "untouched by pruning), means over the scenes:", "",
              "| method | fixed MiB | bytes per Gaussian (mask excluded) | mask MiB full | mask MiB compact |",
              "|---|---|---|---|---|"]
    for exp, b in split.items():
        lines.append(f"| {exp} | {b['fixed_mib']:.2f} | {b['bytes_per_gaussian']:.0f} | {b['mask_mib_full']:.2f} | "
                     f"{b['mask_mib_compact']:.2f} |")
    out = root.parent
    (out / "table_test.md").write_text("\n".join(lines) + "\n")
    (out / "table_test.json").write_text(json.dumps(
        {"targets": targets, "bytes_split": split, "records": {f"{e}/{r}/{s}": v for (e, r), d in recs.items() for s, v in d.items()}},
        indent=1, default=str))
    print("\n".join(lines))
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("dnerf", help="folder with the D-NeRF scenes")
    r.add_argument("--headline", required=True, help="the headline queue's WORK_DIR (its run folders)")
    r.add_argument("--seed", type=int, default=0, help="the trunks' seed: branch WORK/<exp>/<scene>/s<seed>")
    r.add_argument("--follow", action="store_true", help="wait for trunks the headline queue has yet to train")
    r.add_argument("--records", default=str(RECORDS), help="where the records go (default: the study's runs/)")
    r.add_argument("--hold", action="store_true", help="pause the headline queue (WORK/pause.compact) while branches "
                   "are runnable, so each trunk is branched before the next is trained")
    r.add_argument("--poll", type=float, default=30.0, help="with --follow: seconds between looks for new trunks")
    r.add_argument("--variants", nargs="*", choices=[*VARIANTS, *STDR_VARIANTS, *SCRATCH_VARIANTS],
                   help="only these variants (default: all)")
    r.add_argument("--scratch", action="store_true", help="also train the from-scratch time_bins variants "
                   "(protocol.md, amendment 2), one at a time whenever no trunk is waiting for its branches")
    r.add_argument("--work", default=str(ROOT / "outputs" / "compact"))
    r.add_argument("--code", default=str(ROOT), help="checkout whose scripts/run.sh trains (frozen at one commit)")
    r.add_argument("--experiments", nargs="*", choices=EXPERIMENTS, help="only these methods (default: all)")
    r.add_argument("--scenes", nargs="*", choices=SCENES, help="only these scenes' branches (default: all)")
    t = sub.add_parser("table")
    t.add_argument("--records", default=str(RECORDS))
    e = sub.add_parser("test", help="amendment 4: evaluate each full and compact run once on test")
    e.add_argument("dnerf", help="folder with the D-NeRF scenes")
    e.add_argument("--headline", required=True, help="the headline queue's WORK_DIR (the trunks)")
    e.add_argument("--seed", type=int, default=2, help="the trunks' seed")
    e.add_argument("--records", default=str(RECORDS), help="the val records (the decision; `preset` branches go here)")
    e.add_argument("--test-records", default=str(TEST_RECORDS), help="where the test records go")
    e.add_argument("--work", default=str(ROOT / "outputs" / "compact"), help="the branches' run folders (`run`'s --work)")
    e.add_argument("--code", default=str(ROOT), help="checkout whose scripts/run.sh trains and evaluates")
    e.add_argument("--experiments", nargs="*", choices=EXPERIMENTS, help="only these methods (default: all)")
    tt = sub.add_parser("test-table")
    tt.add_argument("--test-records", default=str(TEST_RECORDS))
    args = ap.parse_args(argv)
    return {"run": run_queue, "table": table, "test": run_test, "test-table": test_table}[args.cmd](args)


if __name__ == "__main__":
    raise SystemExit(main())
