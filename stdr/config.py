"""Structured configs: typed defaults registered with Hydra's ConfigStore.

YAML files under stdr/configs/ select and override these; every key a run used is written to the run
directory (config.yaml), and that file is what stdr-eval rebuilds the run from.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional

from hydra.core.config_store import ConfigStore
from omegaconf import OmegaConf

from .data.procedural import SceneOptions
from .data.stress import StressConfig
# every baseline's config dataclass lives beside its module (stdr.deform.registry)
from .deform import BASELINES, BaselineConfig, DeformConfig, HexPlaneConfig, ScgsConfig, SpgsConfig  # noqa: F401
from .deform.registry import BaselineSpec, add_listener, discover_baselines, get_baseline
from .scene.strategy import DensifyStrategy
from .train.guard import GuardConfig

#: the YAML config groups; they ship inside the package, so an installed wheel has them too
CONFIG_DIR = Path(__file__).resolve().parent / "configs"


@dataclass
class DataConfig:
    format: str = "procedural"  # procedural | dnerf | nerfies
    name: Optional[str] = "embedded"  # scene label in tables (null: the folder name)
    path: Optional[str] = None  # scene folder (dnerf, nerfies); procedural: the generated cache folder
    root: Optional[str] = None  # a dataset folder; the sweeps (stdr/configs/sweep) set path = root/<name>
    cache_dir: str = "data/embedded"  # where the procedural scene is generated (relative: under the checkout, or ~/.cache/stdr when installed)
    background: Any = "white"   # white | black | [r, g, b]
    resolution_scale: float = 1.0
    max_width: Optional[int] = None  # after resolution_scale, cap the width (aspect kept)
    eval_split: str = "test"    # test | val (D-NeRF lego's test split disagrees with train)
    procedural: SceneOptions = field(default_factory=SceneOptions)  # generator options
    # Nerfies format (NeRF-DS, HyperNeRF); docs/data.md. Nothing is read from folder names.
    split_mode: Optional[str] = None  # ids (train_ids / val_ids) | interp (ids[::4] / ids[2::4]); required
    image_scale: Optional[int] = None  # N of the rgb/<N>x folder; intrinsics scale to match; required
    time_key: str = "auto"       # auto (time_id, else warp_id) | time_id | warp_id; t = key / max key
    normalize_scene: bool = True  # positions and points: (x - scene.json center) * scene.json scale
    distortion: str = "undistort"  # undistort (once, cached) | error | ignore (peers' pinhole, warned)
    intrinsics: str = "camera"   # camera (camera/<id>.json) | colmap (colmap/sparse/0)
    points_source: str = "auto"  # auto (points.npy, else COLMAP) | points_npy | colmap | none
    undistort_cache: Optional[str] = "data/cache/undistorted"  # repo-relative; null: no cache
    scenes: List[str] = field(default_factory=list)  # the benchmark's scene folders (scripts iterate them)
    # a stressed training set (dropped or sparse times, fewer frames, pose and time noise), seeded;
    # the evaluation splits are untouched (stdr.data.stress, docs/stability.md)
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
class StdrConfig:
    """STDR plug-in (docs/stdr.md: what the paper says, what is chosen here, and why)."""

    enabled: bool = False
    # ablation switches
    mask: bool = True             # false: no mask (the field, if on, gets a uniform p)
    temporal_reg: bool = True
    spatial_reg: bool = True
    separated_field: bool = True
    # the mask
    time_bins: int = 0            # 0: one column per distinct training time; else K evenly spaced bins
    mask_init: Optional[float] = 2.0  # initial logit; null: sigmoid(o) * sigmoid(m) = model.init_opacity
    opacity_init: Optional[float] = None  # opacity held during the warm-up; null: model.init_opacity
    mask_lr: float = 0.05         # Adam lr of the mask logits (that of opacity logits)
    mask_after_freeze: bool = True  # the frozen sigmoid mask keeps modulating opacity
    prune_by_mask: bool = True    # prune on sigmoid(o) * max_t mask, the opacity a Gaussian reaches
    freeze_cleanup: float = 0.0   # at the freeze, switch off mask entries with sigmoid(o) * mask below this
    # phases: static_warmup = the baseline's static warm-up (baseline.warmup) and twice it;
    # fraction = warmup_fraction / freeze_fraction of optim.iterations. Explicit steps win.
    phase_rule: str = "static_warmup"
    warmup_fraction: float = 0.075  # the paper's 3000 / 40000
    freeze_fraction: float = 0.15   # the paper's 6000 / 40000
    warmup_end: Optional[int] = None
    freeze_at: Optional[int] = None
    # true: the paper's text, opacity frozen in the warm-up. false (default): opacity trains with
    # the mask; on the val split it gained +0.83 dB over true (docs/notes/2026-11-24-stdr-measurements.md, fidelity study, candidate 5)
    freeze_opacity: bool = False
    # regularizers
    lambda_temp: float = 0.1      # x L_temp = sum (or mean) over i, t of (mask_t - mask_{t+1})^2
    temporal_reduction: str = "mean"  # sum: the paper's formula; mean: divided by N(K-1)
    lambda_spatial: float = 0.2   # x mean KL(p_i || p_j) over sampled Gaussians and their KNN
    knn_samples: int = 1000
    knn_candidates: int = 20000
    knn_k: int = 5
    knn_every: int = 100          # resample queries and recompute neighbours (and after densification)
    # separated deformation field
    field_width: int = 64
    temporal_dim: int = 16
    dropout: float = 0.1
    field_pe_xyz: bool = False    # also feed PE(x) (baseline.xyz_freqs) to the field
    # the field's own lr schedule: null follows the deformation network's (baseline.lr_*); a value
    # starts at the freeze (where the field starts training) and decays log-linearly to
    # field_lr_final (null: constant) at the end of the run
    field_lr_init: Optional[float] = None
    field_lr_final: Optional[float] = None
    scale_deltas_by_dynamic: bool = False  # multiply the deformation deltas by the dynamic probability


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


@dataclass
class RenderConfig:
    backend: str = "auto"       # auto (cuda > cpu > reference) | cuda | cpu | reference
    tile_size: int = 0          # 0 = the backend's measured default (stdr.render.DEFAULT_TILE)
    antialiased: bool = False
    eps2d: float = 0.3
    near: float = 0.01
    # temporal culling (docs/stdr.md §6): rows whose opacity at time t (sigmoid(o) x STDR's mask)
    # is below 1/255 skip the deformation, projection and rasterizer; the image is unchanged.
    # off | eval (evaluation, FPS and every render outside training) | train (training too;
    # needs densify.count_invisible=false, since a culled row is not seen by densification)
    cull: str = "eval"
    # with a compiled backend, projection and SH shading run in the extension too (forward and
    # backward; csrc/project_math.h); false runs their torch twin (stdr/render/projection.py, sh.py).
    # null (auto): compiled on the backends whose kernels passed their checks on real hardware
    # (stdr.render.VERIFIED_PROJECTION: the CPU, and CUDA since the H100 check of 2026-11-26)
    compiled_projection: Optional[bool] = None


@dataclass
class TrainConfig:
    eval_every: int = 0         # periodic evaluation (0 = only at the end and end of warm-up) -> metrics.json curve
    eval_frames: int = 0        # frames of each periodic / warm-up evaluation: 0 = all, N = a fixed subset (seeded)
    eval_lpips: bool = False    # LPIPS in periodic evaluations too (the final one follows eval.lpips)
    eval_at_warmup_end: bool = True
    checkpoint_every: int = 5000
    log_every: int = 50
    image_every: int = 1000
    resume: bool = True         # resume from run_dir/checkpoints/last.pt when present
    skip_finished: bool = True  # in a sweep (-m): a run whose metrics.json exists is skipped, not retrained
    threads: int = 0            # torch threads (0 = torch default)
    progress: bool = True
    # non-finite loss / gradients / parameters and divergence: restore, lower the lrs, go on
    # (docs/stability.md)
    guard: GuardConfig = field(default_factory=GuardConfig)


@dataclass
class EvalConfig:
    lpips: str = "auto"         # auto (if weights are found) | true (required) | false
    lpips_net: str = "vgg"
    lpips_weights: Optional[str] = None  # folder with <net>16_features.pth + lpips_v0.1_<net>_lin.pth
    lpips_input: str = "[-1,1]"  # official convention; "[0,1]" reproduces the peers' usage
    fps_warmup: int = 3
    # timed passes over the split (the quality pass is the first); fps is the median pass, all
    # passes are kept in metrics.json -> fps_passes. Single passes on a busy CPU vary by ~35 %
    fps_repeats: int = 3
    save_images: bool = True


@dataclass
class Config:
    name: str = "embedded_deform"  # experiment name (run folder, tables)
    budget: str = "cpu"
    seed: int = 0
    device: str = "auto"  # auto (cuda when torch sees a GPU, else cpu) | cpu | cuda | cuda:<index>
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    # the common keys; the option baseline=<name> (default deform) types it as that baseline's
    # registered dataclass (a subclass), which adds its own keys
    baseline: BaselineConfig = field(default_factory=BaselineConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    densify: DensifyStrategy = field(default_factory=DensifyStrategy)  # the strategy is its own schema
    stdr: StdrConfig = field(default_factory=StdrConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    # derived, read-only: every phase boundary of the run resolved from the keys above
    # (stdr.schedule.resolve_schedule); shown by `stdr-train --cfg job` and kept in config.yaml.
    # Setting it changes nothing: the model recomputes it from the keys.
    schedule: Dict[str, Any] = field(default_factory=lambda: "${stdr_schedule:}")


def _overrides_of(cls, name: str, doc: str):
    """A dataclass with the fields of `cls`, each Optional and None by default: the keys a
    command changes in a saved config, the others keeping the config's own values."""
    import dataclasses
    import typing
    hints = typing.get_type_hints(cls)
    out = dataclasses.make_dataclass(name, [(f.name, Optional[hints[f.name]], None) for f in dataclasses.fields(cls)])
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


def _schedule_resolver(*, _root_) -> dict:
    from .schedule import resolve_schedule
    return resolve_schedule(_root_).as_dict()


def data_options() -> list[str]:
    """The options of the `data` group (stdr/configs/data/*.yaml)."""
    return sorted(p.stem for p in (CONFIG_DIR / "data").glob("*.yaml"))


def _experiment_files() -> set[str]:
    return {p.stem for p in (CONFIG_DIR / "experiment").glob("*.yaml")}


def derived_experiments(name: str) -> dict[str, dict]:
    """The experiments baseline `name` gets: `<data>_<name>` and `<data>_<name>_stdr` for every
    data option, each selecting data, baseline and stdr, plus what every experiment on that
    data adds (stdr/configs/experiment_data/<data>.yaml, optional: e.g. init from the capture's
    points). A YAML file stdr/configs/experiment/<same name>.yaml, when present, is used instead."""
    files = _experiment_files()
    out = {}
    for d in data_options():
        for suffix, stdr in (("", "off"), ("_stdr", "on")):
            exp = f"{d}_{name}{suffix}"
            if exp not in files:
                out[exp] = {"defaults": [{"optional /experiment_data": d}, {"override /data": d},
                                         {"override /baseline": name}, {"override /stdr": stdr}],
                            "name": exp}
    return out


def experiment_names() -> list[str]:
    """Every experiment `stdr-train experiment=<name>` accepts."""
    return sorted(_experiment_files() | {e for b in BASELINES for e in derived_experiments(b)})


def _sync_baseline(spec: BaselineSpec, added: bool) -> None:
    """Keep Hydra's ConfigStore in step with the registry: the option baseline=<name> (the
    registered dataclass: typed defaults) and its derived experiments."""
    cs = ConfigStore.instance()
    if added:
        cs.store(group="baseline", name=spec.name, node=spec.config)
        for exp, node in derived_experiments(spec.name).items():
            cs.store(group="experiment", name=exp, node=node, package="_global_")
    else:
        cs.repo.get("baseline", {}).pop(f"{spec.name}.yaml", None)
        for exp in derived_experiments(spec.name):
            cs.repo.get("experiment", {}).pop(f"{exp}.yaml", None)


def _experiments_resolver(data: str, *which: str) -> str:
    """`${stdr_experiments:dnerf}`: every experiment on data option `data` (each registered
    baseline, plain and +STDR) as a comma-separated sweep list; `${stdr_experiments:dnerf,stdr}`
    (or `plain`) only those."""
    names = [e for b in sorted(BASELINES) for e in (f"{data}_{b}", f"{data}_{b}_stdr")]
    if "stdr" in which:
        names = [n for n in names if n.endswith("_stdr")]
    elif "plain" in which:
        names = [n for n in names if not n.endswith("_stdr")]
    return ",".join(names)


def _scene_path_resolver(root, name) -> str:
    """`${stdr_scene_path:${data.root},${data.name}}` (the sweeps): root/name, or an error that
    names the missing key (a null root must not become a path 'None/<scene>')."""
    if root is None or root == "":
        raise ValueError("data.root is not set: a sweep over scenes needs the dataset folder, e.g. "
                         "data.root=/data/dnerf")
    if name is None or name == "":
        raise ValueError("data.name is not set: the scene folder under data.root")
    return f"{root}/{name}"


def register() -> None:
    """Register the structured configs, every baseline (and the ones registered later) and the
    `stdr_schedule` / `stdr_experiments` resolvers with Hydra. Idempotent; the entry points call it."""
    if not OmegaConf.has_resolver("stdr_schedule"):
        OmegaConf.register_new_resolver("stdr_schedule", _schedule_resolver)
    if not OmegaConf.has_resolver("stdr_experiments"):
        OmegaConf.register_new_resolver("stdr_experiments", _experiments_resolver)
    if not OmegaConf.has_resolver("stdr_scene_path"):
        OmegaConf.register_new_resolver("stdr_scene_path", _scene_path_resolver)
    discover_baselines()  # baselines of other installed distributions (entry points)
    cs = ConfigStore.instance()
    cs.store(name="base_config", node=Config)
    cs.store(name="base_eval", node=EvalAppConfig)
    for spec in BASELINES.values():
        _sync_baseline(spec, True)
    add_listener(_sync_baseline)


# keys of other baselines that configs written before per-baseline config classes carried under
# `baseline` (every run had baseline.scgs, .spgs and .hexplane); dropped when such a config is read
_LEGACY_BASELINE_KEYS = ("scgs", "spgs", "hexplane")
# STDR keys of earlier code that no longer exist; configs that carry them still load
_REMOVED_STDR_KEYS = ("static_skip",)


def load_config(raw: Any, where: str = "config"):
    """A saved config (a run's config.yaml, a checkpoint's config: a dict, DictConfig or path)
    merged onto the typed defaults of its baseline. Unknown keys are an error naming `where`."""
    if isinstance(raw, (str, Path)):
        where = str(raw)
        raw = OmegaConf.load(raw)
    raw = OmegaConf.to_container(raw) if OmegaConf.is_config(raw) else dict(raw)
    b = dict(raw.get("baseline") or {})
    name = b.get("name", "deform")
    try:
        spec = get_baseline(name)
    except ValueError as e:
        raise ValueError(f"{where}: {e}") from None
    fields = set(spec.config.__dataclass_fields__)
    for k in _LEGACY_BASELINE_KEYS:
        if k in b and k not in fields:
            del b[k]
    raw["baseline"] = b
    if isinstance(raw.get("stdr"), dict):  # a render-time key removed on 2026-11-26 (docs/stdr.md)
        raw["stdr"] = {k: v for k, v in raw["stdr"].items() if k not in _REMOVED_STDR_KEYS}
    schema = OmegaConf.merge(OmegaConf.structured(Config), {"baseline": OmegaConf.structured(spec.config)})
    try:
        return OmegaConf.merge(schema, raw)
    except Exception as e:  # omegaconf's errors name the key; say which file
        raise ValueError(f"{where}: {e}") from None
