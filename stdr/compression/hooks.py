"""The compact file's optional protocol: what a method tells the file about its tables.

A baseline's deformation module or a plug-in implements these methods only if the compact file
should store something of it other than every tensor as it is; the file reads them through the
functions below, which give the defaults for a method that implements none.

* `CompactColumns.compact_columns(params)` (a deformation module): per-Gaussian tables that a
  trained model's renders read only at some columns of each row, {key: column indices [N, K]}
  (SP-GS's association logits at each Gaussian's K nearest superpoints). Default: none.
* `CompactPlugin.compact_form(params, state, step, derive)` (a plug-in): its part of the file, a
  `CompactForm`. Default: its state as it is.
* `check_compact_spec(pcfg, spec)` (a classmethod of a plug-in, read by `check_plugin_spec`): before training, raise a
  ValueError when the spec asks this plug-in for a form its config cannot give, so a run fails at
  its start and not after training. Default: nothing to check.
* `compact_fallback` (a class attribute of a plug-in, read by `fallback_of`): {key: codec} for each derivable table, the
  codec used when the run's config does not allow the `derived` form (`stdr-tool compact` applies
  the compact preset to older runs that way). Default: none.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

from torch import Tensor


@dataclass
class CompactForm:
    """A plug-in's part of a compact file (CompactPlugin.compact_form)."""

    #: per-Gaussian tables a trained model reads only through an activation to [0, 1] and also
    #: accepts in 8 bits (uint8 q for q / 255): {key: the activated values, float [N, ...]}. A lossy
    #: codec named for such a key encodes these values, and the file reads them back as uint8
    units: dict[str, Tensor] = field(default_factory=dict)
    #: the tables asked for in their `derived` form: {key: (the stored key, the values [N, D] of
    #: the fixed function through which a finished model reads the table)}; the plug-in reads them
    #: back from the stored key
    derived: dict[str, tuple[str, Tensor]] = field(default_factory=dict)
    #: the plug-in's state_dict for the file, without what a render of the finished model does not
    #: read (training-only state, and what only the derivation needed)
    state: dict[str, Any] = field(default_factory=dict)


@runtime_checkable
class CompactColumns(Protocol):
    def compact_columns(self, params) -> dict[str, Tensor]: ...


@runtime_checkable
class CompactPlugin(Protocol):
    def compact_form(self, params, state: dict[str, Any], step: int, derive: set[str]) -> CompactForm: ...


def columns_of(deform, params) -> dict[str, Tensor]:
    """The column indices the compact file stores of `deform`'s tables ({} for a module that
    implements no `compact_columns`)."""
    return deform.compact_columns(params) if isinstance(deform, CompactColumns) else {}


def form_of(plugin, params, state: dict[str, Any], step: int, derive: set[str]) -> CompactForm:
    """`plugin`'s part of the compact file: its `compact_form`, else its state as it is."""
    if isinstance(plugin, CompactPlugin):
        return plugin.compact_form(params, state, step, derive)
    return CompactForm(state=state)


def check_plugin_spec(plugin_cls, pcfg, spec: dict) -> None:
    """The plug-in class's `check_compact_spec` of `spec` for its config node `pcfg`, if it has one."""
    check = getattr(plugin_cls, "check_compact_spec", None)
    if check is not None:
        check(pcfg, spec)


def fallback_of(plugin_cls) -> dict[str, str]:
    """The plug-in class's `compact_fallback` ({} if it names none)."""
    return dict(getattr(plugin_cls, "compact_fallback", None) or {})
