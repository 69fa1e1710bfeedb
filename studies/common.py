"""What the studies' scripts share: the code stamp of a record, and the `run` / `table` command line."""
from __future__ import annotations

import argparse
import subprocess
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parents[1]


def commit() -> str:
    """The checkout's short commit, `+dirty` when tracked files differ from it (a record's stamp)."""
    out = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True).stdout.strip()
    return out.stdout.strip() + ("+dirty" if dirty else "")


def run_table_main(doc: str, out: Path, table_name: str, run: Callable, table: Callable[[Path], str],
                   add_run_args: Callable[[argparse.ArgumentParser], None] = lambda p: None, argv=None) -> None:
    """`run RUN_DIR ... [--out FOLDER]` calls run(args) and then writes the table; `table [--out
    FOLDER]` writes it alone: FOLDER/table_name from table(FOLDER), also printed."""
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("runs", type=Path, nargs="+")
    r.add_argument("--out", type=Path, default=out)
    add_run_args(r)
    t = sub.add_parser("table")
    t.add_argument("--out", type=Path, default=out)
    args = ap.parse_args(argv)
    if args.cmd == "run":
        run(args)
    text = table(args.out)
    (args.out / table_name).write_text(text)
    print(text)
