"""The one registry helper behind baselines, plug-ins and densification strategies.

A `Registry` maps names to components of one kind. It is read like a dict (`name in R`, `R[name]`,
`sorted(R)`, `R.values()`: what is registered now) and changed only through `add` / `remove`,
which call its listeners with `(name, added)` (stdr.store keeps Hydra's options in step that way).
`get(name)` and `discover()` first register the built-in modules and whatever installed
distributions provide through the registry's entry-point group:

    # in another distribution's pyproject.toml
    [project.entry-points."stdr.baselines"]      # or "stdr.plugins", "stdr.strategies"
    mine = "my_package.mine:register"            # a function that registers (or a module whose import does)

| registry | entry-point group | registers with |
|---|---|---|
| `stdr.baselines.BASELINES` | `stdr.baselines` | `register_baseline(name, module, config)` |
| `stdr.plugins.PLUGINS` | `stdr.plugins` | `register_plugin(name, plugin, config, label)` |
| `stdr.densify.strategy.STRATEGIES` | `stdr.strategies` | `register_strategy(name, cls)` |

Each kind's own `register_*` function checks what is specific to it (base class, config
dataclass, name rules) and then calls `add`.
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import Callable, Generic, Iterator, Optional, TypeVar

from .errors import RegistrationError, UserError

T = TypeVar("T")

#: what a baseline can declare (its module's `capabilities`, checked by register_baseline) and a
#: plug-in can require (its `requires` names them)
CAPABILITY_NAMES = ("conditioning", "opacity_deltas", "mixes_rows")


def entry_point_name(ep, group: str) -> str:
    """How an error names entry point `ep` of `group`: its name, value, group and distribution."""
    return f"entry point {ep.name!r} = {ep.value!r} (group {group!r}" + (
        f", distribution {ep.dist.name} {ep.dist.version})" if getattr(ep, "dist", None) else ")")


class Registry(Mapping, Generic[T]):
    """Components of one kind by name (see the module docstring).

    kind: what one component is called in errors ("baseline"); key: the config key that selects
    one ("baseline.name"); group: the entry-point group; how: the function an entry point should
    call; builtin: modules whose import registers the components that ship with stdr; owner: the
    object two registrations of one name must share (a re-registration by another is an error);
    fixed: names that cannot be removed."""

    def __init__(self, kind: str, key: str, group: str, how: str, builtin: tuple[str, ...] = (),
                 owner: Callable[[T], object] = lambda item: item, fixed: tuple[str, ...] = (),
                 initial: Optional[dict[str, T]] = None):
        self.kind, self.key, self.group, self.how = kind, key, group, how
        self.builtin, self.owner, self.fixed = builtin, owner, frozenset(fixed)
        self._items: dict[str, T] = dict(initial or {})
        self._listeners: list[Callable[[str, bool], None]] = []
        self._discovered = False

    # ------------------------------------------------------------ read (what is registered now)
    def __getitem__(self, name: str) -> T:
        return self._items[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._items)

    def __len__(self) -> int:
        return len(self._items)

    def __repr__(self) -> str:
        return f"Registry({self.kind}: {sorted(self._items)})"

    # ------------------------------------------------------------ change
    def add_listener(self, fn: Callable[[str, bool], None]) -> None:
        """fn(name, added) after every add and remove."""
        if fn not in self._listeners:
            self._listeners.append(fn)

    def add(self, name: str, item: T) -> T:
        """Register `item` under `name`. The same owner again is a no-op update; another owner
        under a taken name is a ValueError naming both."""
        if name in self._items and self.owner(self._items[name]) is not self.owner(item):
            held = self.owner(self._items[name])
            raise RegistrationError(f"{self.kind} {name!r} is already registered (by {getattr(held, '__name__', held)})")
        self._items[name] = item
        for fn in self._listeners:
            fn(name, True)
        return item

    def remove(self, name: str) -> None:
        """Unregister `name` (tests that register a temporary component); fixed names stay."""
        if name not in self.fixed and self._items.pop(name, None) is not None:
            for fn in self._listeners:
                fn(name, False)

    # ------------------------------------------------------------ discovery and lookup
    def discover(self) -> list[str]:
        """Import the built-in modules and load the entry-point group, once per process. Returns
        the names added. An entry point that fails, or registers nothing, is an error naming it
        and its distribution: a RegistrationError (reported in one line) where its package declared
        something wrongly, a RuntimeError with the traceback for anything else (an import, a bug)."""
        if self._discovered:
            return []
        self._discovered = True
        import importlib
        from importlib.metadata import entry_points
        before = set(self._items)
        for mod in self.builtin:
            importlib.import_module(mod)
        for ep in entry_points(group=self.group):
            where = entry_point_name(ep, self.group)
            had = set(self._items)
            try:
                obj = ep.load()
                if callable(obj) and not isinstance(obj, type):
                    obj()
            except UserError as e:  # a declaration its package can fix: one line, naming the entry point
                raise RegistrationError(f"{where}: {e}") from e
            except Exception as e:
                raise RuntimeError(f"{where} failed: {type(e).__name__}: {e}") from e
            if not (set(self._items) - had) and ep.name not in self._items:
                raise RegistrationError(f"{where} registered nothing; it must name a function (or module) that calls "
                                        f"{self.how}")
        return sorted(set(self._items) - before)

    def get(self, name: str) -> T:
        """The component `name`, after discovery; a ValueError naming the config key and the
        choices when there is none."""
        if name not in self._items:
            self.discover()
        if name not in self._items:
            raise ValueError(f"{self.key}={name!r} is not a registered {self.kind}; choose one of "
                             f"{sorted(self._items)} ({self.how} adds one)")
        return self._items[name]

    def registered(self) -> list[T]:
        """Every component, in registration order (built-in ones first), after discovery."""
        self.discover()
        return list(self._items.values())
