"""Old module names that keep working after the renames of 2026-11-28 (CHANGELOG.md):
`stdr.deform` is `stdr.baselines`, `stdr.decouple` is `stdr.plugins.stdr`, `stdr.scene.*` is
`stdr.densify`, `stdr.gaussians`, `stdr.knn` and `stdr.io`, `stdr.train.adam` /
`stdr.train.schedule` are `stdr.train.optim`. Importing an old name works, gives the new module
itself (one module object: monkeypatching either name patches both) and warns once
(DeprecationWarning)."""
from __future__ import annotations

import importlib
import sys
import warnings


def alias(old: str, new: str, submodules: dict[str, str], same: bool = False) -> None:
    """Make every `old.<sub>` the module `submodules[sub]` in sys.modules, so that `import old.sub`
    and `from old.sub import x` find the new module, and warn that `old` moved to `new`. same: `old`
    itself becomes the module `new` (a package renamed as a whole)."""
    warnings.warn(f"{old} is now {new}: the old name will be removed in a later release", DeprecationWarning,
                  stacklevel=3)
    parent = sys.modules[old]
    for sub, target in submodules.items():
        mod = importlib.import_module(target)
        sys.modules[f"{old}.{sub}"] = mod
        setattr(parent, sub, mod)
    if same:
        sys.modules[old] = importlib.import_module(new)  # what `import old` returns once this body ends
