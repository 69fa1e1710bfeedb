"""The compiled extension: its sources, its build and its loading, and the switch every compiled
form goes through.

One extension module per device kind, `cpu` (C++, vectorized, multi-threaded) and `cuda`, built
just in time on first use with `torch.utils.cpp_extension` into a cache keyed by the sources,
flags, torch version and CPU, or ahead of time with `stdr-build`. The CUDA one is built only where
torch has CUDA. The CPU one holds five kernel families and the CUDA one the first four
(csrc/cpu/ops_cpu.cpp lists them), each bound in Python beside its torch twin, which the tests pin
it to:

| family | bindings | torch twin |
|---|---|---|
| rasterizer (+ projection and SH) | stdr/render/compiled.py | stdr/render/reference.py, projection.py, sh.py |
| HexPlane sampling | stdr/baselines/fourdgs.py `hexplane_compiled` | `HexPlaneField.features_torch` |
| training loss | stdr/metrics.py `image_loss_compiled` | `image_loss` |
| guard's check | stdr/train/guard.py `nonfinite_flags_compiled`, `guard_update_compiled` | `nonfinite_flags`, `Guard.flag_step` |
| nearest points (CPU only) | stdr/knn.py `knn_direct` | `knn_direct_torch` (the same bits; CUDA runs it) |

Whether a `null` switch picks a compiled form on a device is one table, stdr.verified.VERIFIED,
read by `use_compiled`.
"""
from __future__ import annotations

import contextlib
import hashlib
import os
import platform
import sys
import threading
import time
import warnings
from pathlib import Path
from typing import Optional

import torch

from .verified import verified_on
from . import user_cache

CSRC = Path(__file__).resolve().parent / "csrc"
CPU_SOURCES = [CSRC / "cpu" / "ops_cpu.cpp"]
CUDA_SOURCES = [CSRC / "cuda" / "ops_cuda.cpp", CSRC / "cuda" / "kernels.cu"]
# every header under csrc/ is in the cache key: a cached module is loaded without asking the
# build tool, so a header the key missed could leave an edited kernel unbuilt
HEADERS = sorted(CSRC.rglob("*.h"))
PORTABLE_ENV = "STDR_PORTABLE_BUILD"  # =1: no -march=native (e.g. a cache shared by machines)

_lock = threading.Lock()
_modules: dict[str, object] = {}
_errors: dict[str, str] = {}
_observer = None  # callback(name, args, result) while `observe_calls` is open


class BuildError(RuntimeError):
    pass


def cache_root() -> Path:
    """Where compiled extensions live: $STDR_EXT_DIR, else the user cache's extensions folder
    (~/.cache/stdr/extensions; $XDG_CACHE_HOME moves it)."""
    env = os.environ.get("STDR_EXT_DIR")
    return Path(env) if env else user_cache() / "extensions"


def _cpu_id() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("flags"):
                return line
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _cpu_flags(native: bool) -> list[str]:
    # -fopenmp: ATen's parallel_for is inline OpenMP code, serial without it. The extension then
    # needs libgomp.so.1, which resolves to the copy torch has already loaded (same soname), so
    # torch and the rasterizer share one thread pool.
    flags = ["-O3", "-fopenmp", "-std=c++17"]
    if native:
        flags += ["-march=native", "-mprefer-vector-width=512"]
    return flags + os.environ.get("STDR_EXTRA_CFLAGS", "").split()


def _key(kind: str, sources: list[Path], flags: list[str]) -> str:
    h = hashlib.sha1()
    # torch's JIT loader rebuilds when a build directory was last built from sources at other
    # paths, so each checkout gets its own entry (no rebuild ping-pong between clones)
    h.update(str(CSRC).encode())
    for p in sources + HEADERS:
        if p.exists():
            h.update(p.read_bytes())
    h.update(" ".join(flags).encode())
    h.update(torch.__version__.encode())
    h.update(str(torch.version.cuda).encode())
    h.update(_cpu_id().encode())
    h.update(sys.version.encode())
    return f"stdr_ext_{kind}_{h.hexdigest()[:12]}"


STALE_LOCK_SECONDS = 900  # a build takes ~15-60 s on the CPU, a few minutes with nvcc


def clear_stale_lock(build_dir: Path, max_age: float = STALE_LOCK_SECONDS) -> bool:
    """torch's extension builder holds `build_dir/lock` while it compiles, and every other
    process waits for it to disappear, with no time limit. A build killed midway (Ctrl-C during
    the first run) leaves the file behind, and every later run would hang silently. A lock older
    than `max_age` seconds is removed with a warning; a younger one is announced (another
    process may be building right now). Returns True when a stale lock was removed."""
    lock = build_dir / "lock"
    try:
        age = time.time() - lock.stat().st_mtime
    except FileNotFoundError:
        return False
    if age > max_age:
        warnings.warn(f"removing {lock}: left {age / 60:.0f} min ago by a build that did not finish "
                      "(killed?); building again", RuntimeWarning, stacklevel=2)
        lock.unlink(missing_ok=True)
        return True
    print(f"[stdr] waiting for another process's build of the extension ({lock}, {age:.0f} s old); if no "
          "build is running, delete that file", file=sys.stderr, flush=True)
    return False


def _built_paths(name: str, build_dir: Path) -> tuple[Path, Path]:
    """(the module file, its stamp: the size and time of the file a successful load imported)."""
    return build_dir / f"{name}.so", build_dir / f"{name}.so.built"


def _stamp(so: Path) -> str:
    st = so.stat()
    return f"{st.st_size} {st.st_mtime_ns}\n"


def _load_built(name: str, build_dir: Path):
    """The module a finished build left in `build_dir`, imported without running the build tool,
    or None where there is none to trust. The folder's name is the key of every input (sources,
    headers, flags, torch, CPU, Python), so a module there is up to date once its build finished:
    the stamp beside it (size and time of the file a successful load imported) says so, and a
    link killed midway, which leaves a partial file (importing it kills the process), never has
    one. Asking ninja instead rebuilds it (~45 s, silently) whenever a process finds another ninja
    first on PATH than the one that built it (the system's and the pip package's logs differ)."""
    import importlib.util

    so, stamp = _built_paths(name, build_dir)
    try:
        if not stamp.is_file() or stamp.read_text() != _stamp(so):
            return None
        spec = importlib.util.spec_from_file_location(name, so)
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        return mod
    except Exception as e:  # e.g. a file another machine built into a shared cache
        warnings.warn(f"{so} does not load ({e}); asking the build tool", RuntimeWarning, stacklevel=3)
        return None


def _mark_built(name: str, build_dir: Path) -> None:
    so, stamp = _built_paths(name, build_dir)
    tmp = stamp.with_name(f"{stamp.name}.{os.getpid()}")
    # a cache this user may read but not write stays unstamped: each load asks the build tool
    with contextlib.suppress(OSError):
        tmp.write_text(_stamp(so))
        os.replace(tmp, stamp)
    with contextlib.suppress(OSError):
        tmp.unlink(missing_ok=True)


def _compile(kind: str, verbose: bool = False):
    import shutil

    from torch.utils import cpp_extension

    # the `ninja` pip package installs next to the interpreter, which may not be on PATH
    bindir = str(Path(sys.executable).parent)
    if shutil.which("ninja") is None and (Path(bindir) / "ninja").exists():
        os.environ["PATH"] = bindir + os.pathsep + os.environ.get("PATH", "")

    native = os.environ.get(PORTABLE_ENV, "0") != "1" and platform.machine() in ("x86_64", "AMD64")
    attempts = [native, False] if native else [False]
    last_err: Optional[BaseException] = None
    for use_native in attempts:
        cflags = _cpu_flags(use_native)
        if kind == "cpu":
            sources, extra = CPU_SOURCES, {}
        else:
            sources = CUDA_SOURCES
            extra = {"extra_cuda_cflags": ["-O3", "--use_fast_math", "-std=c++17"],
                     "with_cuda": True}
        name = _key(kind, sources, cflags + extra.get("extra_cuda_cflags", []))
        build_dir = cache_root() / name
        build_dir.mkdir(parents=True, exist_ok=True)
        clear_stale_lock(build_dir)
        cached = any(build_dir.glob(f"{name}*.so"))
        if cached and not (build_dir / "lock").exists():
            mod = _load_built(name, build_dir)
            if mod is not None:
                return mod
        if not cached:
            print(f"[stdr] compiling the {kind.upper()} kernels into {build_dir} "
                  f"(first use only; ~20-60 s)...", file=sys.stderr, flush=True)
        t0 = time.perf_counter()
        try:
            mod = cpp_extension.load(name=name, sources=[str(s) for s in sources],
                                     extra_cflags=cflags, extra_ldflags=["-fopenmp"],
                                     build_directory=str(build_dir),
                                     verbose=verbose, **extra)
        except Exception as e:  # compiler missing, unsupported flag, ...
            last_err = e
            continue
        if not cached:
            print(f"[stdr] {kind.upper()} kernels built in {time.perf_counter() - t0:.0f} s",
                  file=sys.stderr, flush=True)
        _mark_built(name, build_dir)
        return mod
    raise BuildError(f"could not build the {kind} extension: {last_err}")


def load_extension(kind: str, verbose: bool = False):
    """The compiled module for `kind` ('cpu' or 'cuda'), building it if needed (cached)."""
    if kind not in ("cpu", "cuda"):
        raise ValueError(f"unknown compiled backend {kind!r}")
    with _lock:
        if kind in _modules:
            return _observed(_modules[kind])
        if kind in _errors:
            raise BuildError(_errors[kind])
        if kind == "cuda" and not (torch.cuda.is_available() and torch.version.cuda):
            _errors[kind] = "torch has no CUDA here; the CUDA extension is not built"
            raise BuildError(_errors[kind])
        try:
            _modules[kind] = _compile(kind, verbose=verbose)
        except BuildError as e:
            _errors[kind] = str(e)
            raise
        return _observed(_modules[kind])


class _Observed:
    """A compiled module whose every function call is also reported to a callback."""

    def __init__(self, module, callback):
        self._module, self._callback = module, callback

    def __getattr__(self, name: str):
        f = getattr(self._module, name)
        if not callable(f):
            return f

        def call(*args, **kwargs):
            out = f(*args, **kwargs)
            if _observer is self._callback:  # a graph kept past the observation reports nothing
                self._callback(name, (*args, *kwargs.values()), out)
            return out
        return call


def _observed(module):
    return module if _observer is None else _Observed(module, _observer)


@contextlib.contextmanager
def observe_calls(callback):
    """While open, the modules `load_extension` returns report every call of theirs as
    callback(function name, its arguments, its result), after the call (`stdr-tool bench-train`
    counts the bytes the compiled kernels read and write). One observer at a time, not for training."""
    global _observer
    if _observer is not None:
        raise RuntimeError("observe_calls is already open")
    _observer = callback
    try:
        yield
    finally:
        _observer = None


def available(kind: str) -> bool:
    try:
        load_extension(kind)
        return True
    except BuildError:
        return False


def build_error(kind: str) -> Optional[str]:
    return _errors.get(kind)


def use_compiled(key: str, setting: Optional[bool], kind: str, supported: bool = True,
                 unsupported: str = "") -> bool:
    """A `<key>: null | true | false` switch between a compiled kernel on `kind` ('cpu', 'cuda')
    and its torch twin: false = the twin; null = the kernel where it has been verified (`kind` in
    stdr.verified.VERIFIED[key]), the inputs are `supported` and the extension builds; true = the
    kernel, or an error that names the key and says why not (`unsupported`: what the kernel does
    not take)."""
    if setting is False:
        return False
    if setting is None:
        return supported and kind in verified_on(key) and available(kind)
    if not supported:
        raise ValueError(f"{key}=true: {unsupported}; set {key}=null (or false) to use the torch ops")
    if not available(kind):
        raise RuntimeError(f"{key}=true, but the {kind} extension could not be built: {build_error(kind)}; "
                           f"set {key}=null (or false)")
    return True
