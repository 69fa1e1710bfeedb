"""Structured configs: typed defaults registered with Hydra's ConfigStore.

YAML files under stdr/configs/ select and override these; every key a run used is written to the run
directory (config.yaml), and that file is what stdr-eval rebuilds the run from.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional


from .data.procedural import SceneOptions
from .data.stress import StressConfig
# every baseline's config dataclass lives beside its module (stdr.baselines.registry)
from .baselines import BASELINES, BaselineConfig, DeformConfig, HexPlaneConfig, ScgsConfig, SpgsConfig  # noqa: F401
from .plugins import registered_plugins
from .densify.prune import PruneConfig
from .densify.strategy import DensifyStrategy

#: the YAML config groups; they ship inside the package, so an installed wheel has them too
CONFIG_DIR = Path(__file__).resolve().parent / "configs"


@dataclass
class DataConfig:
    format: str = "procedural"  # procedural | dnerf | nerfies
    name: Optional[str] = "embedded"  # scene label in tables (null: the folder name)
    path: Optional[str] = None  # scene folder (dnerf, nerfies); procedural: the generated cache folder
    root: Optional[str] = None  # a dataset folder; the sweeps (stdr/configs/sweep) set path = root/<name>
    cache_dir: str = "data/embedded"  # where the procedural scene is generated (relative: under ~/.cache/stdr)
    background: Any = "white"   # white | black | [r, g, b]
    resolution_scale: float = 1.0
    max_width: Optional[int] = None  # after resolution_scale, cap the width (aspect kept)
    eval_split: str = "test"    # test | val (D-NeRF lego's test split disagrees with train)
    procedural: SceneOptions = field(default_factory=SceneOptions)  # generator options
    # Nerfies format (NeRF-DS, HyperNeRF; docs/data.md); nothing is read from folder names
    split_mode: Optional[str] = None  # ids (train_ids / val_ids) | interp (ids[::4] / ids[2::4]); required
    image_scale: Optional[int] = None  # N of the rgb/<N>x folder; intrinsics scale to match; required
    time_key: str = "auto"       # auto (time_id, else warp_id) | time_id | warp_id; t = key / max key
    normalize_scene: bool = True  # positions and points: (x - scene.json center) * scene.json scale
    distortion: str = "undistort"  # undistort (once, cached) | error | ignore (peers' pinhole, warned)
    intrinsics: str = "camera"   # camera (camera/<id>.json) | colmap (colmap/sparse/0)
    points_source: str = "auto"  # auto (points.npy, else COLMAP) | points_npy | colmap | none
    undistort_cache: Optional[str] = "data/cache/undistorted"  # relative: under ~/.cache/stdr; null: no cache
    scenes: List[str] = field(default_factory=list)  # the benchmark's scene folders (scripts iterate them)
    # a stressed training set, seeded; the evaluation splits untouched (stdr.data.stress, docs/stability.md)
    stress: StressConfig = field(default_factory=StressConfig)


@dataclass
class ModelConfig:
    init: str = "random"        # random (cube) | points (from the data)
    init_num: int = 100_000
    init_extent: float = 1.3
    init_opacity: float = 0.1
    sh_degree: int = 3
    sh_interval: int = 1000     # raise the active SH degree every this many iterations


@dataclass
class OptimConfig:
    iterations: int = 40_000
    lambda_dssim: float = 0.2
    spatial_lr_scale: float = 5.0   # Deformable 3DGS hard-codes 5 (not the scene extent)
    means_lr_init: float = 1.6e-4   # x spatial_lr_scale
    means_lr_final: float = 1.6e-6  # x spatial_lr_scale
    means_lr_max_steps: int = 30_000
    scales_lr: float = 1e-3         # x spatial_lr_scale
    quats_lr: float = 1e-3
    opacities_lr: float = 0.05
    sh0_lr: float = 2.5e-3
    shN_lr: float = 1.25e-4
    fused_adam: bool = True         # torch's fused Adam on CPU and CUDA (false: the for-loop one)
    # the photometric loss ((1 - lambda_dssim) L1 + lambda_dssim D-SSIM, with the step's PSNR) as one
    # compiled pass, forward and backward (stdr.metrics.image_loss_compiled), or its torch
    # twin (stdr.metrics.image_loss). null: compiled where it has been checked (stdr.verified.VERIFIED:
    # the CPU; the CUDA kernel passed its parity tests on an H100, not yet a full run) and the
    # extension builds; true / false
    fused_loss: Optional[bool] = None


@dataclass
class RenderConfig:
    backend: str = "auto"       # auto (cuda > cpu > reference) | cuda | cpu | reference
    tile_size: int = 0          # 0 = the backend's measured default (stdr.render.DEFAULT_TILE)
    antialiased: bool = False
    eps2d: float = 0.3
    near: float = 0.01
    # temporal culling (docs/stdr.md §6): rows whose opacity at time t (sigmoid(o) x the plug-ins' opacity factors)
    # is below 1/255 skip the deformation, projection and rasterizer; the image is unchanged.
    # off | eval (evaluation, FPS and every render outside training) | train (training too;
    # needs densify.count_invisible=false, since a culled row is not seen by densification)
    cull: str = "eval"
    # with a compiled backend, projection and SH shading run in the extension too (forward and
    # backward; csrc/project_math.h); false runs their torch twin (stdr/render/projection.py, sh.py).
    # null (auto): compiled on the backends whose kernels passed their checks on real hardware
    # (stdr.verified.VERIFIED: the CPU, and CUDA after its check on an H100)
    compiled_projection: Optional[bool] = None


@dataclass
class GuardConfig:
    """train.guard: non-finite and divergence recovery."""

    # on by default: without a fault it changes nothing (bit-identical to enabled=false in the
    # runs of tests/test_guard.py) and costs 0.2-0.6 % of a step
    enabled: bool = True
    snapshot_every: int = 100    # steps between in-memory snapshots of the last good state
    lr_factor: float = 0.5       # every learning rate x this at each recovery
    max_recoveries: int = 3      # one more stops the run (TrainingDiverged, checkpoint of the last good state)
    # a periodic evaluation (train.eval_every) more than this many dB below the best one so far
    # restores the best one's state (0 = off)
    divergence_db: float = 10.0
    # an evaluation within this many steps after an opacity reset (densify.reset_every) is not
    # compared with the best: the reset drops the render by design (a D-NeRF scene at budget=gpu:
    # 30.9 dB at step 2700, 15.2 dB right after the reset at 3000) and the model rebuilds it
    after_reset: int = 500
    # what the divergence detector evaluates. It restores earlier states, so what it reads steers
    # training, and it never reads the test split: auto = val where the scene has a val split of
    # its own (D-NeRF, the embedded scene), else train (Nerfies format: its val frames are its
    # test frames); or val, or train (a fixed seeded subset of the training frames)
    monitor: str = "auto"
    # frames of the detector's own evaluation (a fixed seeded subset; 0 = all). When the monitor
    # split is data.eval_split, the periodic evaluation itself is used (train.eval_frames)
    monitor_frames: int = 10
    # the step check without a host sync: its verdict stays a flag on the device, read at the steps
    # that wait for the device anyway (log, evaluation, checkpoint, snapshot, the end); fused Adam
    # skips every update from the faulty step on (its found_inf), and the read restores the last
    # snapshot, the state an immediate check restores. null: on where it has been checked
    # (stdr.verified.VERIFIED); true / false. Needs optim.fused_adam (false reads the check every step)
    sync_free: Optional[bool] = None
    # the check of a step's tensors as one compiled call (guard_update_compiled, below;
    # instead of two operators a tensor and ten for the verdict) or as torch operators. null: compiled
    # where it has been checked (stdr.verified.VERIFIED: the CPU; the CUDA kernel is built, not yet
    # run on a GPU) and the extension builds; true / false
    compiled: Optional[bool] = None
    # fault injection, for tests and drills: a NaN in the gradient of the means at each step
    # listed (counted from 1), once per process
    inject_nan_grad_at: List[int] = field(default_factory=list)


@dataclass
class TrainConfig:
    eval_every: int = 0         # periodic evaluation (0 = only at the end and end of warm-up) -> metrics.json curve
    eval_frames: int = 0        # frames of each periodic / warm-up evaluation: 0 = all, N = a fixed subset (seeded)
    eval_lpips: bool = False    # LPIPS in periodic evaluations too (the final one follows eval.lpips)
    eval_at_warmup_end: bool = True
    checkpoint_every: int = 5000
    # also a checkpoint after this many minutes of wall time since the last one (0: off): what a hard
    # kill can lose. Ctrl+C and SIGTERM checkpoint the step they stop at whatever this says
    checkpoint_minutes: float = 10.0
    log_every: int = 50
    image_every: int = 1000
    # resume from run_dir/checkpoints/last.pt when present (true | false: start over | override: resume
    # even though keys that change training differ from the run's config.yaml, which records it)
    resume: Any = True
    # stop after this iteration as an interrupted run would (checkpoint, no final evaluation; the
    # schedules follow optim.iterations; the same run without it resumes). deadline, start_by: Unix
    # times: stop there as at stop_at; not started after start_by (a Slurm slot, a rented GPU's hour)
    stop_at: Optional[int] = None
    deadline: Optional[float] = None
    start_by: Optional[float] = None
    skip_finished: bool = True  # in a sweep (-m): a run whose metrics.json exists is skipped, not retrained
    threads: int = 0            # torch threads (0 = torch default)
    progress: bool = True
    # non-finite loss / gradients / parameters and divergence: restore, lower the lrs, go on (docs/stability.md)
    guard: GuardConfig = field(default_factory=GuardConfig)


@dataclass
class EvalConfig:
    lpips: str = "auto"         # auto (if weights are found) | true (required) | false
    lpips_net: str = "vgg"
    lpips_weights: Optional[str] = None  # folder with <net>16_features.pth + lpips_v0.1_<net>_lin.pth
    # with lpips_weights unset and no weights found: download the official files once into the user
    # cache (SHA-256 pinned; stdr.eval.lpips.fetch_weights). Offline, the run still ends (LPIPS null)
    lpips_download: bool = True
    lpips_input: str = "[-1,1]"  # official convention; "[0,1]" reproduces the peers' usage
    fps_warmup: int = 3
    # timed passes (the quality pass is the first); fps: their median, all in metrics.json -> fps_passes
    fps_repeats: int = 3
    save_images: bool = True


@dataclass
class PackConfig:
    """The compact model file written at the end of training (stdr.compression.file; `stdr-tool
    pack` writes one for any trained run). `compact=on` turns it on with the codecs its study chose."""
    enabled: bool = False       # true: RUN/model.stdrc and RUN/pack.json after the final evaluation
    # per-tensor codecs over stdr.compression.file.DEFAULT_SPEC (e.g. {shN: "vq:1024", state: f16})
    codecs: Dict[str, str] = field(default_factory=dict)
    finetune: int = 0           # steps of the vq codebooks' fine-tune on the training frames (stdr.compact.finetune)
    finetune_state: Optional[str] = None  # and in its steps the quantized state with these parts ("grids")
    sh_degree: Optional[int] = None  # keep the SH rest to this degree's bands (null: all)
    evaluate: bool = True       # render the eval split from the file too (pack.json: PSNR / SSIM of both)


@dataclass
class Config:
    name: str = "embedded_deform"  # experiment name (run folder, tables)
    budget: str = "cpu"
    # the compact preset (stdr/configs/compact/<off|on>.yaml, docs/compactness.md): "on" sets the
    # pruning keys and the plug-ins' compact forms the compactness study chose; config.yaml keeps what it set
    compact: str = "off"
    seed: int = 0
    device: str = "auto"  # auto (cuda when torch sees a GPU, else cpu) | cpu | cuda | cuda:<index>
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    # the common keys; the option baseline=<name> (default deform) types it as that baseline's
    # registered dataclass (a subclass), which adds its own keys
    baseline: BaselineConfig = field(default_factory=BaselineConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    # the option densify=<name> (default `default`) types it as that registered strategy (a subclass)
    densify: DensifyStrategy = field(default_factory=DensifyStrategy)
    # contribution pruning at scheduled steps (stdr/densify/prune.py; off while prune.share=0)
    prune: PruneConfig = field(default_factory=PruneConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    pack: PackConfig = field(default_factory=PackConfig)
    # derived, read-only: every phase boundary of the run resolved from the keys above
    # (stdr.schedule.resolve_schedule); shown by `stdr-train --cfg job` and kept in config.yaml.
    # Setting it changes nothing: the model recomputes it from the keys.
    schedule: Dict[str, Any] = field(default_factory=lambda: "${stdr_schedule:}")
    # + one node per registered plug-in, `<name>: <its config dataclass>` (root_schema)


def _overrides_of(cls, name: str, doc: str, skip=()):
    """A dataclass with the fields of `cls` (but `skip`), each Optional and None by default: the
    keys a command changes in a saved config, the others keeping the config's own values."""
    import dataclasses
    import typing
    hints = typing.get_type_hints(cls)
    out = dataclasses.make_dataclass(name, [(f.name, Optional[hints[f.name]], None) for f in dataclasses.fields(cls)
                                            if f.name not in skip])
    out.__doc__ = doc
    return out


RenderOverrides = _overrides_of(RenderConfig, "RenderOverrides",
                                "stdr-eval: render keys to change in each run's config (null = the run's own).")


@dataclass
class EvalAppConfig:
    """stdr-eval: (re)evaluate run directories and write the comparison table."""

    runs: List[str] = field(default_factory=list)
    split: Optional[str] = None  # default: each run's data.eval_split
    out: Optional[str] = None    # table folder (default: outputs/tables/<timestamp>)
    reevaluate: bool = True      # False: only tabulate the metrics.json already in the runs
    eval: EvalConfig = field(default_factory=EvalConfig)
    # render settings to change in each run's own (e.g. render.backend=reference, render.cull=off);
    # the keys left null keep the run's value
    render: RenderOverrides = field(default_factory=lambda: RenderOverrides())
    device: Optional[str] = None  # override the runs' device (auto | cpu | cuda | cuda:<index>)
    # fps: re-time the render FPS alone (e.g. on an idle machine) and update only `fps` in each
    # run's metrics.json, keeping the earlier values under `fps_history`; quality is not touched.
    # size: add model_mb to runs evaluated before it was recorded. fps+size: both
    remeasure: Optional[str] = None
    # a run that has not finished (checkpoint before optim.iterations) is refused; true: evaluate its
    # last checkpoint into <out>/unfinished/<run folder name>/, never into the run
    unfinished: bool = False
    # a row whose runs differ in iterations, budget or code version is refused; true: tabulate it,
    # the row's label naming what differs
    allow_mixed: bool = False


_ROOTS: dict[tuple, tuple[type, type]] = {}


def _schemas() -> tuple[type, type]:
    """(run config, stdr-eval config) with one typed node per registered plug-in: `<name>` (its
    config dataclass) in the run's, `<name>` (the same keys, null = the run's own; `enabled`
    excluded) in stdr-eval's. Rebuilt when the plug-ins change."""
    import dataclasses
    specs = registered_plugins()
    key = tuple((s.name, s.config) for s in specs)
    if key not in _ROOTS:
        run = dataclasses.make_dataclass(
            "RunConfig", [(s.name, s.config, field(default_factory=s.config)) for s in specs], bases=(Config,))
        run.__doc__ = Config.__doc__
        over = []
        for s in specs:
            o = _overrides_of(s.config, f"{s.config.__name__}Overrides",
                              f"stdr-eval: {s.name} keys to change in each run's config (null = the run's own).",
                              skip=("enabled",))
            over.append((s.name, o, field(default_factory=o)))
        ev = dataclasses.make_dataclass("EvalRunsConfig", over, bases=(EvalAppConfig,))
        ev.__doc__ = EvalAppConfig.__doc__
        _ROOTS[key] = (run, ev)
    return _ROOTS[key]


def root_schema() -> type:
    """The run config's schema: Config plus a node per registered plug-in."""
    return _schemas()[0]


def eval_schema() -> type:
    """stdr-eval's schema: EvalAppConfig plus each plug-in's evaluation-time overrides."""
    return _schemas()[1]
