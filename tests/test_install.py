"""stdr as an installed library: the wheel round trip (scripts/wheel_check.sh: configs and kernel
sources inside the package, stdr-train and stdr-eval from a fresh venv outside the checkout), and
no lookup relative to the source tree."""
import subprocess
from pathlib import Path

import pytest

import stdr
from stdr.data.load import cache_base
from stdr.eval.lpips import default_search_dirs

ROOT = Path(__file__).resolve().parents[1]


def test_lpips_weights_are_never_looked_up_relative_to_the_source(monkeypatch, tmp_path):
    monkeypatch.delenv("STDR_LPIPS_WEIGHTS", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    dirs = default_search_dirs()
    assert tmp_path / "xdg" / "stdr" / "lpips" in dirs
    assert not [d for d in dirs if d.resolve().is_relative_to(ROOT.parent)], dirs
    monkeypatch.setenv("STDR_LPIPS_WEIGHTS", str(tmp_path / "w"))
    assert default_search_dirs()[0] == tmp_path / "w"


def test_caches_never_live_in_the_source_even_when_running_from_it(tmp_path, monkeypatch):
    """An editable install or a checkout keeps its caches where an installed copy does: the user
    cache, never the source (a researcher's outside package must not fill stdr's checkout)."""
    assert stdr.source_checkout() == ROOT
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_base() == tmp_path / "xdg" / "stdr"
    monkeypatch.delenv("XDG_CACHE_HOME")
    assert cache_base() == Path.home() / ".cache" / "stdr" and not cache_base().is_relative_to(ROOT)


@pytest.mark.slow
def test_wheel_installs_and_runs_outside_the_checkout(tmp_path):
    # the checkout's package folder, which no other test writes (data/ is not compared: tests on the
    # other pytest-xdist worker fill its caches meanwhile; the installed copy's caches are checked by
    # wheel_check.sh, which finds them under XDG_CACHE_HOME and site-packages unchanged)
    status = ["git", "status", "--porcelain", "--ignored", "--untracked-files=all", "--", "stdr"]

    def listing():  # (bytecode caches aside: any test process importing stdr may write them)
        out = subprocess.run(status, cwd=ROOT, capture_output=True, text=True, check=True).stdout
        return [ln for ln in out.splitlines() if "__pycache__" not in ln]

    before = listing()
    p = subprocess.run(["bash", str(ROOT / "scripts" / "wheel_check.sh"), str(tmp_path / "w")],
                       capture_output=True, text=True, timeout=1200)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    assert "[wheel] ok" in p.stdout and "deform+STDR" in p.stdout
    assert "configs in " + str(tmp_path / "w" / "venv") in p.stdout
    assert "site-packages unchanged" in p.stdout
    after = listing()
    assert after == before  # nothing written into the checkout's package folder
