"""Old name of `stdr.plugins.stdr` (the STDR plug-in's package), kept working: stdr/_moved.py."""
from .._moved import alias

alias(__name__, "stdr.plugins.stdr", {m: f"stdr.plugins.stdr.{m}" for m in ("config", "field", "mask", "plugin")}, same=True)
