#!/usr/bin/env bash
# Kept for old commands: scripts/bench.sh handles D-NeRF and Nerfies-format folders.
exec "$(dirname "$0")/bench.sh" "$@"
