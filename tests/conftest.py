import os
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


def pytest_collection_modifyitems(config, items):
    """The markers `needs_shared` (a test that uses the shared_dir fixture, directly or through
    another fixture) and `cuda` (a test whose name or parameters name CUDA), so that
    `-m "not needs_shared"` or `-m cuda` select by what a test needs."""
    for item in items:
        if "shared_dir" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.needs_shared)
        if "cuda" in item.nodeid.split("::", 1)[-1].lower():
            item.add_marker(pytest.mark.cuda)
