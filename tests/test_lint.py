"""Habits: ruff's small rule set (pyproject.toml, [tool.ruff.lint]) is clean, and the markers
`cuda` and `needs_shared` select what they say."""
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_ruff_is_clean():
    p = subprocess.run([sys.executable, "-m", "ruff", "check", "stdr", "tests", "scripts", "studies"], cwd=ROOT,
                       capture_output=True, text=True)
    assert "No module named ruff" not in p.stderr, "ruff is part of the test extra: pip install -e '.[test]'"
    assert p.returncode == 0, p.stdout[-4000:] + p.stderr[-2000:]


def _collected(marker: str, path: str) -> list[str]:
    p = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider", "-m", marker, path],
                       cwd=ROOT, capture_output=True, text=True)
    return [ln for ln in p.stdout.splitlines() if "::" in ln]


def test_markers_select_the_tests_that_need_shared_data_or_cuda():
    shared = _collected("needs_shared", "tests/test_data.py")
    assert shared == ["tests/test_data.py::test_shared_dnerf_scenes_load"]
    toy = _collected("needs_shared", "tests/test_nerfies.py")  # through the `toy` fixture
    assert [t.split("::")[1] for t in toy] == ["test_colmap_reader_on_the_capture",
                                               "test_toy_capture_loads_and_colmap_points_project_where_observed",
                                               "test_toy_capture_undistortion_round_trips",
                                               "test_toy_capture_short_training_run"]
    cuda = _collected("cuda", "tests/test_device.py")
    assert sorted(cuda) == [f"tests/test_device.py::test_training_on_cuda_keeps_every_tensor_there_and_resumes[{b}]"
                            for b in ("4dgs", "deform", "scgs", "spgs")] + \
        [f"tests/test_device.py::test_training_with_the_speed_keys_on_cuda_through_prunes_resets_and_a_recovery[{b}]"
         for b in ("4dgs", "deform_stdr")]
