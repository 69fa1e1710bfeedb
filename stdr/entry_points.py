"""Components from other installed distributions, through entry points (the registries of
baselines and plug-ins share this loader).

An entry point names a function that registers (or a module whose import does): in the
distribution's pyproject.toml

    [project.entry-points."stdr.plugins"]
    mine = "my_package.mine:register"
"""
from __future__ import annotations

from typing import Callable, Iterable


def load_group(group: str, registered: Callable[[], Iterable[str]], how: str) -> list[str]:
    """Load every entry point of `group` and return the names it added to the registry that
    `registered()` lists. An entry point that fails, or registers nothing, is an error naming it
    and its distribution; `how` says what it should call (e.g. 'stdr.plugins.register_plugin')."""
    from importlib.metadata import entry_points
    added: list[str] = []
    for ep in entry_points(group=group):
        where = f"entry point {ep.name!r} = {ep.value!r} (group {group!r}" + (
            f", distribution {ep.dist.name} {ep.dist.version})" if getattr(ep, "dist", None) else ")")
        before = set(registered())
        try:
            obj = ep.load()
            if callable(obj) and not isinstance(obj, type):
                obj()
        except Exception as e:
            raise RuntimeError(f"{where} failed: {type(e).__name__}: {e}") from e
        new = sorted(set(registered()) - before)
        if not new and ep.name not in set(registered()):
            raise RuntimeError(f"{where} registered nothing; it must name a function (or module) that calls {how}")
        added += new
    return added
