"""stdr: dynamic-scene reconstruction with deformable 3D Gaussian Splatting and STDR."""

__version__ = "0.1.0"

import os as _os

# Intel MKL's strict reproducibility mode: its matrix products (the deformation networks' weight
# gradients sum over every Gaussian) then give the same bits on any thread count, so a run's
# numbers do not depend on the machine's cores (docs/performance.md, "Determinism"; measured
# cost: ~7 % of such a product). MKL reads it at its first call, so it is set on import, before
# any training; a value you set yourself wins. Torch builds without MKL ignore it.
_os.environ.setdefault("MKL_CBWR", "AUTO,STRICT")


def user_cache():
    """stdr's folder in the user cache (a pathlib.Path): $XDG_CACHE_HOME/stdr, default
    ~/.cache/stdr. Installed copies keep their caches here (data, LPIPS weights, kernels)."""
    import os
    from pathlib import Path
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "stdr"


def source_checkout():
    """The source checkout this package runs from (a pathlib.Path: pyproject.toml beside the
    package), or None for an installed copy (a wheel in site-packages)."""
    from pathlib import Path
    root = Path(__file__).resolve().parents[1]
    return root if (root / "pyproject.toml").is_file() and (root / "stdr" / "__init__.py").is_file() else None
