"""stdr-tool experiments: every experiment stdr-train accepts, with what it composes."""
import json

import pytest

from stdr import store as C
from stdr.testing import make_cfg
from stdr.tools import experiments as tool


def test_every_experiment_is_listed_with_what_it_composes(capsys):
    rows = C.experiment_table()
    assert [r["name"] for r in rows] == C.experiment_names()
    by = {r["name"]: r for r in rows}
    for name in ("dnerf_scgs_stdr", "nerfds_4dgs", "embedded_deform"):
        r = by[name]
        cfg = make_cfg([f"experiment={name}", "data.path=/x"])
        assert r["source"] == "derived" and r["baseline"] == cfg.baseline.name
        assert r["plugins"] == (["stdr"] if cfg.stdr.enabled else [])
        assert name.startswith(r["data"] + "_")
    tool.main(["--data", "dnerf", "--plugin", "plain", "--json"])
    got = json.loads(capsys.readouterr().out)
    assert sorted(r["name"] for r in got) == ["dnerf_4dgs", "dnerf_deform", "dnerf_scgs", "dnerf_spgs"]


def test_a_yaml_file_replaces_the_derived_experiment_of_its_name(monkeypatch, capsys):
    monkeypatch.setattr(C, "_experiment_files", lambda: {"dnerf_deform", "my_study"})
    rows = {r["name"]: r for r in C.experiment_table()}
    assert rows["dnerf_deform"]["source"] == "stdr/configs/experiment/dnerf_deform.yaml"
    assert rows["my_study"]["source"].endswith("my_study.yaml") and rows["my_study"]["baseline"] is None
    assert sum(r == "dnerf_deform" for r in rows) == 1
    tool.main(["--baseline", "deform", "--data", "dnerf"])
    out = capsys.readouterr().out
    assert "| dnerf_deform_stdr | dnerf | deform | stdr | derived |" in out and "dnerf_deform |" not in out.replace(
        "dnerf_deform_stdr", "")


@pytest.mark.parametrize("argv", [["--plugin", "stdr"]])
def test_the_filters_select(argv, capsys):
    tool.main(argv + ["--json"])
    got = json.loads(capsys.readouterr().out)
    assert got and all(r["plugins"] == ["stdr"] for r in got)


def test_a_run_is_named_after_the_baseline_and_plugins_it_trains():
    """baseline=X without experiment= is the run <data>_X (not the default experiment's name);
    stdr=on adds _stdr; an experiment as composed, or a name the user gave, stays."""
    from stdr.store import run_name
    from stdr.testing import make_cfg
    assert run_name(make_cfg([])) == "embedded_deform"
    assert run_name(make_cfg(["baseline=scgs"])) == "embedded_scgs"
    assert run_name(make_cfg(["stdr=on"])) == "embedded_deform_stdr"
    assert run_name(make_cfg(["experiment=dnerf_spgs_stdr", "data.path=/x"])) == "dnerf_spgs_stdr"
    assert run_name(make_cfg(["experiment=dnerf_spgs_stdr", "data.path=/x", "baseline=4dgs"])) == "dnerf_4dgs_stdr"
    assert run_name(make_cfg(["name=my_study", "baseline=scgs"])) == "my_study"
