"""Per-run records of the studies, kept as one compressed archive per study.

    python -m studies.records pack STUDY [STUDY ...] | --all   # folders -> STUDY/records.tar.xz
    python -m studies.records extract STUDY [--dest DIR]       # records.tar.xz -> the folders again
    python -m studies.records list                              # what each study keeps and archives

(studies/records.py runs this module's `main`; the studies read records through
`records_dir` and `record_file`.)

A study folder under research/measurements/ keeps what a reader opens — its README, protocol, tables
(*.md, and *.json under 100 kB, at its top level), `charts/` (PNG) and `table/` — in the repository
as files, and the rest in `records.tar.xz`: its per-run records (every other subfolder: runs/,
test/, first_attempt/, ...), the SVG copies of its charts and its bulk tables (top-level files of
100 kB or more that are not Markdown or PNG). `records_dir(study, sub)` and `record_file(study,
path)` give a reader the folder or file either way: itself where it exists (extracted, or a study
still writing), else the archive's copy unpacked once into a cache keyed by the archive's SHA-256.
Continuing a study: `extract` it, run, `pack` it again.
"""
from __future__ import annotations

import argparse
import hashlib
import io
import os
import shutil
import tarfile
import tempfile
from pathlib import Path

from stdr.data.fetch import DataError, extract_tar

ROOT = Path(__file__).resolve().parents[1]  # the checkout
M = ROOT / "research" / "measurements"
ARCHIVE = "records.tar.xz"
KEEP = frozenset({"charts", "table"})  # subfolders a reader opens (images and tables the docs link)
BULK = 100_000  # bytes: a top-level file this large (not .md or .png) goes into the archive


def archived_subdirs(study: Path) -> list[Path]:
    return sorted(p for p in study.iterdir() if p.is_dir() and p.name not in KEEP)


def archived_files(study: Path) -> list[Path]:
    """Loose files that go into the archive: every SVG (the PNGs stay) and the bulk tables."""
    svg = [p for p in study.rglob("*.svg") if p.is_file()]
    bulk = [p for p in study.iterdir() if p.is_file() and p.name != ARCHIVE and p.suffix not in (".md", ".png")
            and p.stat().st_size >= BULK]
    return sorted(set(svg + bulk))


def _add_tree(tar: tarfile.TarFile, folder: Path, arc: str) -> None:
    """Files of `folder` under `arc`, sorted, with fixed owners and times (the same bytes give the
    same archive)."""
    for p in sorted(folder.rglob("*")):
        if p.is_symlink():
            raise SystemExit(f"{p}: a symbolic link; records are plain files")
        if not p.is_file():
            continue
        data = p.read_bytes()
        rel = p.relative_to(folder).as_posix()
        info = tarfile.TarInfo(rel if arc == "." else f"{arc}/{rel}")
        info.size, info.mtime, info.mode = len(data), 0, 0o644
        tar.addfile(info, io.BytesIO(data))


def pack(study: Path) -> int:
    """Move every archived subfolder of `study` into study/records.tar.xz (merged with what the
    archive already holds: a folder here replaces the archive's copy). Returns the files archived."""
    subs, loose = archived_subdirs(study), archived_files(study)
    if not subs and not loose:
        return 0
    old = study / ARCHIVE
    with tempfile.TemporaryDirectory() as tmp:
        staging = Path(tmp)
        if old.is_file():
            extract_to(old, staging)
        for s in subs:
            if (staging / s.name).exists():
                shutil.rmtree(staging / s.name)
            shutil.copytree(s, staging / s.name)
        for f in loose:
            dst = staging / f.relative_to(study)
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(f, dst)
        new = study / (ARCHIVE + ".tmp")
        with tarfile.open(new, "w:xz", preset=9) as tar:
            _add_tree(tar, staging, ".")
        n = sum(1 for p in staging.rglob("*") if p.is_file())
        new.replace(old)
    for s in subs:
        shutil.rmtree(s)
    for f in loose:
        f.unlink()
    return n


def extract_to(archive: Path, dest: Path) -> None:
    """Unpack `archive` into dest, all or nothing; members that would leave dest are refused."""
    try:
        extract_tar(archive, dest)
    except DataError as e:
        raise SystemExit(str(e)) from None


def _cache_root() -> Path:
    env = os.environ.get("STDR_MEASUREMENTS_CACHE")
    if env:
        return Path(env)
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "stdr" / "measurements"


def records_dir(study: str, sub: str) -> Path:
    """research/measurements/<study>/<sub> as a folder: itself where it exists, else the study
    archive's copy unpacked (once per archive content) into the user cache. A study without either
    gives the folder's path (which does not exist: the reader says so)."""
    folder = M / study / sub
    archive = M / study / ARCHIVE
    if folder.is_dir() or not archive.is_file():
        return folder
    digest = hashlib.sha256(archive.read_bytes()).hexdigest()[:16]
    cache = _cache_root()
    dest = cache / f"{study}-{digest}"
    if not (dest / ".complete").is_file():
        cache.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{study}-", dir=cache))
        extract_to(archive, tmp)
        (tmp / ".complete").write_text("")
        try:
            os.rename(tmp, dest)  # atomic; another process that got there first wins
        except OSError:
            shutil.rmtree(tmp, ignore_errors=True)
            if not (dest / ".complete").is_file():
                raise
    return dest / sub


def record_file(study: str, rel: str) -> Path:
    """research/measurements/<study>/<rel>: the file itself where it exists, else the archive's copy
    (unpacked into the cache as records_dir does)."""
    path = M / study / rel
    if path.is_file() or not (M / study / ARCHIVE).is_file():
        return path
    return records_dir(study, rel)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("pack")
    p.add_argument("studies", nargs="*")
    p.add_argument("--all", action="store_true")
    e = sub.add_parser("extract")
    e.add_argument("study")
    e.add_argument("--dest", type=Path, default=None)
    sub.add_parser("list")
    args = ap.parse_args(argv)
    if args.cmd == "pack":
        names = sorted(p.name for p in M.iterdir() if p.is_dir()) if args.all else args.studies
        for name in names:
            n = pack(M / name)
            if n:
                print(f"{name}: {n} files into {name}/{ARCHIVE} ({(M / name / ARCHIVE).stat().st_size / 1e6:.1f} MB)")
    elif args.cmd == "extract":
        archive = M / args.study / ARCHIVE
        if not archive.is_file():
            raise SystemExit(f"{archive}: no archive")
        extract_to(archive, args.dest or M / args.study)
        print(f"{args.study}: unpacked into {args.dest or M / args.study}")
    else:
        for s in sorted(p for p in M.iterdir() if p.is_dir()):
            arch = s / ARCHIVE
            print(f"{s.name}: keeps {sorted(p.name for p in s.iterdir() if p.name != ARCHIVE)}"
                  + (f"; archive {arch.stat().st_size / 1e6:.1f} MB" if arch.is_file() else ""))


if __name__ == "__main__":
    main()
