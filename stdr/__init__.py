"""stdr: dynamic-scene reconstruction with deformable 3D Gaussian Splatting and STDR."""

__version__ = "0.1.0"


def source_checkout():
    """The source checkout this package runs from (a pathlib.Path: pyproject.toml beside the
    package), or None for an installed copy (a wheel in site-packages)."""
    from pathlib import Path
    root = Path(__file__).resolve().parents[1]
    return root if (root / "pyproject.toml").is_file() and (root / "stdr" / "__init__.py").is_file() else None
