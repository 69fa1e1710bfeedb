"""studies/ops_per_step.py's comparison of operator counts (the counts themselves are measured;
this pins how they are put side by side)."""
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from studies.ops_per_step import compare, main  # noqa: E402


def _res(label, rows):
    return {"label": label, "code": {"commit": label * 5, "dirty": False}, "scene": "/x/jumpingjacks",
            "rows": [{"experiment": e, "ops": o, "compute_ops": c} for e, o, c in rows]}


def test_each_later_count_is_set_against_the_first():
    a = _res("before", [("dnerf_deform", 500, 300), ("dnerf_4dgs", 1900, 1400)])
    b = _res("after", [("dnerf_deform", 450, 285), ("dnerf_4dgs", 700, 480)])
    c = _res("fused", [("dnerf_deform", 350, 147)])  # 4dgs not counted: its row is left out
    text = compare(a, b, c)
    lines = [ln for ln in text.splitlines() if ln.startswith("| dnerf")]
    assert lines == ["| dnerf_deform | 500 | 450 (0.90) | 350 (0.70) | 300 | 285 (0.95) | 147 (0.49) |"]
    assert "Ratios are to before" in text
    assert "| dnerf_4dgs | 1900 | 700 (0.37) | 1400 | 480 (0.34) |" in compare(a, b)


def test_compare_needs_two_counts(tmp_path, capsys):
    p = tmp_path / "a.json"
    p.write_text("{}")
    with pytest.raises(SystemExit):
        main(["--compare", str(p)])
    assert "at least two" in capsys.readouterr().err
