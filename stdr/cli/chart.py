"""stdr-chart RUNS... --out DIR: speed/accuracy charts (PNG, SVG and the plotted CSV) from run
directories, folders of runs (a Hydra multirun folder, a sweep) or a stdr-eval table.json."""
from __future__ import annotations

import argparse
import sys
from ..errors import reported
from ..eval.chart import CHARTS, METRIC_LABELS, chart


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="stdr-chart", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="run folders, folders holding runs, or a stdr-eval table.json")
    ap.add_argument("--out", required=True, help="folder for the charts")
    ap.add_argument("--metric", default="psnr", choices=sorted(METRIC_LABELS), help="the y axis")
    ap.add_argument("--split", default="test")
    ap.add_argument("--charts", nargs="+", default=list(CHARTS), choices=list(CHARTS))
    a = ap.parse_args(sys.argv[1:] if argv is None else argv)
    with reported("stdr-chart"):  # a disk fault: one line naming the file
        try:
            files = chart(a.runs, a.out, a.metric, a.split, a.charts)
        except (ValueError, KeyError, FileNotFoundError) as e:
            raise SystemExit(f"stdr-chart: {e}")
    for name, paths in files.items():
        print(f"[stdr] {name}: {', '.join(str(p) for p in paths.values())}")


if __name__ == "__main__":
    main()
