"""Every I/O fault is one line naming the path and the cause, exit != 0, the previous file intact
and no temporary file left behind.

Two kinds of test, both on real files:
* the failpoints (stdr.io.files.failpoint, STDR_FAILPOINT=<site>): each write site of the
  commands fails in turn, as a full disk would after its bytes went to the temporary file;
* real faults of a real disk: a read-only mount, a full tmpfs, a file-size limit (ulimit -f),
  a folder the user may not write, and a path through a file. The mounts need root (CI runs as
  root); elsewhere those cases skip with the reason.
"""
from __future__ import annotations

import errno
import hashlib
import json
import os
import resource
import shutil
import subprocess
import sys
import uuid
from pathlib import Path

import pytest

from stdr.io.files import SITES
from stdr.testing import TINY_SCENE

TINY = [*TINY_SCENE, "device=cpu", "model.init_num=300", "eval.lpips=false", "train.progress=false",
        "train.image_every=0", "eval.fps_repeats=1", "eval.fps_warmup=0", "baseline.warmup=10",
        "train.eval_at_warmup_end=false", "densify.refine_start=5", "densify.refine_every=10", "train.threads=1",
        "optim.iterations=20", "train.log_every=5"]

#: the files of a run folder each write site replaces
SITE_FILE = {"config": "config.yaml", "checkpoint": "checkpoints/last.pt", "ply": "point_cloud.ply",
             "profile": "train_profile.json", "metrics": "metrics.json", "history": "history.json",
             "renders": "renders/test/000.png", "lock": ".stdr.lock", "tensorboard": "tb",
             "compact": "model.stdrc", "pack": "pack.json"}


def train_cmd(base: Path, run: Path) -> list[str]:
    return [sys.executable, "-m", "stdr.cli.train", *TINY, f"data.cache_dir={base / 'cache'}", f"hydra.run.dir={run}"]


def sh(cmd, env=None, timeout=600, **kw) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env={**os.environ, **(env or {})}, **kw)


def digest(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def leftovers(folder: Path) -> list[str]:
    """Temporary or partial files: what a write cut short must never leave."""
    return [str(p) for p in folder.rglob("*") if ".tmp" in p.name or p.name.endswith((".partial", ".link"))]


def error_line(r: subprocess.CompletedProcess, prog: str) -> str:
    assert r.returncode != 0, r.stdout[-2000:]
    assert "Traceback" not in r.stderr, r.stderr[-4000:]
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith(f"{prog}: error:")]
    assert len(lines) == 1, r.stderr[-4000:]
    return lines[0]


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> Path:
    """A finished 20-step run with its renders, its compact file and a table of it."""
    base = tmp_path_factory.mktemp("faults")
    run = base / "run"
    r = sh(train_cmd(base, run))
    assert r.returncode == 0, r.stderr[-3000:]
    r = sh([sys.executable, "-m", "stdr.cli.tool", "pack", str(run), "--no-eval"])
    assert r.returncode == 0, r.stderr[-3000:]
    return run


def _copy(run: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "run"
    shutil.copytree(run, dst)
    return dst


# ---------------------------------------------------------------- each write site in turn
TRAIN_SITES = ("config", "lock", "checkpoint", "ply", "tensorboard", "profile", "renders", "metrics", "history")


@pytest.mark.parametrize("site", TRAIN_SITES)
def test_a_fault_at_each_write_site_of_stdr_train_is_one_line_and_damages_nothing(finished, tmp_path, site):
    """The same command again over the finished run (it re-saves and re-evaluates): the site fails
    as a full disk would; its file is the previous one, every other file is whole, nothing .tmp."""
    run = _copy(finished, tmp_path)
    before = digest(run)
    r = sh(train_cmd(finished.parent, run), env={"STDR_FAILPOINT": site})
    line = error_line(r, "stdr-train")
    target = run / SITE_FILE[site]
    assert f"cannot write {target}" in line and "No space left on device" in line and "the disk is full" in line
    assert leftovers(run) == []
    after = digest(run)
    assert set(before) <= set(after), set(before) - set(after)  # no file lost
    if target.is_file():
        assert after[SITE_FILE[site]] == before[SITE_FILE[site]], "the previous file was changed"
    assert json.loads((run / "metrics.json").read_text())["test"]["iterations"] == 20  # whole and readable
    from stdr.io.checkpoint import load_checkpoint
    assert load_checkpoint(run / "checkpoints" / "last.pt")["model"]["step"] == 20


@pytest.mark.parametrize("site", ["compact", "pack"])
def test_a_fault_while_packing_leaves_the_previous_compact_file(finished, tmp_path, site):
    run = _copy(finished, tmp_path)
    before = digest(run)
    r = sh([sys.executable, "-m", "stdr.cli.tool", "pack", str(run), "--no-eval"], env={"STDR_FAILPOINT": site})
    assert f"cannot write {run / SITE_FILE[site]}: No space left on device" in error_line(r, "stdr-tool")
    assert leftovers(run) == [] and digest(run)[SITE_FILE[site]] == before[SITE_FILE[site]]


def test_a_fault_while_writing_a_table_leaves_the_previous_one(finished, tmp_path):
    out = tmp_path / "t"
    ok = sh([sys.executable, "-m", "stdr.cli.eval", str(finished), "reevaluate=false", f"out={out}"])
    assert ok.returncode == 0, ok.stderr[-2000:]
    before = digest(out)
    r = sh([sys.executable, "-m", "stdr.cli.eval", str(finished), "reevaluate=false", f"out={out}"],
           env={"STDR_FAILPOINT": "table:EDQUOT"})
    line = error_line(r, "stdr-eval")
    assert f"cannot write {out / 'table.md'}: Disk quota exceeded" in line
    assert digest(out) == before and leftovers(out) == []


def test_a_fault_while_writing_a_chart_leaves_the_previous_one(finished, tmp_path):
    out = tmp_path / "c"
    ok = sh([sys.executable, "-m", "stdr.cli.chart", str(finished), "--out", str(out)])
    assert ok.returncode == 0, ok.stderr[-2000:]
    before = digest(out)
    assert any(k.endswith(".png") for k in before) and any(k.endswith(".csv") for k in before)
    r = sh([sys.executable, "-m", "stdr.cli.chart", str(finished), "--out", str(out)], env={"STDR_FAILPOINT": "chart:ENOSPC"})
    line = error_line(r, "stdr-chart")
    assert f"cannot write {out}/" in line and ".png: No space left on device" in line
    assert digest(out) == before and leftovers(out) == []


def test_a_fault_while_writing_a_camera_path_leaves_the_previous_one(tmp_path, monkeypatch):
    import torch

    from stdr.cameras import Camera
    from stdr.errors import IOFault
    from stdr.view.camera_path import write_camera_path
    cam = Camera(R=torch.eye(3), t=torch.tensor([0.0, 0.0, 4.0]), fx=50.0, fy=50.0, cx=32.0, cy=32.0, width=64, height=64)
    path = write_camera_path(tmp_path / "path.json", [cam, cam], [0.0, 1.0])
    before = path.read_bytes()
    monkeypatch.setenv("STDR_FAILPOINT", "camera_path:ENOSPC")
    with pytest.raises(IOFault, match=f"cannot write {path}: No space left on device"):
        write_camera_path(path, [cam], [0.5])
    assert path.read_bytes() == before and leftovers(tmp_path) == []


def test_a_fault_while_writing_a_video_leaves_the_previous_one(finished, tmp_path):
    cmd = [sys.executable, "-c", "from stdr.cli.view import render_main; import sys; render_main(sys.argv[1:])",
           str(finished), "--out", str(tmp_path / "v"), "--kinds", "time", "--frames", "2", "--width", "32",
           "--format", "gif"]
    ok = sh(cmd)
    assert ok.returncode == 0, ok.stderr[-2000:]
    before = digest(tmp_path / "v")
    assert before
    r = sh(cmd, env={"STDR_FAILPOINT": "video:EFBIG"})
    line = error_line(r, "stdr-render")
    assert f"cannot write {tmp_path / 'v'}/" in line and "File too large" in line and "ulimit -f" in line
    assert digest(tmp_path / "v") == before and leftovers(tmp_path / "v") == []


@pytest.mark.parametrize("fmt", ["mp4", "gif"])
def test_a_video_cut_short_by_a_file_size_limit_is_refused_and_the_good_one_stays(finished, tmp_path, fmt):
    """ulimit -f below the new video's size (the encoder is stopped mid-file, or Python's write fails):
    one line naming the video, a non-zero exit, and the previous, good video untouched."""
    cmd = [sys.executable, "-c", "from stdr.cli.view import render_main; import sys; render_main(sys.argv[1:])",
           str(finished), "--out", str(tmp_path / "v"), "--kinds", "time", "--width", "64", "--format", fmt]
    ok = sh(cmd + ["--frames", "4"])
    assert ok.returncode == 0 and "[stdr] wrote" in ok.stdout, ok.stderr[-2000:]
    video = tmp_path / "v" / f"time_rgb.{fmt}"
    good = video.read_bytes()
    limit = max(len(good) // 2, 512)  # the new, longer video cannot fit

    def cap():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    r = subprocess.run(cmd + ["--frames", "40"], capture_output=True, text=True, timeout=600, preexec_fn=cap)
    line = error_line(r, "stdr-render")
    assert str(video) in line, line
    assert "[stdr] wrote" not in r.stdout
    assert video.read_bytes() == good and leftovers(tmp_path / "v") == []


def test_a_video_is_encoded_as_its_frames_come_and_checked_before_it_is_kept(tmp_path, capsys):
    """write_video takes any iterable: an MP4's memory does not grow with the frame count (each
    frame goes to the encoder as it comes); a file that does not read back with every frame is
    refused, naming it."""
    import tracemalloc

    import numpy as np

    from stdr.view.video import VideoError, check_video, write_video

    def frames(n):
        for i in range(n):
            yield np.full((96, 96, 3), i % 256, np.uint8)  # 27 KB each
    peaks = {}
    for n in (10, 200):
        tracemalloc.start()
        write_video(frames(n), tmp_path / f"v{n}", 10.0, "mp4", total=n, progress=False)
        peaks[n] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    assert peaks[200] < peaks[10] + 1_000_000, peaks  # a list of 200 frames alone would be 5.5 MB
    # a video whose first frame says it takes hours is announced (here 10 million frames are promised)
    write_video(frames(3), tmp_path / "long", 10.0, "mp4", total=10_000_000, progress=False)
    assert "10,000,000 frames at about" in capsys.readouterr().out
    # a GIF keeps its frames until it is written: one too large for the memory is refused at its first frame
    made = []

    def counted(n):
        for f in frames(n):
            made.append(1)
            yield f
    with pytest.raises(VideoError, match=r"long\.gif: a GIF holds every frame in memory .* 10,000,000 frames of 96x96 "
                                         r"need about 257\.5 GiB.*Write an MP4"):
        write_video(counted(10_000_000), tmp_path / "long", 10.0, "gif", total=10_000_000, progress=False)
    assert len(made) == 1 and not list(tmp_path.glob("*long*.gif"))
    for suffix in (".mp4", ".gif"):
        good = write_video(frames(10), tmp_path / f"g{suffix}", 10.0, suffix[1:], progress=False)
        check_video(good, 10, good)
        bad = tmp_path / f"bad{suffix}"
        bad.write_bytes(good.read_bytes()[:len(good.read_bytes()) // 3])
        with pytest.raises(VideoError, match=f"{tmp_path / 'named'}{suffix}: the encoder's file reads back with"):
            check_video(bad, 10, tmp_path / f"named{suffix}")


def test_a_fault_during_a_download_keeps_the_resumable_part_and_names_it(tmp_path):
    from stdr.data import fetch
    from stdr.errors import IOFault
    src = tmp_path / "archive.bin"
    src.write_bytes(os.urandom(300_000))
    dest = tmp_path / "dl" / "archive.bin"
    os.environ["STDR_FAILPOINT"] = "download"
    try:
        with pytest.raises(IOFault, match=rf"cannot write {dest}.part: No space left on device .* stay in "
                                          rf"{dest}.part: the same command resumes"):
            fetch.download([src.as_uri()], dest, log=lambda s: None)
    finally:
        del os.environ["STDR_FAILPOINT"]
    assert not dest.exists()
    fetch.download([src.as_uri()], dest, log=lambda s: None)  # the fault fixed: the same call completes
    assert dest.read_bytes() == src.read_bytes() and not Path(f"{dest}.part").exists()


def test_every_failpoint_site_is_tested_here():
    tested = set(TRAIN_SITES) | {"compact", "pack", "table", "chart", "camera_path", "video", "download"} | \
        {"capture", "frames", "cache"}  # test_capture.py, test_nerfies.py
    assert tested == set(SITES)


# ---------------------------------------------------------------- real faults of a real disk
def _root_mounts() -> str | None:
    if os.geteuid() != 0:
        return "mounting a tmpfs needs root"
    if shutil.which("mount") is None:
        return "no mount command"
    return None


@pytest.fixture
def tmpfs(tmp_path):
    """A 4 MiB tmpfs of this test's own, unmounted at the end: (path, remount(options))."""
    why = _root_mounts()
    if why:
        pytest.skip(why)
    mnt = tmp_path / f"mnt-{uuid.uuid4().hex[:6]}"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", str(mnt)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip()}")

    def remount(opts: str) -> None:
        subprocess.run(["mount", "-o", f"remount,{opts}", str(mnt)], check=True)
    try:
        yield mnt, remount
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)


def test_a_read_only_mount_is_one_line_for_a_new_run_a_rerun_and_stdr_eval(finished, tmpfs, tmp_path):
    mnt, remount = tmpfs
    run = mnt / "run"
    shutil.copytree(finished, run, ignore=shutil.ignore_patterns("renders", "tb", "model.stdrc"))
    before = digest(run)
    remount("ro")
    r = sh(train_cmd(finished.parent, mnt / "new"))
    assert f"cannot write {mnt / 'new'}: Read-only file system" in error_line(r, "stdr-train")
    r = sh(train_cmd(finished.parent, run))  # a rerun of the finished run there
    assert "Read-only file system" in error_line(r, "stdr-train") and str(run) in r.stderr
    r = sh([sys.executable, "-m", "stdr.cli.eval", str(run), f"out={tmp_path / 't'}"])  # re-evaluation writes into it
    assert f"cannot write {run}" in error_line(r, "stdr-eval") and "Read-only file system" in r.stderr
    r = sh([sys.executable, "-m", "stdr.cli.eval", str(run), "reevaluate=false", f"out={mnt / 't'}"])
    assert f"cannot write {mnt / 't'}: Read-only file system" in error_line(r, "stdr-eval")
    assert digest(run) == before
    # reading needs no write: a table of it elsewhere works
    ok = sh([sys.executable, "-m", "stdr.cli.eval", str(run), "reevaluate=false", f"out={tmp_path / 't2'}"])
    assert ok.returncode == 0, ok.stderr[-2000:]


def test_a_full_disk_during_the_checkpoint_keeps_the_previous_and_leaves_no_temporary(finished, tmpfs):
    mnt, _ = tmpfs
    run = mnt / "run"
    shutil.copytree(finished, run, ignore=shutil.ignore_patterns("renders", "tb", "model.stdrc"))
    before = digest(run)
    ck = (run / "checkpoints" / "last.pt").stat().st_size
    free = shutil.disk_usage(mnt).free
    filler = mnt / "filler"
    filler.write_bytes(b"\0" * max(0, free - ck // 2))  # room for half a checkpoint
    r = sh(train_cmd(finished.parent, run))
    line = error_line(r, "stdr-train")
    assert f"cannot write {run / 'checkpoints' / 'last.pt'}: No space left on device" in line and "the disk is full" in line
    assert leftovers(mnt) == []
    after = digest(run)
    assert after["checkpoints/last.pt"] == before["checkpoints/last.pt"]
    assert all(after.get(k) is not None for k in before)


def test_a_file_size_limit_during_the_checkpoint_is_one_line(finished, tmp_path):
    """ulimit -f: the checkpoint is larger than the limit (EFBIG); config.yaml fits."""
    run = _copy(finished, tmp_path)
    before = digest(run)
    limit = (run / "checkpoints" / "last.pt").stat().st_size // 2

    def cap():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    r = subprocess.run(train_cmd(finished.parent, run), capture_output=True, text=True, timeout=600, preexec_fn=cap)
    line = error_line(r, "stdr-train")
    assert f"cannot write {run / 'checkpoints' / 'last.pt'}: File too large" in line and "ulimit -f" in line
    assert leftovers(run) == [] and digest(run)["checkpoints/last.pt"] == before["checkpoints/last.pt"]


@pytest.mark.parametrize("limit", [2_000, 20_000])
def test_a_file_size_limit_on_a_new_run_names_the_file_and_prints_no_traceback(finished, tmp_path, limit):
    """A limit a new run meets early: TensorBoard's writer thread and torch's zip writer hit it,
    and both hide the OSError's path (a thread of its own; a RuntimeError over the OSError). The one
    line still names the file, and nothing prints a traceback."""
    run = tmp_path / "run"

    def cap():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    r = subprocess.run(train_cmd(finished.parent, run), capture_output=True, text=True, timeout=600, preexec_fn=cap)
    line = error_line(r, "stdr-train")
    assert f"cannot write {run}/" in line and ": File too large" in line and "ulimit -f" in line
    assert "Exception in thread" not in r.stderr
    assert leftovers(run) == []


def test_a_path_through_a_file_is_one_line(finished, tmp_path):
    (tmp_path / "afile").write_text("x")
    r = sh(train_cmd(finished.parent, tmp_path / "afile" / "run"))
    assert f"cannot write {tmp_path / 'afile' / 'run'}: Not a directory" in error_line(r, "stdr-train")
    r = sh([sys.executable, "-m", "stdr.cli.eval", str(finished), "reevaluate=false", f"out={tmp_path / 'afile' / 't'}"])
    assert "Not a directory" in error_line(r, "stdr-eval")


def test_a_folder_the_user_may_not_write_is_one_line(finished, tmp_path):
    if os.geteuid() != 0 or shutil.which("setpriv") is None:
        pytest.skip("needs root and setpriv to run the command as another user")
    locked = tmp_path / "theirs"
    locked.mkdir(mode=0o755)  # root's: others may read, not write
    os.chmod(tmp_path, 0o755)
    for p in (tmp_path.parent, tmp_path.parent.parent):
        os.chmod(p, os.stat(p).st_mode | 0o005)
    base = tmp_path / "base"
    shutil.copytree(finished.parent / "cache", base / "cache")
    os.chmod(base, 0o777)
    for p in base.rglob("*"):
        os.chmod(p, 0o777)
    user = ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups", "--"]
    r = sh([*user, *train_cmd(base, locked / "run")], env={"HOME": str(base)})
    if "Permission denied" not in r.stderr and r.returncode != 0 and "Traceback" in r.stderr and "import" in r.stderr:
        pytest.skip(f"the package cannot be imported as another user here: {r.stderr[-300:]}")
    line = error_line(r, "stdr-train")
    assert f"cannot write {locked / 'run'}: Permission denied" in line and "no permission" in line
    assert errno.EACCES  # the cause IO_FIXES names
