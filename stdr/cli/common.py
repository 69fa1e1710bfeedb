"""Shared pieces of the Hydra entry points."""
from __future__ import annotations

import errno
import os
from pathlib import Path

from ..store import compose_config
from ..store import typed_schema
from ..validate import schema_keys, unknown_key_hint
from ..errors import ConfigError, reported


def use_fast_allocator_hint() -> None:
    """Say once how to get the measured 2x CPU speed-up from tcmalloc when it is not in use."""
    lib = "/usr/lib/x86_64-linux-gnu/libtcmalloc_minimal.so.4"
    if "tcmalloc" not in os.environ.get("LD_PRELOAD", "") and Path(lib).is_file():
        print(f"[stdr] hint: CPU training runs faster with LD_PRELOAD={lib} (scripts/run.sh sets it)")


def reproducible_blas() -> None:
    """oneMKL's documented conditions for reproducible results, unless the user chose otherwise
    (MKL_CBWR, MKL_DYNAMIC set):
    * conditional numerical reproducibility on, in its strict form: MKL_CBWR=AUTO,STRICT, set when
      the package is imported (stdr/__init__.py), before MKL's first call. Without CNR (CNR:OFF)
      oneMKL documents that results may differ from run to run with the inputs' memory alignment;
      without STRICT a GEMM's sums still differ with the thread count (measured: the weight
      gradient of a [20000, 90] x [20000, 256] product differs between 1 and 2 threads);
    * a fixed thread count: MKL's dynamic threading off. It is on by default while torch's thread
      count is left alone (MKL_VERBOSE: Dyn:1), and then MKL may run a call on fewer threads than
      asked, while a GEMM's sums differ between 1 and 2 threads. torch.set_num_threads turns it
      off (MKL reads MKL_DYNAMIC when it loads, before this can set it), so the count torch
      already uses is set again; MKL_DYNAMIC=FALSE is then exported for child processes and
      recorded in metrics.json (conventions).
    docs/performance.md, "Determinism", says what they cost."""
    if "MKL_DYNAMIC" not in os.environ:
        import torch
        torch.set_num_threads(torch.get_num_threads())
        os.environ["MKL_DYNAMIC"] = "FALSE"


def _override_problem(e: Exception, overrides: list[str], config_name: str) -> str:
    """Hydra's composition error as one sentence naming the override and what is allowed."""
    import difflib
    import re
    text = str(e)
    m = re.search(r"Could not find '([^']+)/([^']+)'", text)
    if m:  # Hydra lists the group's options, one a line, up to the search path
        listing = text.partition("Available options in")[2].partition("Config search path")[0]
        opts = [ln.strip() for ln in listing.splitlines()[1:] if ln.strip()]
        near = difflib.get_close_matches(m.group(2), opts, n=1, cutoff=0.7)
        if near:
            return f"{m.group(1)}={m.group(2)}: no such option; did you mean {m.group(1)}={near[0]}?"
        return f"{m.group(1)}={m.group(2)}: no such option" + (f"; the options are {', '.join(opts)}" if opts else "")
    m = re.search(r"Could not override '([^']+)'", text)
    if m and config_name == "train":  # a key the config lacks (Hydra would suggest '+', which adds it unchecked)
        from omegaconf import OmegaConf

        key = m.group(1)
        base = compose_config([o for o in overrides if not o.lstrip("+~").startswith(key + "=")], config_name)
        parent = OmegaConf.select(base, key.rpartition(".")[0]) if "." in key else None
        if OmegaConf.is_dict(parent) and OmegaConf.get_type(parent) is dict:  # a map of the user's own entries
            given = next((o for o in overrides if o.startswith(key + "=")), key + "=VALUE")
            return (f"{key}: {key.rpartition('.')[0]} has no entry '{key.rpartition('.')[2]}' yet; "
                    f"a new entry takes a '+': +{given}")
        known = list(schema_keys(typed_schema(OmegaConf.to_container(base, resolve=False))))
        return f"unknown config key {key}: {unknown_key_hint(key, known)}"
    if m:
        return f"unknown config key {m.group(1)}"
    first = text.strip().splitlines()[0] if text.strip() else type(e).__name__
    first = first.removeprefix("Error merging override ")
    cause = e.__cause__
    if cause is not None and str(cause).strip():
        first += ": " + str(cause).strip().splitlines()[0]
    rest = [ln.strip() for ln in text.strip().splitlines()[1:] if ln.strip()]
    return " ".join([first, *rest[:3]])


def check_overrides(prog: str, argv: list[str], config_name: str = "train") -> None:
    """Compose the config a command line asks for before Hydra runs it, so that a bad override
    (a key the config lacks, a value of the wrong type, an option that does not exist) ends in one
    line and exit code 2, like every other user error (stdr.errors.reported). Command lines with
    Hydra's own flags (--cfg, --help, -m, ...) are left to Hydra."""
    if any(a.startswith("-") for a in argv):
        return
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    with reported(prog):
        try:
            compose_config(list(argv), config_name)
        except (HydraException, OmegaConfBaseException) as e:
            raise ConfigError(_override_problem(e, list(argv), config_name)) from None
        except OSError as e:  # Hydra looks an override up as a config file: a key too long for a file name
            if e.errno != errno.ENAMETOOLONG:
                raise
            long = max(argv, key=len)
            raise ConfigError(f"{long[:60]}... ({len(long)} characters): no such key or option in the config; "
                              f"`{prog} --help` lists them") from None


def run_hydra_app(prog: str, app) -> None:
    """Run a Hydra app (`app()`, a @hydra.main function) so that an I/O fault of Hydra's own
    writes (the run folder, .hydra/, the job's log file on a read-only or full disk) is one line
    naming the path, as the app's own are (stdr.errors.reported): Hydra prints every exception as
    a traceback unless HYDRA_FULL_ERROR lets it through to here. Other errors keep their
    traceback (a bug)."""
    os.environ.setdefault("HYDRA_FULL_ERROR", "1")
    with reported(prog):
        app()
