"""The one phase schedule (stdr.schedule): resolved from the config, read by every component."""
import subprocess
import sys

import pytest
from omegaconf import OmegaConf

from stdr.testing import make_cfg
from stdr.testing import tiny_config as _tiny

from stdr.baselines import BASELINES
from stdr.store import resolve_schedule


@pytest.mark.parametrize("name", sorted(BASELINES))
def test_schedule_of_each_baseline_with_and_without_stdr(name):
    plain = resolve_schedule(make_cfg([f"experiment=dnerf_{name}", "data.path=/x"]))
    s = resolve_schedule(make_cfg([f"experiment=dnerf_{name}_stdr", "data.path=/x"]))
    assert plain.static_warmup_end == s.static_warmup_end == 500 and plain.plugins == {}
    steps = [e.step for e in s.sorted_events()]
    assert steps == sorted(steps) and steps[0] == 0
    keys = {e.key for e in s.events}
    assert {"baseline.warmup", "stdr.warmup_end", "densify.refine_start"} <= keys
    assert s.plugins["stdr"]["warmup_end"] == 500
    # the freeze (2 x 500 = 1000) moves by rule only out of a baseline's switch window: SC-GS's
    # node->skinning switch spans [1000, 1100] at budget=cpu, so its freeze lands halfway
    # between the warm-up's end and the window, at 750; the others keep 1000
    expected = {"deform": 1000, "scgs": 750, "spgs": 1000, "4dgs": 1000}
    if name not in expected:
        pytest.skip(f"{name}: a baseline registered outside stdr; its freeze is not pinned here")
    assert s.plugins["stdr"]["freeze_at"] == expected[name]
    assert ("moved" in s.describe()) == (name == "scgs")
    if name == "scgs":
        assert "baseline.scgs.node_stage_end" in keys and s.windows == [(s.windows[0][0], 1000, 1100)]
    # an explicit freeze away from any window is kept as given
    assert resolve_schedule(make_cfg([f"experiment=dnerf_{name}_stdr", "data.path=/x",
                                      "stdr.freeze_at=1300"])).plugins["stdr"]["freeze_at"] == 1300


def test_a_component_that_would_never_train_is_a_named_error_other_late_boundaries_are_marked():
    from stdr.schedule import NeverTrains
    base = ["experiment=dnerf_deform_stdr", "data.path=/x", "budget=cpu"]  # warm-up 500, STDR freeze 1000
    with pytest.raises(NeverTrains, match=r"STDR's freeze resolves to step 1000.*optim.iterations=800.*stdr.freeze_at"
                                          r".*train.stop_at"):
        resolve_schedule(make_cfg(base + ["optim.iterations=800"]))
    with pytest.raises(NeverTrains, match=r"baseline.warmup=900 is at or after the run's end \(optim.iterations=800\)"):
        resolve_schedule(make_cfg(["experiment=dnerf_deform", "data.path=/x", "budget=cpu", "optim.iterations=800",
                                   "baseline.warmup=900"]))
    s = resolve_schedule(make_cfg(base + ["densify.refine_stop=5000"]))  # densify until the end: allowed
    line = [ln for ln in s.describe().splitlines() if "[densify.refine_stop]" in ln][0]
    assert line.endswith("(never reached)") and "5000" in line


def test_components_read_their_boundaries_from_the_schedule(tmp_path):
    from stdr.train.trainer import Trainer
    t = Trainer(_tiny(tmp_path, ["experiment=embedded_scgs_stdr", "baseline.warmup=30",
                                 "baseline.scgs.node_stage_end=60", "baseline.scgs.main_warmup=10",
                                 "baseline.scgs.num_nodes=64", "optim.iterations=100"]), tmp_path / "run")
    s, m = t.state.model.schedule, t.state.model
    assert m.warmup == s.static_warmup_end == 30 == m.deform.start_step
    st = m.plugin("stdr")
    ph = s.plugins["stdr"]
    assert (st.warmup_end, st.freeze_at) == (ph["warmup_end"], ph["freeze_at"]) == (30, 45)  # moved off [60, 70]
    assert st.stats(m.params)["freeze_moved"] == ph["freeze_moved"] == "60 -> 45: " + s.windows[0][0] + " at [60, 70]"
    # the config's derived node holds the same numbers (and config.yaml keeps them)
    node = OmegaConf.to_container(t.cfg, resolve=True)["schedule"]
    assert (node["static_warmup_end"], node["stdr_warmup_end"], node["stdr_freeze_at"]) == (30, 30, 45)


def test_stdr_train_cfg_job_prints_the_resolved_schedule():
    out = subprocess.run([sys.executable, "-c", "from stdr.cli.train import main; main()",
                          "experiment=dnerf_scgs_stdr", "data.path=/x", "--cfg", "job"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "schedule:" in out.stdout and "stdr_freeze_at: 750" in out.stdout
    assert "${stdr_schedule" not in out.stdout
