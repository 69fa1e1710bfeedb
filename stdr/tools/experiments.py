"""Every experiment `stdr-train experiment=<name>` accepts, with what it composes.

    stdr-tool experiments [--data dnerf] [--baseline scgs] [--plugin stdr|plain] [--json]

Experiments are not files: `<data>_<baseline>[_<plug-in>]` is made in stdr/store.py
(`derived_experiments`) for every data option, registered baseline and registered plug-in, so a
baseline or plug-in of your own gets its experiments without a file. A YAML file
stdr/configs/experiment/<name>.yaml defines an experiment of its own, or replaces a derived one of
the same name (docs/configuration.md, "Experiments").
"""
from __future__ import annotations

import argparse
import json
from ..store import experiment_table


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="stdr-tool experiments", description=__doc__.split("\n")[0])
    ap.add_argument("--data", default=None, help="only this data option")
    ap.add_argument("--baseline", default=None, help="only this baseline")
    ap.add_argument("--plugin", default=None, help="only with this plug-in on (plain: none on)")
    ap.add_argument("--json", action="store_true", help="the rows as JSON")
    args = ap.parse_args(argv)
    rows = experiment_table()
    if args.data:
        rows = [r for r in rows if r["data"] == args.data]
    if args.baseline:
        rows = [r for r in rows if r["baseline"] == args.baseline]
    if args.plugin:
        rows = [r for r in rows if r["plugins"] is not None and
                (r["plugins"] == [] if args.plugin == "plain" else args.plugin in r["plugins"])]
    if args.json:
        print(json.dumps(rows, indent=1))
        return
    print("| experiment | data | baseline | plug-ins on | source |\n|---|---|---|---|---|")
    for r in rows:
        plugins = "–" if r["plugins"] is None else (", ".join(r["plugins"]) or "none")
        print(f"| {r['name']} | {r['data'] or '–'} | {r['baseline'] or '–'} | {plugins} | {r['source']} |")
    print(f"\n{len(rows)} experiments")


if __name__ == "__main__":
    main()
