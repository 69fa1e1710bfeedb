import json
import os
import platform
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
sys.path.insert(0, str(ROOT))
# Threads per test process: 2 at most, and the cores shared among pytest-xdist's workers (the README's
# test command runs two), so that two workers on two cores do not each start two threads. Exported
# for the stdr-train / gpu_check subprocesses some tests start (torch reads OMP_NUM_THREADS).
_WORKERS = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
THREADS = max(1, min(2, (os.cpu_count() or 1) // _WORKERS))
if _WORKERS > 1:
    os.environ.setdefault("OMP_NUM_THREADS", str(THREADS))
torch.set_num_threads(THREADS)


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    if not SHARED.is_dir():
        pytest.skip(f"shared data not found at {SHARED} (only present on the project's machines)")
    return SHARED


#: the tests a recorded run of the suite measured over its threshold (`--update-durations`)
DURATIONS = ROOT / "tests" / "durations.json"
#: a test over this many seconds (setup, call and teardown, on the recording machine) is `slow`
SLOW_OVER_S = 1.5


def measured_slow() -> dict[str, float]:
    return json.loads(DURATIONS.read_text())["tests"] if DURATIONS.is_file() else {}


def pytest_addoption(parser):
    parser.addoption("--update-durations", action="store_true",
                     help=f"record the tests of this run that take over {SLOW_OVER_S} s in tests/durations.json "
                          "(they are then `slow`: out of the fast tier); run it on an idle machine")


def pytest_collection_modifyitems(config, items):
    """The markers `needs_shared` (a test that uses the shared_dir fixture, directly or through
    another fixture) and `cuda` (a test whose name or parameters name CUDA), so that
    `-m "not needs_shared"` or `-m cuda` select by what a test needs; and `slow` for the tests
    tests/durations.json measured over SLOW_OVER_S, beside the ones marked slow by hand."""
    slow = measured_slow()
    for item in items:
        if "shared_dir" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.needs_shared)
        if "cuda" in item.nodeid.split("::", 1)[-1].lower():
            item.add_marker(pytest.mark.cuda)
        if item.nodeid in slow:
            item.add_marker(pytest.mark.slow)


_SECONDS: dict[str, float] = {}


def _machine() -> str:
    cpu = next((ln.split(":", 1)[1].strip() for ln in Path("/proc/cpuinfo").read_text().splitlines()
                if ln.startswith("model name")), platform.processor()) if Path("/proc/cpuinfo").is_file() else ""
    return f"{cpu or platform.machine()}, {os.cpu_count()} cores"


def pytest_runtest_logreport(report):
    """Each test's seconds, setup and teardown included (a module fixture counts to the test that
    builds it); on the controlling process, from every worker."""
    _SECONDS[report.nodeid] = _SECONDS.get(report.nodeid, 0.0) + report.duration


def pytest_sessionfinish(session, exitstatus):
    """--update-durations: the tests of this run over SLOW_OVER_S replace their earlier entries
    (a test that ran under it leaves the file; tests this run did not select keep theirs)."""
    config = session.config
    if not config.getoption("--update-durations") or hasattr(config, "workerinput"):
        return
    kept = {k: v for k, v in measured_slow().items() if k not in _SECONDS}
    kept.update({k: round(v, 2) for k, v in _SECONDS.items() if v > SLOW_OVER_S})
    record = {"over_s": SLOW_OVER_S, "machine": _machine(), "workers": getattr(config.option, "numprocesses", None),
              "tests": dict(sorted(kept.items()))}
    DURATIONS.write_text(json.dumps(record, indent=1) + "\n")
