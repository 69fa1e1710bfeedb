"""One phase schedule: every step at which a component changes behaviour, resolved once.

Four components have stages: the loop's static warm-up (`baseline.warmup`: no deformation
before it), the baseline's own stages (SC-GS: node stage, node resampling and the detached
steps after it; SP-GS: superpoints placed when the warm-up ends), each enabled plug-in's phases
(`Plugin.stages`: a mask's warm-up and freeze, say) and the densification
window. `build_schedule` puts them together by the rules below, and `stdr.store.resolve_schedule(cfg)`
asks each component of a config for its stages and calls it: from the config alone; the model and its
components read their boundaries from the result, and `stdr-train` prints it (also in
`stdr-train --cfg job`, as the derived `schedule` node).

Collision rules:
* A baseline may declare *switch windows* [first, last] in which it rebuilds or detaches its
  network (SC-GS: node_stage_end to node_stage_end + main_warmup). A plug-in boundary that must
  not fall inside one (where a plug-in's network starts feeding the deformation) goes through
  `keep_out_of_windows`: resolved by rule, it moves before the window; set explicitly inside
  one, it is an error naming the key.
* `baseline.warmup` (or a plug-in phase that starts training something) at or after
  `optim.iterations` is a `NeverTrains` error naming the key: that component would never train.
  A run stopped early on purpose keeps its `optim.iterations` and sets `train.stop_at`. Any
  other boundary there never fires; the schedule marks it "(never reached)".
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Optional

from .errors import ConfigError


@dataclass(frozen=True)
class Event:
    step: int
    key: str    # the config key or rule that sets the step
    what: str   # what happens from this step on


@dataclass
class Schedule:
    iterations: int
    static_warmup_end: int
    # each enabled plug-in's resolved values (Plugin.stages), e.g. {"<name>": {"freeze_at": 1000, ...}}
    plugins: dict[str, dict[str, Any]] = field(default_factory=dict)
    events: list[Event] = field(default_factory=list)
    windows: list[tuple[str, int, int]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    prune_steps: list[int] = field(default_factory=list)  # contribution pruning (prune.at), empty when off

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

    def never_trains(self, msg: str) -> None:
        """A component would never train in this run: a NeverTrains error (msg names the key).
        To stop a run early on purpose and resume it, keep optim.iterations and set train.stop_at."""
        raise NeverTrains(msg + " (to stop early and resume later, keep optim.iterations and set train.stop_at)")

    def as_dict(self) -> dict[str, Any]:
        """Plain values for the config's derived `schedule` node and for metrics."""
        return {"iterations": self.iterations, "static_warmup_end": self.static_warmup_end,
                "prune_steps": list(self.prune_steps),
                **{f"{name}_{k}": v for name, vals in self.plugins.items() for k, v in vals.items()},
                "events": [f"{e.step}: {e.what} [{e.key}]" for e in self.sorted_events()],
                "notes": list(self.notes)}


def keep_out_of_windows(step: int, floor: int, windows: list[tuple[str, int, int]], key: str,
                       explicit: bool) -> tuple[int, Optional[str]]:
    """A plug-in's phase boundary kept out of the baseline's switch windows (module docstring):
    one resolved by rule moves to the midpoint between `floor` and the window's start (never
    before `floor`); one set explicitly (`key`) inside a window is an error. Returns the step
    and, when it moved, 'old -> new: window' for the log."""
    for name, first, last in windows:
        if not first <= step <= last:
            continue
        if explicit:
            raise ValueError(f"{key}={step} falls in the {name} window [{first}, {last}]; "
                             f"choose a step outside it, or leave {key}=null to resolve it by rule")
        new = max(floor, (floor + first) // 2)
        return new, f"{step} -> {new}: {name} at [{first}, {last}]"
    return step, None


def build_schedule(iterations: int, warmup: int, baseline: tuple[list, list], strategy: tuple[list, list],
                   prune_steps: Optional[list[int]], prune_share: float,
                   plugins: list[tuple[str, Callable[["Schedule"], dict]]]) -> "Schedule":
    """A run's schedule from its components' stages: `baseline` (events, switch windows) of the
    baseline's module, `strategy` (events, notes) of the densification strategy, the contribution
    pruning's steps (None: a config without the node), and each enabled plug-in's `(name,
    stages(schedule) -> values)`, called last so that its phases see the windows. Events are
    `(step, key, what)` tuples."""
    s = Schedule(iterations=iterations, static_warmup_end=warmup)
    if warmup >= iterations:
        s.never_trains(f"baseline.warmup={warmup} is at or after the run's end (optim.iterations={iterations}): the "
                       "deformation never trains in this run. Lower baseline.warmup, or leave it unset in the "
                       "budget files (it then scales with the run)")
    s.events.append(Event(0, "start", "canonical Gaussians rendered without deformation"))
    s.events.append(Event(warmup, "baseline.warmup", "static warm-up ends: the deformation network is on"))
    events, windows = baseline
    s.events += [Event(*e) for e in events]
    s.windows = list(windows)
    events, notes = strategy
    s.events += [Event(*e) for e in events]
    s.notes += notes
    if prune_steps is not None:
        s.prune_steps = list(prune_steps)
        s.events += [Event(k, "prune.at", f"contribution pruning: the {prune_share:.0%} least "
                                          "significant Gaussians removed") for k in s.prune_steps]
    for name, stages in plugins:  # their phases, kept out of the windows above
        s.plugins[name] = dict(stages(s))
    return s


class NeverTrains(ConfigError):
    """A component of the run would never train (its phase starts at or after the last iteration)."""
