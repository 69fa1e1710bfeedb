"""Measurement and reporting tools behind `stdr-tool NAME` (each module also runs as
`python -m stdr.tools.<module>`). Every table they write comes from stdr.eval.table."""

#: stdr-tool subcommand -> module in this package
TOOLS = {
    "runs": "runs",                          # per-run table: metrics, STDR statistics, groups, screening rule
    "gap": "gap",                            # STDR's gap to its baseline at several training lengths
    "densify-trace": "densify_trace",        # where a run's Gaussians come from, how opaque they end
    "ghosting": "ghosting",                  # the ghosting scene: deform vs deform+STDR
    "cost-probe": "cost_probe",              # seconds per training step at large Gaussian counts
    "bench-rasterizer": "bench_rasterizer",  # rasterizer backends: time, memory, share of peak
    "bench-train": "bench_train",            # ms per training step by section at fixed counts and sizes
    "identity-check": "identity_check",      # bit-identity of training / composed configs between commits
    "variants": "variants",                  # variants of one method side by side (plain, +STDR, +cull, ...)
    "stability": "stability",                # the degradation study: accuracy under each stress and level
}
