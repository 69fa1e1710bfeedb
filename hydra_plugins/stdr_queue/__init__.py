"""stdr's Hydra sweeper `stdr_queue` (hydra/sweeper=stdr_queue): the runs of a queue file, handed to
the configured launcher (stdr.tools.runqueue, docs/sweeps.md)."""
