"""Public datasets: where they are, resumable downloads, safe unpacking, layout checks (`stdr-data`).

Small stateless functions:

* `download(urls, dest)`: the first URL that answers, resumed from `dest.part` with an HTTP Range
  request when a transfer was cut, with a progress bar; the bytes land in `dest` only when whole.
* `check_archive(path)`: a zip's CRC of every member (`zipfile.testzip`).
* `Lock`: no checksums are published for these archives, so the first download records size and
  SHA-256 in `<dest>/stdr-data.lock.json`, and later downloads of the same archive must match it.
* `safe_extract(archive, dest)`: unpacks into a temporary folder beside `dest`, refuses members
  that would leave it (absolute paths, `..`, symbolic links), detects the top-level folder
  instead of assuming it, and renames into place, so a failure leaves no half-written dataset.
* `stdr.data.load.verify_scene(folder, fmt)`: the layout the loaders need (D-NeRF: transforms and images;
  Nerfies format: dataset, metadata, scene, cameras and images of every listed id).

Sources and their mirrors: ../shared/reference/data-sources.md (kept in the catalog below).
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import stat
import tarfile
import tempfile
import urllib.error
import urllib.request
import zipfile
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Callable, Optional

from ..errors import IOFault, UserError
from ..io.files import make_folder, writing

CHUNK = 1 << 20
LOCK_NAME = "stdr-data.lock.json"


@dataclass(frozen=True)
class Archive:
    name: str               # file name of the download (and its key in the lock file)
    urls: tuple[str, ...]   # tried in order
    scenes: tuple[str, ...] = ()  # scene folders it holds (informative; the layout is checked, not assumed)


@dataclass(frozen=True)
class Dataset:
    name: str
    title: str
    format: str                       # dnerf | nerfies (the loader that reads its scenes)
    archives: tuple[Archive, ...]
    note: str = ""
    scene_archives: bool = False      # one archive per scene (pick with --scenes)
    aliases: dict = field(default_factory=dict)


_HF = "https://huggingface.co/camenduru/4DGaussians/resolve/main/data/data.zip"
_HN = "https://github.com/google/hypernerf/releases/download/v0.1/"
CATALOG: dict[str, Dataset] = {
    "dnerf": Dataset(
        "dnerf", "D-NeRF synthetic (8 scenes, 800x800 RGBA)", "dnerf",
        (Archive("dnerf-data.zip", (_HF, "https://www.dropbox.com/s/raw/0bf6fl0ye2vz3vr/data.zip",
                                    "https://www.dropbox.com/scl/fi/cdcmkufncwcikk1dzbgb4/data.zip"
                                    "?rlkey=n5m21i84v2b2xk6h7qgiu8nkg&dl=1"),
                 ("bouncingballs", "hellwarrior", "hook", "jumpingjacks", "lego", "mutant", "standup", "trex")),),
        note="~700 MB unpacked; `stdr-data prepare dnerf-400` makes the 400x400 copies the budgets assume"),
    "nerfds": Dataset(
        "nerfds", "NeRF-DS (7 real scenes, specular objects; Nerfies format)", "nerfies",
        (Archive("NeRF-DS.dataset.zip",
                 ("https://github.com/JokerYan/NeRF-DS/releases/download/v0.1-pre-release/NeRF-DS.dataset.zip",),
                 ("as_novel_view", "basin_novel_view", "bell_novel_view", "cup_novel_view", "plate_novel_view",
                  "press_novel_view", "sieve_novel_view")),),
        note="~2.1 GB; train with experiment=nerfds_<baseline> data.path=<dest>/<scene>"),
    "hypernerf": Dataset(
        "hypernerf", "HyperNeRF (17 real scenes in vrig / interp / misc; Nerfies format)", "nerfies",
        tuple(Archive(f"{a}.zip", (f"{_HN}{a}.zip",), (a,)) for a in (
            "vrig_3dprinter", "vrig_broom", "vrig_chicken", "vrig_peel-banana",
            "interp_aleks-teapot", "interp_chickchicken", "interp_cut-lemon", "interp_hand", "interp_slice-banana",
            "interp_torchocolate", "misc_americano", "misc_cross-hands", "misc_espresso", "misc_keyboard",
            "misc_oven-mitts", "misc_split-cookie", "misc_tamping")),
        note="one archive per scene (~1.5 GB each); vrig: experiment=hypernerf_<baseline>, interp: data=hypernerf_interp",
        scene_archives=True),
}


class DataError(UserError, RuntimeError):
    """A download, archive or layout that cannot be used; the message says what to do."""


# ------------------------------------------------------------------ download
def _progress(total: Optional[int], initial: int, desc: str):
    from tqdm import tqdm
    return tqdm(total=total, initial=initial, unit="B", unit_scale=True, desc=desc, dynamic_ncols=True,
                disable=os.environ.get("STDR_DATA_QUIET") == "1")


def _content_range(value: Optional[str]) -> tuple[Optional[int], Optional[int]]:
    """(first byte, total) of a Content-Range header ('bytes 100-199/1000', 'bytes */1000');
    None where it does not say."""
    m = re.fullmatch(r"\s*bytes\s+(?:(\d+)-\d+|\*)/(\d+|\*)\s*", value or "")
    if m is None:
        return None, None
    return (int(m.group(1)) if m.group(1) else None), (int(m.group(2)) if m.group(2) != "*" else None)


def _fetch_one(url: str, dest: Path, timeout: float, verify: Optional[Callable[[Path], None]] = None) -> None:
    """Fetch `url` into dest, resuming dest.part. Only a body whose length is known and reached, or
    that `verify` accepts, is moved into place: a resume whose Content-Range does not start where
    the .part ends starts over, a .part the server calls complete (416) is checked and kept, and a
    body of unknown length is verified before it is kept (and deleted when it fails)."""
    part = dest.with_name(dest.name + ".part")
    have = part.stat().st_size if part.is_file() else 0
    req = urllib.request.Request(url, headers={"User-Agent": "stdr-data"})
    if have:
        req.add_header("Range", f"bytes={have}-")
    try:
        r = urllib.request.urlopen(req, timeout=timeout)
    except urllib.error.HTTPError as e:
        if e.code != 416 or not have:
            raise
        _, total = _content_range(e.headers.get("Content-Range"))
        if total is not None and total == have:  # the .part holds the whole file already
            _keep(part, dest, url, verify, f"{have} bytes, the whole file by the server's word")
            return
        part.unlink()  # a .part the server cannot continue (the file changed): start over
        return _fetch_one(url, dest, timeout, verify)
    with r:
        status = getattr(r, "status", 200)
        if have and status == 206:
            start, whole = _content_range(r.headers.get("Content-Range"))
            length = r.headers.get("Content-Length")
            if start != have or (whole is not None and length is not None and whole != have + int(length)):
                # not the continuation of this .part: start over
                r.close()
                part.unlink()
                return _fetch_one(url, dest, timeout, verify)
        elif have:  # the server ignored the range: the body is the whole file
            have = 0
        length = r.headers.get("Content-Length")
        total = (int(length) + have) if length is not None else None
        try:
            with writing(part, "download"), open(part, "ab" if have else "wb") as f, \
                    _progress(total, have, dest.name) as bar:
                while True:
                    chunk = r.read(CHUNK)
                    if not chunk:
                        break
                    f.write(chunk)
                    bar.update(len(chunk))
        except IOFault as e:  # this machine's disk, not the source: no other source is tried
            kept = part.stat().st_size if part.is_file() else 0
            raise IOFault(e.errno, f"{e} The {kept:,} bytes fetched so far stay in {part}: the same command "
                          "resumes from them once the fault is fixed") from None
    got = part.stat().st_size
    if total is not None and got != total:
        raise DataError(f"{url}: the transfer stopped at {got} of {total} bytes; run the command again to resume "
                        f"from {part}")
    if total is None:
        _keep(part, dest, url, verify, f"{got} bytes of a body whose length the server did not send")
        return
    part.replace(dest)


def _keep(part: Path, dest: Path, url: str, verify: Optional[Callable[[Path], None]], what: str) -> None:
    """Move a .part whose completeness the transfer cannot show into place once `verify` accepts
    it; without a verify it is not kept."""
    if verify is None:
        part.unlink()
        raise DataError(f"{url}: {what}, and nothing to check it against; download it by hand and pass it "
                        "with --archive")
    try:
        verify(part)
    except DataError as e:
        part.unlink()
        raise DataError(f"{url}: {what}, which fails its check ({e}); deleted, run the command again") from None
    part.replace(dest)


def download(urls: tuple[str, ...] | list[str], dest: Path, timeout: float = 60.0,
             log: Callable[[str], None] = print, verify: Optional[Callable[[Path], None]] = None) -> str:
    """Fetch the first of `urls` that works into `dest` (resuming `dest.part`); returns the URL.
    `verify(path)` (e.g. check_archive) checks a file whose completeness the transfer cannot
    show (no Content-Length, or a .part the server calls complete) before it is kept."""
    make_folder(dest.parent)
    errors = []
    for url in urls:
        try:
            _fetch_one(url, dest, timeout, verify)
            return url
        except IOFault:
            raise  # a fault of this machine's disk: the next source would meet it too
        except (urllib.error.URLError, OSError, DataError) as e:
            errors.append(f"{url}: {e}")
            log(f"[stdr-data] {url} failed ({e}); trying the next source" if url != urls[-1] else
                f"[stdr-data] {url} failed ({e})")
    raise DataError(f"no source of {dest.name} worked:\n  " + "\n  ".join(errors) +
                    "\nCheck the network, or download one of these URLs by hand and pass it with --archive")


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(CHUNK), b""):
            h.update(chunk)
    return h.hexdigest()


class Lock:
    """<folder>/stdr-data.lock.json: {archive name: {size, sha256, url}} of the first download."""

    def __init__(self, folder: Path):
        self.path = Path(folder) / LOCK_NAME
        self.entries: dict = json.loads(self.path.read_text()) if self.path.is_file() else {}

    def check(self, name: str, archive: Path, url: str) -> tuple[str, dict]:
        """('recorded', the entry to record once the archive is unpacked) the first time, or
        ('matches', its entry); a different size or SHA-256 is a DataError. Writes nothing."""
        size, digest = archive.stat().st_size, sha256(archive)
        old = self.entries.get(name)
        if old is None:
            return "recorded", {"size": size, "sha256": digest, "url": url}
        if (old["size"], old["sha256"]) != (size, digest):
            raise DataError(f"{archive}: {size} bytes, SHA-256 {digest}, but {self.path} recorded {old['size']} bytes, "
                            f"SHA-256 {old['sha256']} (from {old.get('url')}). The source changed or the file is "
                            f"damaged: delete {archive} and download again; if the new archive is right, remove its "
                            f"entry from {self.path}")
        return "matches", old

    def record(self, name: str, entry: dict) -> None:
        """Write `entry` for archive `name` (after it was unpacked and its scenes checked)."""
        self.entries[name] = entry
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_name(self.path.name + ".tmp")
        tmp.write_text(json.dumps(self.entries, indent=1, sort_keys=True) + "\n")
        tmp.replace(self.path)


# ------------------------------------------------------------------ archives
def check_archive(path: Path) -> None:
    """Every member's CRC (a truncated or corrupted zip is a DataError naming the file)."""
    try:
        with zipfile.ZipFile(path) as z:
            bad = z.testzip()
    except (zipfile.BadZipFile, OSError) as e:
        raise DataError(f"{path}: not a readable zip archive ({e}); delete it and download again") from None
    if bad is not None:
        raise DataError(f"{path}: member {bad!r} fails its CRC check; delete the archive and download again")


def _member_problem(info: zipfile.ZipInfo) -> Optional[str]:
    name = info.filename
    p = PurePosixPath(name.replace("\\", "/"))
    if p.is_absolute() or (len(name) > 1 and name[1] == ":"):
        return "an absolute path"
    if ".." in p.parts:
        return "a '..' component"
    if stat.S_ISLNK(info.external_attr >> 16):
        return "a symbolic link"
    return None


def safe_extract(archive: Path, dest: Path, keep: Optional[Callable[[str], bool]] = None,
                 check: Optional[Callable[[Path], object]] = None) -> list[Path]:
    """Unpack `archive` and move its scene folders into `dest`; returns the folders placed.

    The archive's top level is detected: its one top-level folder is descended into when the
    scenes lie under it (D-NeRF's `data/`), else the top-level folders are the scenes. `keep(name)`
    picks scene folders by name; `check(folder)` (e.g. stdr.data.load.verify_scene) runs on every scene before
    any is moved. Members that would leave the destination are refused before anything is
    written; the unpacking goes to a temporary folder inside `dest` and the scenes are renamed
    into place only when all passed, so a failure leaves no partial dataset. An existing scene
    folder is an error."""
    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(archive) as z:
        infos = z.infolist()
        for info in infos:
            why = _member_problem(info)
            if why is not None:
                raise DataError(f"{archive}: member {info.filename!r} is {why}; refusing to unpack an archive that "
                                "could write outside its destination")
        tmp = Path(tempfile.mkdtemp(prefix=".stdr-data-", dir=dest))
        try:
            z.extractall(tmp)
            root = tmp
            while True:  # descend through single wrapper folders (e.g. data/)
                kids = [k for k in root.iterdir() if not k.name.startswith(("__MACOSX", "."))]
                if len(kids) == 1 and kids[0].is_dir() and not _looks_like_scene(kids[0]):
                    root = kids[0]
                else:
                    break
            scenes = [k for k in sorted(root.iterdir()) if k.is_dir() and not k.name.startswith(("__MACOSX", "."))]
            if _looks_like_scene(root):
                scenes = [root]
            if not scenes:
                raise DataError(f"{archive} holds no scene folder (one with transforms_train.json or dataset.json); "
                                f"nothing was unpacked into {dest}: is it the right archive?")
            if keep is not None:
                scenes = [s for s in scenes if keep(s.name)]
            targets = [dest / (Path(archive).stem if sc == tmp else sc.name) for sc in scenes]
            for t in targets:
                if t.exists():
                    raise DataError(f"{t} exists already; remove it (or pass another --dest) to unpack it again")
            if check is not None:
                for sc, t in zip(scenes, targets):
                    try:
                        check(sc)
                    except DataError as e:
                        raise DataError(f"{archive}: scene {t.name}: {str(e).replace(str(sc), t.name)}; nothing "
                                        f"was unpacked into {dest}") from None
            for sc, t in zip(scenes, targets):
                sc.replace(t)
            return targets
        finally:
            shutil.rmtree(tmp, ignore_errors=True)


def extract_tar(archive: Path, dest: Path, member_ok: Optional[Callable[[str], bool]] = None,
                what: str = "a plain file or folder inside the archive") -> list[str]:
    """Unpack the tar `archive` into `dest`, all or nothing: every member is checked first (plain
    files and folders only; no absolute path, no '..', no link or device; `member_ok(name)` if
    given, `what` naming what it allows), the archive is unpacked into a temporary folder beside
    `dest`, and only then are its files moved into place (over files of the same name). A refused
    member, or a failure while unpacking, leaves `dest` as it was and no temporary folder behind.
    Returns the files' names, as in the archive."""
    dest = Path(dest)
    with tarfile.open(archive) as tar:
        members = tar.getmembers()
        for m in members:
            name = m.name
            p = PurePosixPath(name)
            ok = ((m.isfile() or m.isdir()) and not p.is_absolute() and ".." not in p.parts
                  and (member_ok is None or m.isdir() or member_ok(name)))
            if not ok:
                raise DataError(f"{archive}: member {name!r} is not {what}; refused, nothing was unpacked")
        dest.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{dest.name}-", dir=dest.parent))
        try:
            tar.extractall(tmp, members=members, filter="data")
            files = sorted(m.name for m in members if m.isfile())
            for name in files:
                target = dest / name
                target.parent.mkdir(parents=True, exist_ok=True)
                os.replace(tmp / name, target)
            return files
        finally:
            shutil.rmtree(tmp, ignore_errors=True)


def _looks_like_scene(folder: Path) -> bool:
    return (folder / "transforms_train.json").is_file() or (folder / "dataset.json").is_file()


