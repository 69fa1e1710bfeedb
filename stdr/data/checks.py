"""What every loader checks in the cameras it reads, before anything trains on them.

A NaN in one pose used to load silently and train until the guard gave up with advice about
learning rates; a reflected or scaled "rotation" renders a mirrored or squashed scene. Each check
raises a ValueError that names the file, the frame and the value, so the fix is in the data.
"""
from __future__ import annotations

import math
import sys
from typing import Sequence

import numpy as np

from ..errors import BadInput, MissingKey

#: |R R^T - I| above this is not a rotation (float32 poses written as JSON are ~1e-6 off)
ROTATION_TOL = 1e-3


def _values(x) -> np.ndarray:
    try:
        return np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        return np.asarray([np.nan])


def check_pose(R, position, where: str, what: str = "pose") -> None:
    """R: 3x3 rotation (camera-to-world or world-to-camera: orthonormal either way, det +1);
    position: the camera centre or translation (3 values). `where` names the file and frame."""
    R, p = _values(R), _values(position)
    if R.shape != (3, 3):
        raise BadInput(f"{where}: the {what}'s rotation must be 3x3, got shape {R.shape}")
    if p.shape != (3,):
        raise BadInput(f"{where}: the {what}'s position must have 3 values, got shape {p.shape}")
    if not (np.isfinite(R).all() and np.isfinite(p).all()):
        bad = [f"{v}" for v in np.concatenate([R.ravel(), p]) if not np.isfinite(v)]
        raise BadInput(f"{where}: the {what} has non-finite values ({', '.join(bad[:3])}); "
                         "fix or drop this frame")
    err = float(np.abs(R @ R.T - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if err > ROTATION_TOL or det <= 0:
        kind = "a reflection (det < 0)" if det <= 0 and err <= ROTATION_TOL else "not orthonormal"
        raise BadInput(f"{where}: the {what}'s rotation is {kind} (|R R^T - I| = {err:.1e}, det = {det:.3f}); "
                         f"a camera rotation is orthonormal within {ROTATION_TOL:g} with det +1 (scale or "
                         "mirroring baked into the matrix? fix the export)")


def check_intrinsics(fx: float, fy: float, cx: float, cy: float, width: int, height: int, where: str) -> None:
    """Positive, finite focal lengths and a principal point inside the image it belongs to."""
    vals = {"fx": fx, "fy": fy, "cx": cx, "cy": cy}
    for k, v in vals.items():
        if not isinstance(v, (int, float)) or not math.isfinite(float(v)):
            raise BadInput(f"{where}: {k}={v!r} is not a finite number")
    if not (int(width) >= 1 and int(height) >= 1):
        raise BadInput(f"{where}: image size {width}x{height} must be positive")
    if fx <= 0 or fy <= 0:
        raise BadInput(f"{where}: focal lengths must be positive, got fx={fx:g}, fy={fy:g}")
    if not (0.0 <= cx <= width and 0.0 <= cy <= height):
        raise BadInput(f"{where}: principal point ({cx:g}, {cy:g}) lies outside the {width}x{height} image it "
                         "describes; do the intrinsics belong to images of another size?")


def check_time(t, where: str) -> float:
    """A frame's time as a float in [0, 1]."""
    try:
        v = float(t)
    except (TypeError, ValueError):
        raise BadInput(f"{where}: time={t!r} is not a number") from None
    if not 0.0 <= v <= 1.0:  # NaN fails this too
        raise BadInput(f"{where}: time={t} is outside [0, 1]")
    return v


def check_fov(angle, where: str, key: str) -> float:
    """A field of view in radians, in (0, pi)."""
    try:
        v = float(angle)
    except (TypeError, ValueError):
        raise BadInput(f"{where}: {key}={angle!r} is not a number") from None
    if not 0.0 < v < math.pi:  # NaN fails this too
        raise BadInput(f"{where}: {key}={angle} must be a field of view in radians, in (0, pi)")
    if not math.radians(FOV_PLAUSIBLE[0]) <= v <= math.radians(FOV_PLAUSIBLE[1]):
        print(f"[stdr] {where}: {key}={angle} rad ({math.degrees(v):.4g} degrees) is not a field of view a camera "
              f"has (outside {FOV_PLAUSIBLE[0]}-{FOV_PLAUSIBLE[1]} degrees): check the file (radians, horizontal)",
              file=sys.stderr, flush=True)
    return v


#: fields of view (degrees) outside which a camera is implausible: said once where it is read
FOV_PLAUSIBLE = (1.0, 170.0)


def finite_values(values: Sequence, where: str, what: str) -> np.ndarray:
    """values as float64, or an error naming what is not finite."""
    a = _values(values)
    if not np.isfinite(a).all():
        raise BadInput(f"{where}: {what} has non-finite values: {values!r}")
    return a


def need_key(d: dict, key: str, path, where: str = ""):
    """d[key], or a MissingKey naming the file `path` (and `where` in it)."""
    if not isinstance(d, dict) or key not in d:
        raise MissingKey(f"{path}: missing key {key!r}{where}")
    return d[key]


def numbers(value, where: str, key: str, shape: tuple = (), finite: bool = True) -> np.ndarray:
    """A field that must hold finite numbers of `shape` (() for one number; -1 in a shape: any
    length of at least 1), as float64, or a BadInput naming the file, the key and the value.
    finite=False leaves non-finite values to a later check (check_pose names them)."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise BadInput(f"{where}: {key}={value!r:.60} is not {_shape_words(shape)}") from None
    ok = a.ndim == len(shape) and all(s == -1 and d >= 1 or s == d for s, d in zip(shape, a.shape))
    if not ok or isinstance(value, (bool, str)):
        raise BadInput(f"{where}: {key}={value!r:.60} is not {_shape_words(shape)}")
    if finite and not np.isfinite(a).all():
        raise BadInput(f"{where}: {key}={value!r:.60} has non-finite values")
    return a


def _shape_words(shape: tuple) -> str:
    if shape == ():
        return "a number"
    if len(shape) == 1:
        return "a list of numbers" if shape[0] == -1 else f"a list of {shape[0]} numbers"
    return f"a {'x'.join(str(d) for d in shape)} matrix of numbers"
