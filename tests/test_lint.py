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


def _import_graph() -> dict[str, set[str]]:
    """stdr's relative imports, module -> modules (function-level imports included)."""
    import ast
    edges: dict[str, set[str]] = {}
    for f in (ROOT / "stdr").rglob("*.py"):
        parts = f.relative_to(ROOT).with_suffix("").parts
        mod = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        pkg = mod if f.name == "__init__.py" else mod.rsplit(".", 1)[0]
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level:
                base = pkg.split(".")[:len(pkg.split(".")) - node.level + 1]
                edges.setdefault(mod, set()).add(".".join(base + ([node.module] if node.module else [])))
    return edges


def test_the_config_sits_on_no_import_circle():
    """stdr.config imports the registries (plugins, baselines, densify.strategy) and the schedule; none of
    them imports it back, not even inside a function (the plug-in registry gets the reserved names
    from it: plugins.set_reserved_keys)."""
    edges = _import_graph()

    def reaches(a, b, seen):
        for n in edges.get(a, ()):
            if n == b:
                return True
            if n not in seen:
                seen.add(n)
                if reaches(n, b, seen):
                    return True
        return False
    for mod in ("stdr.plugins", "stdr.schedule", "stdr.baselines", "stdr.densify.strategy"):
        assert not reaches(mod, "stdr.config", set()), mod


def test_no_module_below_the_loop_takes_the_trainer():
    """The guard, densification, pruning and evaluation take the run's state (stdr.train.state),
    never the trainer: no function in stdr/train (but the trainer's own module), stdr/densify or
    stdr/eval has a parameter named `trainer`, and none imports stdr.train.trainer."""
    import ast
    bad = []
    for pkg in ("train", "densify", "eval"):
        for path in sorted((ROOT / "stdr" / pkg).glob("*.py")):
            if path.name == "trainer.py":
                continue
            tree = ast.parse(path.read_text())
            for node in ast.walk(tree):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    names = [a.arg for a in node.args.args + node.args.kwonlyargs + node.args.posonlyargs]
                    if "trainer" in names:
                        bad.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name}(trainer)")
                if isinstance(node, ast.ImportFrom) and (node.module or "").endswith("trainer"):
                    bad.append(f"{path.relative_to(ROOT)}:{node.lineno} imports {node.module}")
    assert not bad, bad


def test_studies_and_scripts_use_no_private_name_of_another_module():
    """Studies and scripts are written on the public API: no `from stdr... import _x`, no
    `from studies.<other> import _x`, no `module._x` of an imported stdr or studies module."""
    import ast
    bad = []
    for folder in ("studies", "scripts"):
        for path in sorted((ROOT / folder).glob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] in ("stdr", "studies"):
                    bad += [f"{path.relative_to(ROOT)}:{node.lineno} {node.module}.{a.name}"
                            for a in node.names if a.name.startswith("_") and a.name != "__version__"]
    assert bad == [], bad
