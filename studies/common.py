"""What the studies' scripts share: the code stamp of a record, and the `run` / `table` command line."""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Callable

from studies.records import ARCHIVE, records_dir

ROOT = Path(__file__).resolve().parents[1]
M = ROOT / "research" / "measurements"


def gmean(xs):
    """The geometric mean of the numbers in xs that are not None; None when there are none or one
    is not positive (a ratio of a missing or zero measurement)."""
    import statistics
    xs = [x for x in xs if x is not None]
    return statistics.geometric_mean(xs) if xs and all(x > 0 for x in xs) else None


def records_in(out: Path, sub: str) -> Path:
    """A study's records folder to read: out/sub where it exists, else (a study folder under
    research/measurements whose records are packed) the archive's copy (studies/records.py)."""
    out = Path(out)
    if (out / sub).is_dir() or out.resolve().parent != M.resolve():
        return out / sub
    return records_dir(out.name, sub)


def records_to_write(out: Path, sub: str) -> Path:
    """out/sub, to add records to; refused while the study's records are only in its archive
    (a new folder would hide them): extract first, pack after."""
    out = Path(out)
    if not (out / sub).is_dir() and (out / ARCHIVE).is_file():
        raise SystemExit(f"{out / sub}: this study's records are packed in {out / ARCHIVE}; extract them first "
                         f"(python -m studies.records extract {out.name}), add, then pack again "
                         f"(python -m studies.records pack {out.name})")
    (out / sub).mkdir(parents=True, exist_ok=True)
    return out / sub


def commit() -> str:
    """The checkout's short commit, `+dirty` when tracked files differ from it (a record's stamp:
    stdr.eval.evaluate.code_version, the one stamp). Files under research/measurements do not count: a
    study rewrites its own tables as it runs."""
    from stdr.eval.evaluate import code_version, commit_stamp
    v = code_version(exclude=("research/measurements",), root=ROOT)
    return commit_stamp(v) if v["commit"] else "unknown"


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
