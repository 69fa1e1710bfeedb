"""stdr-view RUN_DIR: a web viewer of a trained run (time slider, free camera, RGB / depth / alpha,
STDR's mask and static/dynamic split), served on localhost; stdr-render RUN_DIR: videos."""
from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time
from pathlib import Path

from ..errors import UserError, reported


def _positive(kind):
    """argparse type: a number of `kind` > 0 (a width, a frame count, a rate)."""
    def parse(text: str):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a {'whole number' if kind is int else 'number'}") from None
        if not v > 0 or v != v or v == float("inf"):
            raise argparse.ArgumentTypeError(f"{text}: must be > 0")
        return v
    return parse


# The commands import the model's modules in their bodies, under `reported`: importing them
# registers the baselines and plug-ins of the installed packages, and one declared wrongly is then
# a one-line error of the command, not a traceback.
@reported("stdr-view")  # bad input: one line, exit code 2
def view_main(argv=None) -> None:
    from ..view.browser import screenshot  # in the body: the note above view_main
    from ..view.core import VIEWS, open_run, unfinished_note  # in the body: the note above view_main
    from ..view.server import Viewer, check_port  # in the body: the note above view_main
    ap = argparse.ArgumentParser(prog="stdr-view", description="A web viewer of a trained stdr run (viser).")
    ap.add_argument("run", type=Path, help="a run directory (config.yaml + checkpoints/last.pt)")
    ap.add_argument("--port", type=int, default=8080)
    ap.add_argument("--host", default="127.0.0.1", help="127.0.0.1 (default: this machine only) or 0.0.0.0")
    ap.add_argument("--device", default=None, help="cpu | cuda | auto (default: the run's own)")
    ap.add_argument("--model", type=Path, default=None, help="a model file to show instead of the checkpoint, "
                    "e.g. RUN/model.stdrc (stdr-tool pack)")
    ap.add_argument("--max-width", type=_positive(int), default=None, help="initial image width (default: the run's)")
    ap.add_argument("--allow-origin", action="append", default=[], metavar="URL",
                    help="another page address that may drive the viewer (e.g. a reverse proxy's "
                    "https://viewer.lab.example); by default only the viewer's own page can")
    ap.add_argument("--view", default="rgb", choices=VIEWS, help="the view to start with")
    ap.add_argument("--screenshot", type=Path, default=None,
                    help="open the page in headless Chromium, save a PNG once it shows a render, and exit")
    a = ap.parse_args(argv)
    try:
        check_port(a.host, a.port)  # before loading the model: fail fast
        run = open_run(a.run, device=a.device, model_file=a.model)
        note = unfinished_note(run.model, "the view")
        if note:
            print(f"[stdr] {note}", flush=True)
        viewer = Viewer(run, host=a.host, port=a.port, max_width=a.max_width, allow_origins=tuple(a.allow_origin))
    except UserError:
        raise  # bad input: one line and exit 2 (reported)
    except (FileNotFoundError, RuntimeError, ValueError) as e:
        raise SystemExit(f"stdr-view: {e}") from None
    if a.view not in viewer.views:
        viewer.stop()
        raise SystemExit(f"stdr-view: --view {a.view} is not available for this run ({', '.join(viewer.views)})")
    viewer.gui_view.value = a.view
    if run.data_note:
        print(f"[stdr] {run.data_note}")
    if a.screenshot is not None:
        try:
            n0 = 0
            path = screenshot(viewer.url, a.screenshot, ready=lambda: len(viewer.frame_ms) > n0)
        except (RuntimeError, TimeoutError) as e:
            raise SystemExit(f"stdr-view --screenshot: {e}") from None
        finally:
            viewer.stop()
        import numpy as np
        print(f"[stdr] screenshot {path}; frame time {np.median(viewer.frame_ms):.0f} ms (median of "
              f"{len(viewer.frame_ms)} frames)")
        return
    print(f"[stdr] viewing {a.run} ({run.model.num_gaussians:,} Gaussians, backend {run.model.backend} on "
          f"{run.model.device}) at {viewer.url}  (Ctrl+C stops)", flush=True)
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        viewer.stop()
        if viewer.frame_ms:
            import numpy as np
            print(f"[stdr] median frame time {np.median(viewer.frame_ms):.0f} ms over {len(viewer.frame_ms)} frames")


@reported("stdr-render")  # bad input: one line, exit code 2
def render_main(argv=None) -> None:
    from ..compression.file import model_source  # in the body: the note above view_main
    from ..io.checkpoint import source_line  # in the body: the note above view_main
    from ..view.camera_path import read_camera_path  # in the body: the note above view_main
    from ..view.core import VIEWS, open_run, unfinished_note  # in the body: the note above view_main
    from ..view.video import KINDS, path_frames, render_videos, write_video  # in the body: the note above view_main
    ap = argparse.ArgumentParser(prog="stdr-render", description="Videos of a trained stdr run.")
    ap.add_argument("run", type=Path, help="a run directory (config.yaml + checkpoints/last.pt)")
    ap.add_argument("--out", type=Path, default=None, help="folder for the videos (default: RUN/videos)")
    ap.add_argument("--kinds", default=",".join(KINDS), help=f"comma-separated: {', '.join(KINDS)}")
    ap.add_argument("--view", default="rgb", choices=VIEWS)
    ap.add_argument("--width", type=_positive(int), default=None, help="image width (default: the run's)")
    ap.add_argument("--frames", type=_positive(int), default=60, help="frames of the time sweep and the orbit")
    ap.add_argument("--fps", type=_positive(float), default=15.0)
    ap.add_argument("--split", default="test", help="the split the comparison walks through")
    ap.add_argument("--format", default="auto", choices=("auto", "mp4", "gif"))
    ap.add_argument("--path", type=Path, default=None,
                    help="a camera path (nerfstudio's camera_path.json, e.g. saved by stdr-view): render it "
                    "instead of --kinds, at its size (or --width) and fps (or --fps when given)")
    ap.add_argument("--device", default=None)
    ap.add_argument("--model", type=Path, default=None, help="a model file to render instead of the checkpoint, "
                    "e.g. RUN/model.stdrc (stdr-tool pack)")
    a = ap.parse_args(argv)
    fps_given = any(x == "--fps" or x.startswith("--fps=") for x in (argv if argv is not None else sys.argv[1:]))
    try:
        if a.path is not None:
            cp = read_camera_path(a.path, width=a.width)  # before loading the model: fail fast
        run = open_run(a.run, device=a.device, model_file=a.model)
        source = source_line(model_source(a.model or a.run / "checkpoints" / "last.pt"))
        note = unfinished_note(run.model, "the video")
        if note:
            print(f"[stdr] {note}", flush=True)
        if a.path is not None:
            imgs = path_frames(run, cp.cameras, cp.times, a.view)
            paths = {"path": write_video(imgs, (a.out or a.run / "videos") / f"{a.path.stem}_{a.view}",
                                         a.fps if fps_given else cp.fps, a.format, total=len(cp.cameras),
                                         comment=source)}
        else:
            paths = render_videos(run, a.out or a.run / "videos", [k for k in a.kinds.split(",") if k], a.width,
                                  a.frames, a.fps, a.view, a.split, a.format, comment=source)
    except UserError:
        raise  # bad input: one line and exit 2 (reported)
    except (FileNotFoundError, RuntimeError, ValueError) as e:
        raise SystemExit(f"stdr-render: {e}") from None
    how = "MP4 (imageio-ffmpeg)" if any(p.suffix == ".mp4" for p in paths.values()) else \
        "GIF (--format gif, or no ffmpeg writer: pip install imageio-ffmpeg for MP4)"
    print(f"[stdr] wrote {how}: " + ", ".join(str(p) for p in paths.values()))


@reported("stdr-export")  # bad input: one line, exit code 2
def export_main(argv=None) -> None:
    """stdr-export RUN --times 0 0.5 1 --out DIR: the model at each time as a 3DGS PLY."""
    from ..compression.file import model_source  # in the body: the note above view_main
    from ..io.checkpoint import source_line  # in the body: the note above view_main
    from ..io.export import check_times, export_times  # in the body: the note above view_main
    from ..io.files import run_lock  # in the body: the note above view_main
    from ..model import load_model  # in the body: the note above view_main
    from ..view.core import unfinished_note  # in the body: the note above view_main
    ap = argparse.ArgumentParser(prog="stdr-export", description="A trained run at given times as standard 3DGS "
                                 "PLY files (deformed, opacity with the plug-ins' factors), for splat viewers.")
    ap.add_argument("run", type=Path, help="a run directory (checkpoints/last.pt), a checkpoint file or a compact "
                    "model file (model.stdrc, stdr-tool pack)")
    ap.add_argument("--times", type=float, nargs="+", required=True, help="times in [0, 1]")
    ap.add_argument("--out", type=Path, default=None, help="folder (default: RUN/export)")
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args(argv)
    ck = args.run if args.run.is_file() else args.run / "checkpoints" / "last.pt"
    if not ck.is_file():
        raise SystemExit(f"stdr-export: {ck} not found: pass a run directory with checkpoints/last.pt or a checkpoint")
    check_times(args.times)  # before the model is loaded: fail fast
    model = load_model(ck, device=args.device)
    model.eval()
    note = unfinished_note(model, "the export")
    if note:
        print(f"[stdr] {note}", flush=True)
    run_dir = args.run if args.run.is_dir() else None
    out = args.out or (args.run if args.run.is_dir() else args.run.parent) / "export"
    inside = run_dir is not None and Path(os.path.realpath(out)).is_relative_to(os.path.realpath(run_dir))
    with run_lock(run_dir, "stdr-export") if inside else contextlib.nullcontext():  # writing into the run
        for p in export_times(model, args.times, out, source=source_line(model_source(ck))):
            print(f"[stdr] {p}")
