"""stdr-data: the public datasets (list, download, verify) and their prepared copies.

    stdr-data list
    stdr-data download dnerf --dest data/dnerf [--scenes standup jumpingjacks]
    stdr-data download hypernerf --scenes vrig_broom --dest data/hypernerf
    stdr-data download lpips [--net vgg alex]                  # LPIPS weights into the user cache
    stdr-data verify data/dnerf
    stdr-data prepare dnerf-400 data/dnerf data/dnerf_400      # the 400x400 copies the budgets assume
    stdr-data capture my_video.mp4 --out data/my_scene          # a phone video to a dataset (pycolmap)

Sources, mirrors and the checks: stdr.data.fetch and docs/data.md ("Getting the datasets").
"""
from __future__ import annotations

import argparse
from pathlib import Path

from ..data.capture import capture
from ..data.capture_input import MATCHERS, SELECT_MODES, CaptureConfig
from ..data import fetch, load
from ..errors import MissingInput, reported
from ..eval.lpips import fetch_dir, fetch_weights
from ..data.dnerf import _resolve_image


def _list() -> None:
    for d in fetch.CATALOG.values():
        print(f"{d.name:10s} {d.title}  [format {d.format}]")
        if d.scene_archives:
            print(f"{'':10s} scenes (one archive each, --scenes): {', '.join(a.name[:-4] for a in d.archives)}")
        else:
            for a in d.archives:
                print(f"{'':10s} scenes: {', '.join(a.scenes)}")
        if d.note:
            print(f"{'':10s} {d.note}")
        print(f"{'':10s} sources: {', '.join(a.urls[0] for a in d.archives[:1])}"
              + (f" (+{len(d.archives[0].urls) - 1} mirrors)" if len(d.archives[0].urls) > 1 else "")
              + (" ..." if len(d.archives) > 1 else ""))
    print(f"{'lpips':10s} LPIPS v0.1 weights (torchvision VGG16 / AlexNet trunks, linear heads), SHA-256 pinned; "
          "fetched on first evaluation, or ahead of time with `stdr-data download lpips`")


def _download_lpips(args) -> Path:
    """`stdr-data download lpips [--net vgg alex] [--dest DIR]`: the LPIPS weights the evaluation
    would fetch on first use, ahead of time (default: the user cache, where it looks)."""
    dest = Path(args.dest) if args.dest else fetch_dir()
    for net in args.net:
        fetch_weights(net, dest)
        print(f"[stdr-data] LPIPS-{net}: weights in {dest} (SHA-256 ok)")
    if args.dest:
        print(f"[stdr-data] not the default folder: set eval.lpips_weights={dest} (or STDR_LPIPS_WEIGHTS)")
    return dest


def _download(args) -> list[Path]:
    if args.name == "lpips":
        return [_download_lpips(args)]
    d = fetch.CATALOG.get(args.name)
    if d is None:
        raise SystemExit(f"stdr-data: no dataset {args.name!r}; `stdr-data list` names them: {sorted(fetch.CATALOG)}")
    dest = Path(args.dest or f"data/{d.name}")
    wanted = set(args.scenes or [])
    archives = list(d.archives)
    keep = None
    if d.scene_archives:
        if wanted:
            names = {a.name[:-4] for a in archives}
            unknown = sorted(wanted - names)
            if unknown:
                raise SystemExit(f"stdr-data: {d.name} has no scene(s) {unknown}; choose from {sorted(names)}")
            archives = [a for a in archives if a.name[:-4] in wanted]
    elif wanted:
        keep = wanted.__contains__
    if args.archive and len(archives) != 1:
        raise SystemExit("stdr-data: --archive names one downloaded file; pick one scene with --scenes")
    lock = fetch.Lock(dest)
    placed: list[Path] = []
    for a in archives:
        if args.archive:
            path, url = Path(args.archive), f"file:{Path(args.archive).resolve()}"
        else:
            path = dest / ".downloads" / a.name
            url = fetch.download(args.urls or a.urls, path, verify=fetch.check_archive)
        fetch.check_archive(path)  # a damaged transfer is never recorded
        state, entry = lock.check(a.name, path, url)  # a changed source stops here
        counts: dict[str, int] = {}

        def check(sc: Path, counts=counts) -> None:
            counts[sc.name] = load.verify_scene(sc, d.format)
        got = fetch.safe_extract(path, dest, keep=keep, check=check)
        for s in got:
            print(f"[stdr-data] {s}: {d.format} layout ok ({counts.get(s.name, '?')} images)")
        if state == "recorded":  # only once the archive unpacked and its scenes passed their checks
            lock.record(a.name, entry)
        print(f"[stdr-data] {a.name}: {path.stat().st_size:,} bytes, CRC ok, SHA-256 {state} ({lock.path})")
        placed += got
        if not args.keep_archive and not args.archive:
            path.unlink()
    if wanted and not d.scene_archives:
        missing = sorted(wanted - {p.name for p in placed})
        if missing:
            raise SystemExit(f"stdr-data: the archive holds no scene(s) {missing}")
    if placed:
        exp = {"dnerf": "dnerf", "nerfies": d.name}[d.format]
        print(f"[stdr-data] done: {len(placed)} scene(s) in {dest}; e.g. stdr-train experiment={exp}_deform "
              f"data.path={placed[0]}")
    return placed


def _existing_folder(path: Path, what: str) -> Path:
    """`path` as a folder that exists, else one MissingInput naming it."""
    path = Path(path)
    if not path.exists():
        raise MissingInput(f"{path}: no such folder ({what})")
    if not path.is_dir():
        raise MissingInput(f"{path}: a file, not a folder ({what})")
    return path


def _verify(folder: Path, fmt: str | None) -> int:
    folder = _existing_folder(folder, "stdr-data verify takes a scene folder or a folder of scenes")
    scenes = [folder] if load.detect_format(folder) else sorted(p for p in folder.iterdir()
                                                                  if p.is_dir() and load.detect_format(p))
    if not scenes:
        raise SystemExit(f"stdr-data verify: {folder} is neither a scene folder (transforms_train.json or "
                         "dataset.json) nor a folder of scenes")
    bad = 0
    for s in scenes:
        try:
            n = load.verify_scene(s, fmt or load.detect_format(s))
            print(f"ok   {s} ({n} images)")
        except fetch.DataError as e:
            print(f"FAIL {s}: {e}")
            bad += 1
    return bad


def prepare_dnerf(src: Path, dest: Path, size: int = 400) -> list[Path]:
    """D-NeRF scenes resized to size x size: RGBA resampled with premultiplied alpha (PIL's RGBa)
    and Lanczos, so edges do not pick up the colour of transparent pixels; transforms copied (the
    field of view does not change): the method the 400x400 copies in ../shared are described
    with, and SC-GS's "resolution 2" setting of the 800x800 originals (not compared pixel by
    pixel with those copies: the originals are not on this machine)."""
    import json
    import shutil

    from PIL import Image

    src, dest = _existing_folder(src, "stdr-data prepare takes a D-NeRF scene or a folder of them"), Path(dest)
    scenes = [src] if load.detect_format(src) == "dnerf" else sorted(
        p for p in src.iterdir() if p.is_dir() and load.detect_format(p) == "dnerf")
    if not scenes:
        raise SystemExit(f"stdr-data prepare: no D-NeRF scene (transforms_train.json) in {src}")
    out = []
    for s in scenes:
        load.verify_scene(s, "dnerf")
        t = dest / s.name
        if t.exists():
            raise SystemExit(f"stdr-data prepare: {t} exists already; remove it or choose another destination")
        tmp = dest / f".{s.name}.partial"
        shutil.rmtree(tmp, ignore_errors=True)
        try:  # a failure (a full disk, a read-only destination) leaves no .partial folder
            tmp.mkdir(parents=True)
            for split in ("train", "val", "test"):
                jp = s / f"transforms_{split}.json"
                shutil.copy2(jp, tmp / jp.name)
                for i, fr in enumerate(json.loads(jp.read_text())["frames"]):
                    img = _resolve_image(s, fr["file_path"], jp, i)
                    rel = img.relative_to(s)
                    (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
                    with Image.open(img) as im:
                        im = im.convert("RGBA").convert("RGBa").resize((size, size), Image.Resampling.LANCZOS)
                        im.convert("RGBA").save(tmp / rel)
            tmp.replace(t)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        print(f"[stdr-data] {t}: {size}x{size}")
        out.append(t)
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="stdr-data", description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    sub.add_parser("list", help="the datasets, their scenes and sources")
    d = sub.add_parser("download", help="download, check and unpack a dataset (resumable)")
    d.add_argument("name", help="dnerf | nerfds | hypernerf | lpips (the LPIPS weights, into the user cache)")
    d.add_argument("--net", nargs="*", choices=("vgg", "alex"), default=["vgg", "alex"],
                   help="lpips: which networks' weights (default both)")
    d.add_argument("--dest", default=None, help="folder for the scenes (default data/<name>)")
    d.add_argument("--scenes", nargs="*", default=None, help="only these scenes")
    d.add_argument("--archive", default=None, help="an archive downloaded by hand (checked and unpacked)")
    d.add_argument("--keep-archive", action="store_true", help="keep the downloaded archive (in DEST/.downloads)")
    d.add_argument("--urls", nargs="*", default=None, help=argparse.SUPPRESS)  # other sources (tests, mirrors)
    v = sub.add_parser("verify", help="check scene folders against the loaders' needs")
    v.add_argument("folder", type=Path)
    v.add_argument("--format", choices=("dnerf", "nerfies"), default=None)
    p = sub.add_parser("prepare", help="prepared copies: dnerf-400 (400x400, premultiplied-alpha Lanczos)")
    p.add_argument("what", choices=("dnerf-400",))
    p.add_argument("src", type=Path)
    p.add_argument("dest", type=Path)
    c = sub.add_parser("capture", help="a video or a folder of images to a Nerfies-format dataset (pycolmap SfM)",
                       description="Frames, camera poses by SfM (pycolmap, CPU), undistortion and a dataset "
                       "`stdr-train experiment=nerfies_deform data.path=OUT` trains on (docs/data.md).")
    c.add_argument("source", type=Path, help="a video file (.mp4, .mov, ...) or a folder of images")
    c.add_argument("--out", type=Path, required=True, help="the dataset folder to create")
    cd = CaptureConfig()
    c.add_argument("--frames", type=int, default=cd.frames, help=f"about this many frames kept (default {cd.frames}; "
                   "0 keeps every frame)")
    c.add_argument("--select", choices=SELECT_MODES, default=cd.select,
                   help="which frame of each stride window is kept (default: the sharpest)")
    c.add_argument("--max-size", type=int, default=cd.max_size, help=f"long side in pixels (default {cd.max_size}; 0 keeps)")
    c.add_argument("--val-every", type=int, default=cd.val_every, help=f"every k-th frame is held out (default {cd.val_every})")
    c.add_argument("--matcher", choices=MATCHERS, default=cd.matcher,
                   help=f"auto: exhaustive up to {cd.exhaustive_max} frames, else sequential")
    c.add_argument("--vocab-tree", default=None, help="COLMAP vocabulary tree file: loop detection in sequential matching")
    c.add_argument("--min-registered", type=float, default=cd.min_registered,
                   help=f"fail when SfM registers a smaller share of the frames (default {cd.min_registered})")
    c.add_argument("--camera-model", default=cd.camera_model, help=f"COLMAP camera model (default {cd.camera_model})")
    c.add_argument("--seed", type=int, default=cd.seed)
    c.add_argument("--threads", type=int, default=cd.threads, help="pycolmap threads (default: all cores)")
    c.add_argument("--overwrite", action="store_true", help="replace an existing --out folder")
    c.add_argument("--keep-work", action="store_true", help="keep COLMAP's database and raw models (colmap/work)")
    args = ap.parse_args(argv)
    with reported("stdr-data"):  # bad input, a failed download or capture: one line, exit code 2
        if args.cmd == "list":
            _list()
        elif args.cmd == "download":
            _download(args)
        elif args.cmd == "verify":
            if _verify(args.folder, args.format):
                raise SystemExit(1)
        elif args.cmd == "prepare":
            prepare_dnerf(args.src, args.dest)
        elif args.cmd == "capture":
            cfg = CaptureConfig(
                frames=args.frames or None, select=args.select, max_size=args.max_size, val_every=args.val_every,
                matcher=args.matcher, vocab_tree=args.vocab_tree, min_registered=args.min_registered,
                camera_model=args.camera_model, seed=args.seed, threads=args.threads)
            capture(args.source, args.out, cfg, overwrite=args.overwrite, keep_work=args.keep_work)


if __name__ == "__main__":
    main()
