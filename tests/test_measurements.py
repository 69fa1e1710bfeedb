"""studies/records.py (run as studies/records.py): a study's per-run records in one archive, read through records_dir."""
import io
import subprocess
import tarfile
from pathlib import Path

import pytest
from helpers import load_script

ROOT = Path(__file__).resolve().parents[1]


def _module(monkeypatch, tmp_path):
    from studies import records as mod
    monkeypatch.setattr(mod, "M", tmp_path / "m")
    monkeypatch.setenv("STDR_MEASUREMENTS_CACHE", str(tmp_path / "cache"))
    return mod


def test_pack_keeps_what_a_reader_opens_and_records_dir_reads_the_rest(tmp_path, monkeypatch):
    mm = _module(monkeypatch, tmp_path)
    st = tmp_path / "m" / "study"
    for rel, text in {"README.md": "r", "table.json": "{}", "charts/a.png": "png", "charts/a.svg": "svg",
                      "runs/x/s0/metrics.json": '{"psnr": 1}', "runs/y/s1/metrics.json": '{"psnr": 2}',
                      "big.json": "x" * 200_000}.items():
        (st / rel).parent.mkdir(parents=True, exist_ok=True)
        (st / rel).write_text(text)
    assert mm.pack(st) == 4  # two run records, the SVG and the bulk table
    assert sorted(p.relative_to(st).as_posix() for p in st.rglob("*") if p.is_file()) == \
        ["README.md", "charts/a.png", "records.tar.xz", "table.json"]
    runs = mm.records_dir("study", "runs")
    assert runs.is_dir() and (runs / "y" / "s1" / "metrics.json").read_text() == '{"psnr": 2}'
    assert mm.record_file("study", "big.json").read_text() == "x" * 200_000
    assert mm.records_dir("study", "runs") == runs  # unpacked once per archive content
    # a study continued: extract, add a record, pack again (merged)
    mm.extract_to(st / mm.ARCHIVE, st)
    (st / "runs" / "z" / "s0").mkdir(parents=True)
    (st / "runs" / "z" / "s0" / "metrics.json").write_text('{"psnr": 3}')
    assert mm.pack(st) == 5 and not (st / "runs").exists()
    assert sorted(p.name for p in mm.records_dir("study", "runs").iterdir()) == ["x", "y", "z"]


def test_an_archive_member_that_leaves_the_destination_is_refused(tmp_path, monkeypatch):
    mm = _module(monkeypatch, tmp_path)
    bad = tmp_path / "bad.tar.xz"
    with tarfile.open(bad, "w:xz") as tar:
        info = tarfile.TarInfo("../escape.txt")
        info.size = 1
        tar.addfile(info, io.BytesIO(b"x"))
    with pytest.raises(SystemExit, match="refused"):
        mm.extract_to(bad, tmp_path / "dest")
    assert not (tmp_path / "escape.txt").exists()


def test_the_repository_is_code_with_its_records_archived():
    """At most 600 tracked files and 6 MB of them; every study's records in its archive."""
    files = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, text=True).stdout.split("\0")
    files = [f for f in files if f and (ROOT / f).is_file()]
    if not files:
        pytest.skip("not a git checkout")
    assert len(files) <= 600, len(files)
    assert sum((ROOT / f).stat().st_size for f in files) <= 6 * 2 ** 20
    assert not [f for f in files if f.startswith("research/measurements/") and f.endswith(".svg")]


def test_a_study_refuses_to_write_records_beside_its_packed_archive(tmp_path):
    """studies.common.records_to_write: a new records folder would hide the archived ones from the
    tables, so it is refused with the commands that fix it; an extracted folder is written to."""
    import sys
    sys.path.insert(0, str(ROOT))
    from studies.common import records_in, records_to_write
    study = tmp_path / "study"
    study.mkdir()
    (study / "records.tar.xz").write_bytes(b"")
    with pytest.raises(SystemExit, match="extract study"):
        records_to_write(study, "records")
    assert not (study / "records").exists()
    (study / "records").mkdir()
    assert records_to_write(study, "records") == study / "records" == records_in(study, "records")


def test_a_records_stamp_ignores_the_tables_a_study_rewrites_but_not_code(tmp_path, monkeypatch):
    """studies.common.commit: `+dirty` for a changed tracked file outside research/measurements, none for
    a study's own generated table there (a `val` pass rewrites it while the records are written)."""
    import studies.common as common

    def git(*a):
        subprocess.run(["git", "-C", str(tmp_path), *a], check=True, capture_output=True)
    (tmp_path / "research" / "measurements" / "s").mkdir(parents=True)
    (tmp_path / "research" / "measurements" / "s" / "table.md").write_text("a\n")
    (tmp_path / "code.py").write_text("x = 1\n")
    git("init", "-q")
    git("add", ".")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "init")
    monkeypatch.setattr(common, "ROOT", tmp_path)
    head = common.commit()
    assert head and "+" not in head
    (tmp_path / "research" / "measurements" / "s" / "table.md").write_text("b\n")
    (tmp_path / "new_untracked.py").write_text("")
    assert common.commit() == head
    (tmp_path / "code.py").write_text("x = 2\n")
    assert common.commit() == head + "+dirty"


def test_the_size_prune_rule_takes_the_best_quiet_candidate_and_refuses_partial_records():
    """studies/size_prune.py decide(): protocol.md's rule on hand-made records."""
    sp = load_script(ROOT / "studies" / "size_prune.py", "size_prune")

    def rec(c, s, psnr, warn=False):
        return {"candidate": c, "scene": s, "curve": [{"iteration": sp.VAL_STOP, "psnr": psnr}],
                "warnings": [{"step": 1600, "removes": 9, "of": 10}] if warn else []}
    scenes = sp.SCENES
    loud_best = [rec("s20_1500", s, 30.0, warn=True) for s in scenes] + [rec("s20_3000", s, 29.95) for s in scenes]
    d = sp.decide(loud_best + [rec("ws_1500", s, 29.97) for s in scenes])
    assert d["choice"] == "ws_1500" and not d["quiet"]["s20_1500"]  # within 0.05 of s20_3000: the reference's
    d = sp.decide(loud_best + [rec("ws_1500", s, 29.0) for s in scenes])
    assert d["choice"] == "s20_3000"
    d = sp.decide([rec("s20_1500", s, 30.0) for s in scenes] + [rec("s20_3000", s, 29.0, warn=True) for s in scenes]
                  + [rec("ws_1500", s, 29.5) for s in scenes])
    assert d["choice"] == "s20_1500"  # quiet and best
    d = sp.decide([rec("s20_1500", s, 30.0, warn=True) for s in scenes] + [rec("s20_3000", s, 29.0, warn=True)
                  for s in scenes] + [rec("ws_1500", s, 29.5) for s in scenes])
    assert d["choice"] == "s20_1500" and "preset stays" in d["why"]  # the quiet one loses 0.5 dB
    assert sp.decide(loud_best)["choice"] is None  # a candidate without its scenes decides nothing
