"""stdr-linear: a baseline (`linear`) and a plug-in (`velocity_l1`) from outside stdr, found through
entry points (pyproject.toml); docs/extending.md walks through them."""
