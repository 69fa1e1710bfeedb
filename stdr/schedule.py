"""One phase schedule: every step at which a component changes behaviour, resolved once.

Four components have stages: the loop's static warm-up (`baseline.warmup`: no deformation
before it), the baseline's own stages (SC-GS: node stage, node resampling and the detached
steps after it; SP-GS: superpoints placed when the warm-up ends), STDR's phases (mask warm-up,
regularized, frozen) and the densification window. `resolve_schedule(cfg)` computes them from
the config alone; the model and its components read their boundaries from the result, and
`stdr-train` prints it (also in `stdr-train --cfg job`, as the derived `schedule` node).

Collision rules, applied here and nowhere else:
* A baseline may declare *switch windows* [first, last] in which it rebuilds or detaches its
  network (SC-GS: node_stage_end to node_stage_end + main_warmup). STDR's freeze (where the
  separated field starts feeding the network) must not fall inside one. A freeze resolved by
  `stdr.phase_rule` moves to the midpoint between the end of STDR's warm-up and the window's
  start (never before the warm-up's end); an explicit `stdr.freeze_at` inside a window is an
  error.
* `stdr.freeze_at` resolving to 0 with the mask on is an error (the mask would freeze at its
  initial value); so is a freeze before STDR's warm-up ends.
* `baseline.warmup` or STDR's freeze at or after `optim.iterations` is a `NeverTrains` warning
  naming the key, repeated in the printed schedule (the deformation, or STDR's separated field,
  never trains in that run; not an error, since a run stopped early to be resumed longer is
  legitimate). Any other boundary there never fires; the schedule marks it "(never reached)".
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Any, Optional


@dataclass(frozen=True)
class Event:
    step: int
    key: str    # the config key or rule that sets the step
    what: str   # what happens from this step on


@dataclass
class Schedule:
    iterations: int
    static_warmup_end: int
    stdr_warmup_end: Optional[int] = None
    stdr_freeze_at: Optional[int] = None
    stdr_freeze_moved: Optional[str] = None
    events: list[Event] = field(default_factory=list)
    windows: list[tuple[str, int, int]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def sorted_events(self) -> list[Event]:
        return sorted(self.events, key=lambda e: e.step)

    def describe(self) -> str:
        """The schedule as lines for the run's log."""
        lines = [f"[stdr] schedule ({self.iterations} iterations):"]
        for e in self.sorted_events():
            late = "  (never reached)" if e.step >= self.iterations else ""
            lines.append(f"[stdr]   {e.step:>7}  {e.what}  [{e.key}]{late}")
        lines += [f"[stdr]   note: {n}" for n in self.notes]
        return "\n".join(lines)

    def as_dict(self) -> dict[str, Any]:
        """Plain values for the config's derived `schedule` node and for metrics."""
        return {"iterations": self.iterations, "static_warmup_end": self.static_warmup_end,
                "stdr_warmup_end": self.stdr_warmup_end, "stdr_freeze_at": self.stdr_freeze_at,
                "events": [f"{e.step}: {e.what} [{e.key}]" for e in self.sorted_events()],
                "notes": list(self.notes)}


def place_freeze(freeze_at: int, warmup_end: int, windows: list[tuple[str, int, int]],
                 explicit: bool) -> tuple[int, Optional[str]]:
    """STDR's freeze kept out of the baseline's switch windows (module docstring). Returns the
    step and, when it moved, 'old -> new: window' for the log."""
    for name, first, last in windows:
        if not first <= freeze_at <= last:
            continue
        if explicit:
            raise ValueError(f"stdr.freeze_at={freeze_at} falls in the {name} window [{first}, {last}]; "
                             f"choose a step outside it, or leave stdr.freeze_at=null to resolve it by rule")
        new = max(warmup_end, (warmup_end + first) // 2)
        return new, f"{freeze_at} -> {new}: {name} at [{first}, {last}]"
    return freeze_at, None


class NeverTrains(UserWarning):
    """A component of the run would never train (its phase starts at or after the last iteration)."""


def _never_trains(s: Schedule, msg: str) -> None:
    """A warning (and a note in the printed schedule), not an error: a run stopped early on
    purpose, to be resumed with more iterations (the tests' resume legs), is legitimate."""
    s.notes.append("WARNING: " + msg)
    warnings.warn(msg, NeverTrains, stacklevel=3)


def resolve_schedule(cfg) -> Schedule:
    """Every boundary of a run from its config (a Config or DictConfig)."""
    from .decouple.plugin import resolve_phases
    from .deform import get_baseline

    b = cfg.baseline
    total = int(cfg.optim.iterations)
    warm = int(b.warmup)
    s = Schedule(iterations=total, static_warmup_end=warm)
    if warm >= total:
        _never_trains(s, f"baseline.warmup={warm} is at or after the run's end (optim.iterations={total}): the "
                         "deformation never trains in this run. Lower baseline.warmup, or leave it unset in the "
                         "budget files (it then scales with the run)")
    s.events.append(Event(0, "start", "canonical Gaussians rendered without deformation"))
    s.events.append(Event(warm, "baseline.warmup", "static warm-up ends: the deformation network is on"))
    events, windows = get_baseline(b.name).module.stages(b)
    s.events += [Event(*e) for e in events]
    s.windows = list(windows)
    d = cfg.densify
    s.events.append(Event(int(d.refine_start), "densify.refine_start", "densification starts (clone, split, prune)"))
    s.events.append(Event(int(d.refine_stop), "densify.refine_stop", "densification stops"))
    if int(d.reset_every) > 0:
        s.notes.append(f"opacity reset every {int(d.reset_every)} steps while densifying (densify.reset_every)")
    if cfg.stdr.enabled:
        w, f = resolve_phases(cfg.stdr, warm, total)
        f, moved = place_freeze(f, w, s.windows, explicit=cfg.stdr.freeze_at is not None)
        if f >= total:
            _never_trains(s, f"STDR's freeze resolves to step {f}, at or after the run's end (optim.iterations="
                             f"{total}): the mask never freezes and the separated field never feeds the network "
                             "in this run. Set stdr.freeze_at (or stdr.warmup_end) below the end, or use "
                             "stdr.phase_rule=fraction")
        s.stdr_warmup_end, s.stdr_freeze_at, s.stdr_freeze_moved = w, f, moved
        held = "opacity frozen" if cfg.stdr.freeze_opacity else "opacity trains"
        s.events.append(Event(0, "stdr", f"STDR mask warm-up ({held}), L_temp and L_spatial on"))
        s.events.append(Event(w, "stdr.warmup_end", "STDR warm-up ends" + (
            ": opacity trains again, mask still regularized" if cfg.stdr.freeze_opacity else
            " (no change: stdr.freeze_opacity=false)")))
        s.events.append(Event(f, "stdr.freeze_at" + (" (moved)" if moved else ""),
                              "STDR mask frozen, regularizers off, separated field feeds the network"))
        if moved:
            s.notes.append(f"STDR freeze moved {moved}")
    return s
