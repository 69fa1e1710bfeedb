#!/usr/bin/env bash
# Run a command from the project venv, with tcmalloc preloaded when the system has it
# (measured: torch CPU code runs 2-2.5x faster with it).
here=$(cd "$(dirname "$0")/.." && pwd)
lib=/usr/lib/x86_64-linux-gnu/libtcmalloc_minimal.so.4
if [ -f "$lib" ] && [[ "${LD_PRELOAD:-}" != *tcmalloc* ]]; then export LD_PRELOAD="$lib${LD_PRELOAD:+:$LD_PRELOAD}"; fi
export PATH="$here/.venv/bin:$PATH"
exec "$@"
