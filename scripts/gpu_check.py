"""The checks that need an NVIDIA GPU, staged to fit one short job (a time-limited cloud or Slurm job).

    python scripts/gpu_check.py OUT --scene DNERF_SCENE [--budget 420] [--stages a b ...]
    python scripts/gpu_check.py OUT --dry-run           # every stage's plumbing, CPU, toy sizes (CI)

Stages run in order of value; each has an estimate and a cap (seconds). A stage is skipped when
its estimate no longer fits before the deadline (`--budget`), and killed at its cap. After each
stage OUT holds everything that finished, in four files (few and small: a job that copies back only some files keeps them):

    summary.json   one record per stage: status (ok, failed, timeout, skipped), rc, seconds, and
                   the facts the stage extracted (test counts, a run's PSNR and seconds, ...)
    summary.md     the same as a table (`--report` prints it again from summary.json)
    progress.log   what the script printed
    results.tgz    every stage's log, pytest's junit XML, each run's metrics.json, config.yaml
                   and train_profile.json, the benchmarks' JSON and Markdown

Stages (GPU): env (GPU, torch, nvcc, Python packages: exit 3 when one is missing) -> build (the
CUDA extension, failing loudly: exit 4; the CPU extension builds beside it) -> kernels (the CUDA
parity tests of the projection + SH, the rasterizer, 4dgs's HexPlane sampling, the training loss and the guard's check, CUDA_LAUNCH_BLOCKING=1)
-> binning_memcheck (compute-sanitizer memcheck over the binning with its two passes made to
disagree) -> train_keys (short trainings with the speed keys through prunes, opacity resets,
evaluations and a guard recovery, against the torch forms; blocking launches) -> memcheck_keys (one
40-step training with the speed keys through the same events, under memcheck) -> proj_scale
(CUDA against the CPU extension at 200k and 1M Gaussians, both antialiasing modes) -> train_tests
(rasterizer at training scale; training + resume on CUDA, all four baselines with STDR; the compact
file's quantization-aware fine-tune on CUDA) ->
syncs_cuda (an ordinary training step of every baseline +- STDR makes no synchronizing call the
CUDA runtime reports; the guard's one) -> run_deform (a budget=cpu D-NeRF run, comparable to
research/measurements/gpu_check_h100) -> bench_train -> bench_train_fast (the same with the speed keys
whose CUDA kernels wait for this check: FAST) -> run_gpu_deform (deform at budget=gpu: a row
of a D-NeRF table in minutes) -> run_gpu_deform_fast (the same with FAST: the full-run half of
the rule in stdr/verified.py) -> run_gpu_deform_stdr -> run_deform_twin (the budget=cpu run with the torch projection +
SH: what the compiled one saves) -> bench_raster -> bench_train_compile (baseline.compile=true) ->
run_4dgs, run_deform_stdr, run_4dgs_stdr, run_scgs, run_spgs -> sanitize (compute-sanitizer
memcheck over every kernel of the extension) -> run_paper_deform, run_paper_scgs (budget=paper at
400 px, FAST on; a job each). Where compute-sanitizer cannot run (some virtual machines
refuse it the device), the stages that use it run without it and summary.md says so.

Training pins render.backend=cuda and render.compiled_projection=true: a broken build fails
instead of falling back to the pure-torch reference, and the kernels under test are the ones
that run. The CUDA build cache is STDR_EXT_DIR (default build/ext in this checkout, kept while a
device machine stays warm); a build lock left there by a killed call is removed at start (this
script is the cache's only user). In --dry-run every stage runs on the CPU at toy sizes: the
same code paths of this script, the same tools with the CPU backend, the embedded scene.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shlex
import shutil
import signal
import subprocess
import sys
import tarfile
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# the embedded scene at test size (stdr.testing.TINY_SCENE), for --dry-run
TINY = ["data.procedural.resolution=64", "data.procedural.n_train=40", "data.procedural.n_val=2",
        "data.procedural.n_test=4", "model.init_num=1500", "optim.iterations=30",
        "baseline.warmup=10"]  # the deformation (and STDR's phases, 10 / 20) inside the 30 steps
# the speed keys whose CUDA kernels wait for a GPU check (their defaults keep the torch forms on
# CUDA); 4dgs's baseline.hexplane.compiled is not among them (a key of 4dgs alone): the kernels
# stage checks that kernel
FAST = ["optim.fused_loss=true", "train.guard.compiled=true", "train.guard.sync_free=true"]
# memcheck_keys: deform+STDR on the embedded scene at test size, 40 steps with FAST through four
# densifications (clone, split, opacity and size prunes), an opacity reset, STDR's freeze, two
# evaluations and a guard recovery from a NaN injected at step 17 (the CPU's dry run: the same)
KEYS_RUN = ["experiment=embedded_deform_stdr", *TINY[:5], "optim.iterations=40", "baseline.warmup=10",
            "densify.refine_start=10", "densify.refine_every=5", "densify.refine_stop=30", "densify.reset_every=20",
            "densify.prune_big_after=20", "stdr.warmup_end=10", "stdr.freeze_at=20", "train.eval_every=15",
            "train.guard.snapshot_every=10", "train.guard.inject_nan_grad_at=[17]", "train.checkpoint_every=0",
            "train.progress=false", "eval.save_images=false", "eval.lpips=false", *FAST]
SANITIZE_PROBE = "--sanitize-probe"
SPEED_KEYS_TEST = "test_training_with_the_speed_keys_on_cuda_through_prunes_resets_and_a_recovery"
MEMCHECK = ["compute-sanitizer", "--tool", "memcheck", "--error-exitcode", "9"]
NO_SANITIZER = "compute-sanitizer cannot run on this machine: the stage runs without it"


def memchecked(cmd: list, py: str) -> list:
    """cmd under compute-sanitizer memcheck where the sanitizer can run here, else cmd alone after
    the line NO_SANITIZER (some virtual machines refuse it the device: "Device not supported").
    A one-allocation probe decides, so a refusal is not mistaken for an error the kernels made."""
    probe = shlex.join([*MEMCHECK, py, "-c", "import torch; torch.zeros(1, device='cuda').sum().item()"])
    full = shlex.join([str(c) for c in cmd])
    return ["bash", "-c", f"if {probe} >/dev/null 2>&1; then exec {shlex.join(MEMCHECK)} {full}; "
                          f"else echo {shlex.quote(NO_SANITIZER)}; exec {full}; fi"]


def sanitizer_facts(facts=None):
    """A stage's facts plus whether compute-sanitizer ran (memchecked's line absent)."""
    def f(text: str, res) -> dict:  # a line of its own: the log's first line, the command, quotes it
        ran = re.search(rf"^{re.escape(NO_SANITIZER)}$", text, flags=re.M) is None
        return {**(facts(text, res) if facts else {}), "sanitizer": ran}
    return f


@dataclass
class Stage:
    name: str
    est: int  # seconds expected on an H100 machine
    cap: int  # killed after this many seconds
    cmd: list
    env: dict = field(default_factory=dict)
    facts: object = None  # fn(log_text, res_dir) -> dict


class Runner:
    def __init__(self, out: Path, work: Path, budget: float, only: set[str]):
        self.out, self.work, self.budget, self.only = out, work, budget, only
        self.res = work / "res"
        self.res.mkdir(parents=True, exist_ok=True)
        self.t0 = time.monotonic()
        self.records: list[dict] = []
        self.header = {"started": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "host": platform.node(), "budget_s": budget}
        self.log = open(out / "progress.log", "a", buffering=1)

    def say(self, msg: str) -> None:
        line = f"[gpu_check {time.strftime('%H:%M:%S')}] {msg}"
        print(line, flush=True)
        self.log.write(line + "\n")

    def left(self) -> float:
        return self.budget - (time.monotonic() - self.t0)

    def pack(self) -> None:
        (self.out / "summary.json").write_text(json.dumps(self.records, indent=1) + "\n")
        (self.out / "summary.md").write_text(report(self.records, self.header))
        tmp = self.out / "results.tgz.tmp"
        with tarfile.open(tmp, "w:gz") as tar:
            tar.add(self.res, arcname="res")
        tmp.replace(self.out / "results.tgz")

    def run(self, st: Stage, always: bool = False) -> bool:
        rec = {"stage": st.name, "est_s": st.est}
        if not always and self.only and st.name not in self.only:
            return False
        left = self.left()
        if left < st.est:
            rec.update(status="skipped", rc=None, seconds=0, why=f"{left:.0f} s left < estimate {st.est} s")
            self.records.append(rec)
            self.say(f"{st.name}: skipped ({rec['why']})")
            self.pack()
            return False
        cap = max(1, int(min(st.cap, left)))
        self.say(f"{st.name}: start (cap {cap} s, {left:.0f} s left)")
        logf = self.res / f"{st.name}.log"
        t = time.monotonic()
        with open(logf, "w") as fh:
            fh.write("$ " + " ".join(map(str, st.cmd)) + "\n")
            fh.flush()
            proc = subprocess.Popen([str(c) for c in st.cmd], stdout=fh, stderr=subprocess.STDOUT, cwd=ROOT,
                                    env={**os.environ, **st.env}, start_new_session=True)
            try:
                rc = proc.wait(timeout=cap)
                status = "ok" if rc == 0 else "failed"
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                rc = proc.wait()
                status = "timeout"
        rec.update(status=status, rc=rc, seconds=round(time.monotonic() - t, 1))
        text = logf.read_text(errors="replace")
        if st.facts is not None:
            try:
                rec.update(st.facts(text, self.res))
            except Exception as e:  # a stage's facts must never hide its status
                rec["facts_error"] = repr(e)
        self.records.append(rec)
        tail = "\n".join("    " + ln for ln in text.rstrip().splitlines()[-6:])
        self.say(f"{st.name}: {status} (rc {rc}, {rec['seconds']} s)\n{tail}")
        self.pack()
        return status == "ok"


RUN_KEYS = (("psnr", "PSNR", "{:.2f}"), ("lpips", "LPIPS", "{:.4f}"), ("train_seconds", "train s", "{:.1f}"), ("num_gaussians", "#G", "{:,}"),
            ("fps", "FPS", "{:.1f}"), ("projection", "projection", "{}"), ("backend", "backend", "{}"))


def report(records: list[dict], header: dict | None = None) -> str:
    """summary.json as a Markdown table: one row per stage with its status, seconds and facts."""
    lines = ["# GPU check summary", ""]
    if header:
        lines += [", ".join(f"{k}: {v}" for k, v in header.items()), ""]
    lines += ["| stage | status | s | facts |", "|---|---|---|---|"]
    for r in records:
        facts = []
        for k in ("passed", "failed", "skipped", "errors", "error"):
            if k in r:
                facts.append(f"{r[k]} {k}")
        if r.get("failing"):
            facts.append("failing: " + ", ".join(r["failing"]))
        for k, label, fmt in RUN_KEYS:
            if r.get(k) is not None:
                facts.append(f"{label} {fmt.format(r[k])}")
        if r.get("sanitizer") is False:
            facts.append("WITHOUT compute-sanitizer (it cannot run here)")
        if r.get("why"):
            facts.append(r["why"])
        if r.get("facts_error"):
            facts.append("facts not read: " + r["facts_error"])
        lines.append(f"| {r['stage']} | {r['status']} | {r['seconds']} | {'; '.join(facts) or '–'} |")
    return "\n".join(lines) + "\n"


def pytest_facts(text: str, _res) -> dict:
    """The counts of pytest's summary line and the failing test ids."""
    out = {}
    m = re.findall(r"(\d+) (passed|failed|skipped|errors?|deselected)", text.splitlines()[-1] if text else "")
    for n, k in m:
        out[k] = int(n)
    fails = re.findall(r"^(?:FAILED|ERROR) (\S+)", text, flags=re.M)
    if fails:
        out["failing"] = fails
    return out


def run_facts(name: str, run_dir: Path):
    """Copy a run's small files into res/runs/NAME and extract its test numbers."""
    def facts(_text, res: Path) -> dict:
        dest = res / "runs" / name
        dest.mkdir(parents=True, exist_ok=True)
        for f in ("metrics.json", "config.yaml", "train_profile.json"):
            if (run_dir / f).is_file():
                shutil.copy2(run_dir / f, dest / f)
        m = json.loads((run_dir / "metrics.json").read_text())["test"]
        keys = ("psnr", "ssim", "lpips", "train_seconds", "num_gaussians", "fps", "peak_memory_mb")
        out = {k: m.get(k) for k in keys if k in m}
        conv = m.get("conventions", {})
        out.update(device=conv.get("device"), backend=conv.get("render_backend"), lpips_kind=conv.get("lpips"),
                   projection=conv.get("render_projection"))
        return out
    return facts


def build_stages(args, py: str, dry: bool) -> tuple[list[Stage], list[Stage]]:
    """(env and build, which always run; the rest in order of value)."""
    res = args.work / "res"
    pyt = [py, "-m", "pytest", "-q", "-rfEs", "-p", "no:cacheprovider", "--durations=15"]
    junit = lambda name: [f"--junitxml={res / (name + '.xml')}"]  # noqa: E731
    env_code = ("import importlib, platform, torch; "
                "mods = ['hydra', 'omegaconf', 'plyfile', 'tensorboard', 'imageio', 'cv2', 'skimage', 'pytest', 'tqdm', 'matplotlib']; "
                "missing = [m for m in mods if importlib.util.find_spec(m) is None]; "
                "print('python', platform.python_version(), 'torch', torch.__version__, 'cuda', torch.version.cuda, "
                "'gpu', torch.cuda.get_device_name(0) if torch.cuda.is_available() else None); "
                "print('missing python packages:', missing) if missing else print('python packages: ok'); "
                "raise SystemExit(3 if missing else 0)")
    kind = "cpu" if dry else "cuda"
    build_code = ("import time; from stdr import extension as c; t = time.time(); "
                  f"m = c.load_extension('{kind}', verbose=True); "
                  f"print('{kind} extension in %.1f s: %s' % (time.time() - t, m.__file__))")
    first = [Stage("env", 15, 60, ["bash", "-c", ("nvidia-smi -L && nvidia-smi --query-gpu=name,driver_version,memory.total,"
                                                   "clocks.max.sm --format=csv && (nvcc --version | tail -2); " if not dry else "")
                                   + f"{py} -c \"{env_code}\""], facts=lambda t, r: {"lines": t.splitlines()[1:8]}),
             Stage("build", 60, 240, [py, "-c", build_code])]

    def train(name: str, exp: str, est: int, cap: int, projection: str = "true", budget: str = "cpu",
              extra: tuple = ()) -> Stage:
        d = args.work / "runs" / name
        if dry:
            base = [f"experiment=embedded_{exp}", *([f"budget={budget}"] if budget != "cpu" else []), "device=cpu",
                    "render.backend=cpu", *TINY, f"data.cache_dir={args.work / 'cache'}"]
        else:
            base = [f"experiment=dnerf_{exp}", f"budget={budget}", "device=cuda", "render.backend=cuda",
                    f"data.path={args.scene}", f"data.name={args.scene.name}"]
        cmd = [py, "-m", "stdr.cli.train", *base, f"render.compiled_projection={projection}", *extra,
               "train.progress=false", "eval.save_images=false", f"hydra.run.dir={d}"]
        env = {}
        if args.lpips_weights:  # LPIPS-vgg (the default) where its weights came, else LPIPS-alex (metrics say which)
            env["STDR_LPIPS_WEIGHTS"] = str(args.lpips_weights.resolve())
            if not (args.lpips_weights / "lpips_v0.1_vgg_lin.pth").is_file():
                cmd.insert(-1, "eval.lpips_net=alex")
        return Stage(name, est, cap, cmd, env=env, facts=run_facts(name, d))

    if dry:
        kernels = pyt + junit("kernels") + ["tests/test_compiled.py", "tests/test_hexplane_compiled.py",
                                            "tests/test_fused_loss.py", "tests/test_guard.py", "-k",
                                            "(projection_and_sh_match_the_torch_twin or sampling_matches_the_torch_twin or "
                                            "loss_matches_the_torch_twin or compiled_step_update) and cpu"]
        scale = pyt + junit("proj_scale") + ["tests/test_compiled.py", "-k", "cuda_projection_matches_the_cpu_extension_at_scale"]
        ttests = pyt + junit("train_tests") + ["tests/test_device.py", "-k", "device_names_resolve"]
        binning = pyt + junit("binning_memcheck") + ["tests/test_binning.py"]
        train_keys = pyt + junit("train_keys") + ["tests/test_device.py", "-k", "device_names_resolve"]
        memcheck_keys = [py, "-m", "stdr.cli.train", *KEYS_RUN, "device=cpu", "render.backend=cpu",
                         f"data.cache_dir={args.work / 'cache'}", f"hydra.run.dir={args.work / 'runs' / 'memcheck_keys'}"]
        syncs = pyt + junit("syncs_cuda") + ["tests/test_syncs.py", "-k", "counter"]
        braster = [py, "-m", "stdr.tools.bench_rasterizer", "--backends", "cpu", "--n", "2000", "--res", "64", "--repeats", "1"]
        btrain_x = ["--experiments", "embedded_deform", "--gaussians", "1000", "--res", "64", "--iters", "2",
                    "--warmup-iters", "1", "--", "device=cpu", "render.backend=cpu", *TINY[:4], f"data.cache_dir={args.work / 'cache'}"]
        sanitize = [py, str(Path(__file__).resolve()), SANITIZE_PROBE, "cpu"]
    else:
        kernels = pyt + junit("kernels") + ["tests/test_compiled.py", "tests/test_contribution.py",
                                            "tests/test_hexplane_compiled.py", "tests/test_fused_loss.py",
                                            "tests/test_guard.py", "-k",
                                            "cuda and not nvcc and not torch_headers and not training_scale and not benchmark_row and not at_scale"]
        scale = pyt + junit("proj_scale") + ["tests/test_compiled.py", "-k", "cuda_projection_matches_the_cpu_extension_at_scale"]
        ttests = pyt + junit("train_tests") + ["tests/test_compiled.py", "tests/test_device.py", "tests/test_compact_file.py",
                                               "-k", "training_scale or training_on_cuda or (benchmark_row and not cpu) "
                                               "or fine_tune_on_cuda"]
        syncs = pyt + junit("syncs_cuda") + ["tests/test_syncs.py", "-k", "cuda or counter"]
        # the binning with its passes made to disagree, under memcheck (seconds)
        binning = memchecked([*pyt, *junit("binning_memcheck"), "tests/test_binning.py"], py)
        # short trainings with the speed keys through prunes, resets, evaluations and a recovery,
        # against the torch forms, launches blocking (an illegal access raises at its kernel):
        # under memcheck the first of its two cases had not finished after 270 s on an H200
        train_keys = pyt + junit("train_keys") + [f"tests/test_device.py::{SPEED_KEYS_TEST}"]
        # ... so memcheck gets one run of its own, 40 steps with the keys through the same events
        memcheck_keys = memchecked([py, "-m", "stdr.cli.train", *KEYS_RUN, "device=cuda", "render.backend=cuda",
                                    f"data.cache_dir={args.work / 'cache'}",
                                    f"hydra.run.dir={args.work / 'runs' / 'memcheck_keys'}"], py)
        braster = [py, "-m", "stdr.tools.bench_rasterizer", "--backends", "cuda", "--n", "10000", "100000", "1000000",
                   "--res", "400", "800", "--repeats", "20", "--peak-gflops", os.environ.get("STDR_GPU_PEAK_GFLOPS", "67000")]
        btrain_x = ["--experiments", "dnerf_deform", "dnerf_4dgs", "--gaussians", "10000", "50000", "--res", "200", "400",
                    "--iters", "20", "--warmup-iters", "5", "--", f"data.path={args.scene}", "budget=cpu", "device=cuda",
                    "render.backend=cuda", "render.compiled_projection=true"]
        sanitize = memchecked([py, str(Path(__file__).resolve()), SANITIZE_PROBE, "cuda"], py)
    braster += ["--json", str(res / "bench_raster.json"), "--markdown", str(res / "bench_raster.md")]
    btrain = [py, "-m", "stdr.cli.tool", "bench-train", "--out", str(res / "bench_train"), *btrain_x]
    # the same rows with every speed key that waits for a GPU check on (what flipping their
    # stdr.verified.VERIFIED entries would give), and with the deformation MLP through torch.compile
    btrain_fast = [py, "-m", "stdr.cli.tool", "bench-train", "--out", str(res / "bench_train_fast"), *btrain_x, *FAST]
    btrain_compile = [py, "-m", "stdr.cli.tool", "bench-train", "--out", str(res / "bench_train_compile"),
                      *btrain_x, *FAST, "baseline.compile=true"]
    rest = [
        Stage("kernels", 45, 150, kernels, env={"CUDA_LAUNCH_BLOCKING": "1"}, facts=pytest_facts),
        Stage("binning_memcheck", 30, 90, binning, env={"CUDA_LAUNCH_BLOCKING": "1", "PYTORCH_NO_CUDA_MEMORY_CACHING": "1"},
              facts=sanitizer_facts(pytest_facts) if not dry else pytest_facts),
        Stage("train_keys", 60, 150, train_keys, env={"CUDA_LAUNCH_BLOCKING": "1"}, facts=pytest_facts),
        Stage("memcheck_keys", 120, 240, memcheck_keys, env={"PYTORCH_NO_CUDA_MEMORY_CACHING": "1"},
              facts=sanitizer_facts() if not dry else None),
        Stage("proj_scale", 40, 120, scale, facts=pytest_facts),
        Stage("train_tests", 90, 200, ttests, facts=pytest_facts),
        Stage("syncs_cuda", 60, 150, syncs, facts=pytest_facts),
        train("run_deform", "deform", 80, 150),
        Stage("bench_train", 70, 150, btrain),
        Stage("bench_train_fast", 70, 150, btrain_fast),
        train("run_gpu_deform", "deform", 330, 420, budget="gpu"),  # the budget=gpu preset: a row
        # ... with the speed keys: with run_gpu_deform, the full-run pair a CUDA default needs (stdr/verified.py)
        train("run_gpu_deform_fast", "deform", 330, 420, budget="gpu", extra=FAST),
        train("run_gpu_deform_stdr", "deform_stdr", 360, 450, budget="gpu"),  # ... and its +STDR twin
        train("run_deform_twin", "deform", 80, 150, projection="false"),  # the torch projection: the same run
        Stage("bench_raster", 50, 120, braster),
        Stage("bench_train_compile", 110, 200, btrain_compile),
        train("run_4dgs", "4dgs", 95, 170),
        train("run_deform_stdr", "deform_stdr", 85, 160),
        train("run_4dgs_stdr", "4dgs_stdr", 100, 180),
        train("run_scgs", "scgs", 100, 180),
        train("run_spgs", "spgs", 100, 180),
        Stage("sanitize", 90, 150, sanitize, env={"PYTORCH_NO_CUDA_MEMORY_CACHING": "1"},
              facts=sanitizer_facts() if not dry else None),
        # the published budget (40k iterations) at the scene's 400 px: a call of its own each
        # (--stages run_paper_deform); SC-GS publishes per-scene numbers at 400 px
        train("run_paper_deform", "deform", 540, 590, budget="paper", extra=FAST),
        train("run_paper_scgs", "scgs", 570, 590, budget="paper", extra=FAST),
    ]
    if dry:  # the dry run has no time estimates to honour: toy sizes everywhere
        for st in first + rest:
            st.est = 0
    return first, rest


def sanitize_probe(kind: str) -> None:
    """One small render() forward + backward through every kernel of the extension (projection +
    SH, pack, tiles, forward, backward), both antialiasing modes and two tile sizes, the HexPlane
    sampling forward and backward, the training loss forward and backward and the guard's check."""
    import torch

    sys.path.insert(0, str(ROOT))
    from stdr.render import render
    from stdr.tools.bench_rasterizer import make_scene

    (means, quats, scales, opac, _), cam = make_scene(3000, 96, coverage=5.0, seed=1)
    sh = torch.randn(3000, 16, 3, generator=torch.Generator().manual_seed(2)) * 0.3
    xs = [x.to(kind).requires_grad_(True) for x in (means, quats, scales, opac, sh)]
    for aa, tile in ((False, 16), (True, 8)):
        out = render(*xs, cam, 3, background=torch.ones(3), backend=kind, antialiased=aa, tile_size=tile,
                     compiled_projection=True)
        (out.image.square().sum() + out.depth.sum() + out.alpha.sum()).backward()
    # 4dgs's HexPlane sampling (forward and the planes' backward), points inside and outside
    from stdr.baselines.fourdgs import hexplane_compiled
    g = torch.Generator().manual_seed(3)
    planes = [torch.rand(8, h, w, generator=g).to(kind).requires_grad_(True)
              for h, w in ((32, 32), (32, 32), (25, 32), (32, 32), (25, 32), (25, 32)) * 2]
    coords = (torch.rand(5000, 4, generator=g) * 2.4 - 1.2).to(kind)
    (hexplane_compiled(coords, planes, kind) ** 2).sum().backward()
    # the training loss (forward, backward) and the guard's check (a clean list, then a NaN in a
    # tensor beyond the first block's elements)
    from stdr.metrics import image_loss_compiled
    from stdr.train.guard import guard_update_compiled
    img = torch.rand(37, 53, 3, generator=g).to(kind).requires_grad_(True)
    image_loss_compiled(img, torch.rand(37, 53, 3, generator=g).to(kind), 0.2)[0].backward()
    flag, step, index = (torch.zeros((), device=kind), torch.full((), -1, device=kind),
                         torch.full((), -1, device=kind))
    bad = torch.ones(70_000, device=kind)
    bad[-1] = float("nan")
    guard_update_compiled([img.grad, *planes], flag, step, index, 5)
    guard_update_compiled([img.grad, bad], flag, step, index, 6)
    if kind == "cuda":
        torch.cuda.synchronize()
    sums = [float(x.grad.abs().sum()) for x in xs + planes + [img]]
    assert all(s > 0 and s == s for s in sums), sums
    assert (float(flag), int(step), int(index)) == (1.0, 6, 1), (flag, step, index)
    print("ok: gradient sums", sums, "guard", float(flag), int(step), int(index))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path)
    ap.add_argument("--scene", type=Path, default=None, help="a D-NeRF scene folder (GPU mode)")
    ap.add_argument("--budget", type=float, default=420.0, help="seconds for all stages (deadline)")
    ap.add_argument("--stages", nargs="*", default=[], help="only these (env and build always run)")
    ap.add_argument("--dry-run", action="store_true", help="CPU, toy sizes: the plumbing of every stage")
    ap.add_argument("--work", type=Path, default=None, help="scratch folder (default: a new temporary one)")
    ap.add_argument("--lpips-weights", type=Path, default=None, help="a folder of LPIPS weights for the runs")
    ap.add_argument("--python", default=sys.executable)
    ap.add_argument("--report", action="store_true", help="only print OUT/summary.json as Markdown")
    args = ap.parse_args(argv)
    if args.report:
        print(report(json.loads((args.out / "summary.json").read_text())), end="")
        return 0
    if not args.dry_run and (args.scene is None or not (args.scene / "transforms_train.json").is_file()):
        ap.error(f"--scene must be a D-NeRF scene folder with transforms_train.json (got {args.scene})")
    args.out.mkdir(parents=True, exist_ok=True)
    args.work = args.work or Path(tempfile.mkdtemp(prefix="stdr_gpu_check_"))
    if args.scene is not None:
        args.scene = args.scene.resolve()
    os.environ["PYTHONUNBUFFERED"] = "1"
    os.environ["PYTHONPATH"] = str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")
    if not args.dry_run:
        ext = Path(os.environ.setdefault("STDR_EXT_DIR", str(ROOT / "build" / "ext")))
        for lock in ext.glob("*/lock"):  # left by a build that an earlier call's time-out killed
            lock.unlink()
    runner = Runner(args.out, args.work, args.budget, set(args.stages))
    runner.say(f"{'dry run (CPU)' if args.dry_run else 'GPU check'} on {platform.node()}, budget {args.budget:.0f} s, "
               f"work {args.work}")
    first, rest = build_stages(args, args.python, args.dry_run)
    if not runner.run(first[0], always=True):
        runner.say("environment not usable: see res/env.log")
        return 3
    cpu_build = None
    if not args.dry_run:  # the CPU extension (the CUDA-vs-CPU tests need it) builds beside the CUDA one
        cpu_build = subprocess.Popen([args.python, "-c", "from stdr import extension; extension.load_extension('cpu')"],
                                     cwd=ROOT, stdout=open(args.work / "res" / "build_cpu.log", "w"),
                                     stderr=subprocess.STDOUT)
    if not runner.run(first[1], always=True):
        runner.say("the extension did not build: see res/build.log")
        return 4
    if cpu_build is not None:
        cpu_build.wait()
    for st in rest:
        runner.run(st)
    runner.pack()
    bad = [r["stage"] for r in runner.records if r["status"] in ("failed", "timeout")]
    runner.say(f"done in {time.monotonic() - runner.t0:.0f} s; "
               + (f"FAILED: {', '.join(bad)}" if bad else "no stage failed")
               + f"; skipped: {', '.join(r['stage'] for r in runner.records if r['status'] == 'skipped') or 'none'}")
    return 1 if bad else 0


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == SANITIZE_PROBE:
        sanitize_probe(sys.argv[2])
        sys.exit(0)
    sys.exit(main())
