"""Old name of `stdr.baselines` (the baselines' package), kept working: stdr/_moved.py."""
from .._moved import alias

alias(__name__, "stdr.baselines", {m: f"stdr.baselines.{m}" for m in (
    "base", "control_nodes", "deform3dgs", "geometry", "hexplane", "registry", "superpoints")}, same=True)
