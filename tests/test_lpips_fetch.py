"""LPIPS on the first run: the official weights fetched once into the user cache, each checked
against its pinned SHA-256, from a local HTTP server standing in for the official locations
(success, a corrupted file, no network); offline, the run still ends with LPIPS null."""
import hashlib
import io
import json
import subprocess
import sys

import pytest
import torch

from stdr.data.fetch import DataError
from stdr.eval import lpips as lp
from stdr.eval.evaluate import make_lpips

from test_data_fetch import Server


def _alex_files() -> dict[str, bytes]:
    """Files named and shaped as the official AlexNet trunk and LPIPS-alex heads (random values)."""
    g = torch.Generator().manual_seed(0)
    trunk = {f"features.{k}": torch.randn(*v.shape, generator=g) * 0.05
             for k, v in lp._alexnet_features().state_dict().items()}
    trunk["classifier.1.weight"] = torch.zeros(3, 3)  # the full torchvision model has a classifier too
    lin = {f"lin{i}.model.1.weight": torch.rand(1, c, 1, 1, generator=g) for i, c in enumerate(lp._ALEX_CH)}
    out = {}
    for name, sd in (("alexnet-owt-7be5be79.pth", trunk), ("alex.pth", lin)):
        buf = io.BytesIO()
        torch.save(sd, buf)
        out[name] = buf.getvalue()
    return out


@pytest.fixture
def offline_cache(tmp_path, monkeypatch):
    """No weights anywhere the evaluation looks: an empty user cache, no STDR_LPIPS_WEIGHTS."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.delenv("STDR_LPIPS_WEIGHTS", raising=False)
    monkeypatch.setenv("STDR_DATA_QUIET", "1")
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path / "hub"))
    monkeypatch.setattr(lp.importlib.util, "find_spec", lambda name: None)  # no `lpips` package either
    return tmp_path / "cache" / "stdr" / "lpips"


@pytest.fixture
def served(monkeypatch):
    """The official sources of LPIPS-alex served locally, with their real content's hashes pinned."""
    s = Server()
    files = _alex_files()
    sources = dict(lp.WEIGHT_SOURCES)
    for name, data in files.items():
        s.files[f"/{name}"] = data
        sources[name] = (f"{s.url}/{name}", hashlib.sha256(data).hexdigest(), "1 KB")
    monkeypatch.setattr(lp, "WEIGHT_SOURCES", sources)
    yield s, files
    s.httpd.shutdown()


def _cfg(**kw):
    from stdr.config import EvalConfig
    return EvalConfig(**{"lpips": "auto", "lpips_net": "alex", **kw})


def test_the_first_evaluation_fetches_checks_and_uses_the_weights(offline_cache, served, capsys):
    server, files = served
    fn = make_lpips(_cfg())
    assert fn is not None and fn.net == "alex"
    assert "downloading alexnet-owt-7be5be79.pth" in capsys.readouterr().out  # the one-line message
    assert {p.name for p in offline_cache.iterdir()} == set(files)
    assert all((offline_cache / n).read_bytes() == b for n, b in files.items())
    assert fn.weight_files == (str(offline_cache / "alexnet-owt-7be5be79.pth"), str(offline_cache / "alex.pth"))
    x = torch.rand(32, 32, 3, generator=torch.Generator().manual_seed(1))
    assert float(fn(x, x)) == 0.0 and float(fn(x, 1 - x)) > 0
    # a second run finds them: nothing is downloaded again
    n = len(server.ranges)
    assert make_lpips(_cfg()) is not None and len(server.ranges) == n


def test_a_corrupted_download_is_refused_and_nothing_is_kept(offline_cache, served, capsys):
    server, files = served
    server.files["/alex.pth"] = files["alex.pth"][:-10] + b"0123456789"  # same length, other bytes
    with pytest.raises(DataError, match=r"alex\.pth from http://127\.0\.0\.1:\d+/alex\.pth: SHA-256 [0-9a-f]{64} is "
                                        r"not the pinned [0-9a-f]{64}"):
        lp.fetch_weights("alex", log=lambda m: None)
    assert not (offline_cache / "alex.pth").exists()
    assert not [p for p in offline_cache.iterdir() if p.name.startswith(".alex.pth")]  # no partial file either
    # eval.lpips=auto: the run goes on without LPIPS and says why; eval.lpips=true: an error that says why
    assert make_lpips(_cfg()) is None
    out = capsys.readouterr().out
    assert "LPIPS skipped (reported as null)" in out and "not the pinned" in out
    with pytest.raises(FileNotFoundError, match="not the pinned"):
        make_lpips(_cfg(lpips="true"))


def test_offline_the_run_still_ends_with_the_clear_warning(offline_cache, monkeypatch, capsys):
    port = Server()
    url = port.url
    port.httpd.shutdown()
    port.httpd.server_close()  # nothing listens there any more: a refused connection, as offline
    sources = {n: (f"{url}/{n}", h, s) for n, (_, h, s) in lp.WEIGHT_SOURCES.items()}
    monkeypatch.setattr(lp, "WEIGHT_SOURCES", sources)
    assert make_lpips(_cfg(lpips_net="vgg")) is None
    out = capsys.readouterr().out
    assert "LPIPS skipped (reported as null). LPIPS-vgg weights not found" in out
    assert "The download failed" in out and "stdr-data download lpips" in out
    assert not offline_cache.exists() or not any(offline_cache.iterdir())


def test_no_download_where_the_user_named_a_folder_or_turned_it_off(offline_cache, served, tmp_path):
    server, _ = served
    assert make_lpips(_cfg(lpips_weights=str(tmp_path / "mine"))) is None  # a folder of one's own: not filled
    assert make_lpips(_cfg(lpips_download=False)) is None
    assert server.ranges == [] and not offline_cache.exists()


def test_stdr_data_download_lpips_fetches_ahead_of_time(tmp_path, served):
    server, files = served
    code = ("import sys, json; from stdr.eval import lpips as lp; "
            "lp.WEIGHT_SOURCES.update({k: tuple(v) for k, v in json.loads(sys.argv[1]).items()}); "
            "from stdr.cli.data import main; main(['download', 'lpips', '--net', 'alex', '--dest', sys.argv[2]])")
    proc = subprocess.run([sys.executable, "-c", code, json.dumps(lp.WEIGHT_SOURCES), str(tmp_path / "w")],
                          capture_output=True, text=True, timeout=120, env={**__import__("os").environ, "STDR_DATA_QUIET": "1"})
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "LPIPS-alex: weights in" in proc.stdout and "eval.lpips_weights=" in proc.stdout
    assert {p.name for p in (tmp_path / "w").iterdir()} == set(files)
    assert lp.LPIPS("alex", tmp_path / "w").net == "alex"


def test_the_pinned_trunks_agree_with_torchvision_file_names():
    """torchvision names each weight file with the first 8 hex digits of its SHA-256 (its own
    check on load): the pinned full hashes must begin with them, and every net's files are pinned."""
    for name in ("vgg16-397923af.pth", "alexnet-owt-7be5be79.pth"):
        url, sha, _ = lp.WEIGHT_SOURCES[name]
        assert sha.startswith(name.rsplit("-", 1)[1][:8]) and url.endswith("/" + name) and len(sha) == 64
    for net, names in lp.FETCHED.items():
        assert set(names) <= set(lp.WEIGHT_SOURCES)
        assert names[0] in lp.TRUNK_FILES[net] and names[1] in lp.LIN_FILES[net]  # the loader finds what is fetched
