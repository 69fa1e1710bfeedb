"""Measurement and reporting tools behind `stdr-tool NAME` (each module also runs as
`python -m stdr.tools.<module>`): what users of the framework need. Every table they write comes
from stdr.eval.table. The code of one study each lives in the checkout's studies/ folder."""

#: stdr-tool subcommand -> module in this package, or `module:kind` for a module that serves several
#: (its main takes the kind after the arguments); no module may shadow a standard-library one, e.g.
#: `queue`: a tool run by its path puts this folder first on sys.path
TOOLS = {
    "runs": "runs",                          # per-run table: metrics, STDR statistics, groups, screening rule
    "densify-trace": "densify_trace",        # where a run's Gaussians come from, how opaque they end
    "bench-rasterizer": "bench_rasterizer",  # rasterizer backends: time, memory, share of peak
    "bench-train": "bench_train",            # ms per training step by section at fixed counts and sizes
    "identity-check": "identity_check",      # bit-identity of training / composed configs between commits
    "variants": "variants",                  # variants of one method side by side (plain, +STDR, +cull, ...)
    "compact": "compact_run",                # prune a trained run by contribution, fine-tune, save as a new run
    "pack": "pack_file",                     # a trained run's compact model file (model.stdrc) and its cost
    "queue": "queue_tool",                   # a resumable queue of runs, several at once, time-boxed calls
    "experiments": "experiments",            # every experiment stdr-train accepts, with what it composes
    "check-baseline": "conformance:baseline",  # the conformance kit on a registered baseline
    "check-plugin": "conformance:plugin",      # ... on a registered plug-in
}
