"""stdr-tool NAME [ARGS]: the measurement and reporting tools (stdr.tools)."""
from __future__ import annotations

import importlib
import sys

from ..errors import reported
from ..tools import TOOLS


def usage() -> str:
    return ("usage: stdr-tool NAME [ARGS]  (stdr-tool NAME --help for its options)\n\ntools:\n"
            + "\n".join(f"  {name:<18}{_summary(mod)}" for name, mod in TOOLS.items()))


def _summary(entry: str) -> str:
    mod, _, kind = entry.partition(":")
    first = (importlib.import_module(f"stdr.tools.{mod}").__doc__ or "").strip().splitlines()[0]
    return f"{first} ({kind})" if kind else first


@reported("stdr-tool")  # bad input: one line, exit code 2
def main(argv=None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(usage())
        return
    name, rest = argv[0], argv[1:]
    if name not in TOOLS:
        raise SystemExit(f"stdr-tool: no tool {name!r}; one of {', '.join(TOOLS)}\n\n{usage()}")
    mod, _, kind = TOOLS[name].partition(":")
    entry = importlib.import_module(f"stdr.tools.{mod}").main
    code = entry(rest, kind) if kind else entry(rest)
    if code:
        sys.exit(code)


if __name__ == "__main__":
    main()
