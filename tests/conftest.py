import os
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
sys.path.insert(0, str(ROOT))
torch.set_num_threads(max(1, min(2, os.cpu_count() or 1)))


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
