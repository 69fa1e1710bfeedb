"""The conformance kit (stdr-tool check-baseline / check-plugin): every built-in passes it, and a
baseline that breaks one of its guarantees fails that check, named, with the fix."""
from __future__ import annotations

from dataclasses import dataclass, field

import pytest
import torch
from torch import nn

from stdr.baselines import BaselineConfig, Deformation, Deltas, register_baseline
from stdr.baselines.registry import unregister_baseline
from stdr.tools.conformance import CHECKS, main, run_kit


@pytest.mark.slow
@pytest.mark.parametrize("baseline", ["deform", "scgs", "spgs", "4dgs"])
def test_every_built_in_baseline_with_stdr_passes_the_kit(baseline, tmp_path):
    """Each built-in baseline with the built-in plug-in on: all six checks (the 60-step `learns`)."""
    lines = []
    res = run_kit(baseline, "stdr", quick=True, work=tmp_path, out=lines.append)
    assert set(res) == set(CHECKS) and len(lines) == len(CHECKS)
    assert all(status == "pass" for status, _ in res.values()), "\n".join(lines)


# ------------------------------------------------------------------ outside-style baselines
@dataclass
class SlideOptions:
    speed: float = 0.0


@dataclass
class SlideConfig(BaselineConfig):
    name: str = "slide"
    slide: SlideOptions = field(default_factory=SlideOptions)


class Slide(Deformation):
    """Every Gaussian slides along x with a learned speed times t, plus a head on the conditioning."""

    capabilities = frozenset({"conditioning"})
    zero_cond = True

    def __init__(self, speed: float = 0.0, cond_dim: int = 0):
        super().__init__()
        self.cond_dim = cond_dim
        self.speed = nn.Parameter(torch.tensor([speed, 0.0, 0.0]))
        self.cond_head = nn.Linear(cond_dim, 3) if cond_dim else None
        if self.cond_head is not None and self.zero_cond:
            nn.init.zeros_(self.cond_head.weight)
            nn.init.zeros_(self.cond_head.bias)

    @classmethod
    def config_kwargs(cls, b, cond_dim=0, train_times=None, seed=0, schedule=None):
        return {"speed": b.slide.speed, "cond_dim": cond_dim}

    def offset(self, params):
        return torch.zeros_like(params["means"])

    def forward(self, params, t, cond=None):
        dx = (self.speed * t).expand_as(params["means"]) + self.offset(params)
        if self.cond_head is not None:
            dx = dx + self.cond_head(cond)
        return Deltas(means=dx)


class SlideRandomCond(Slide):
    """Its conditioning head keeps PyTorch's random init: STDR moves the model from its first step."""

    zero_cond = False


class SlideFixedDevice(Slide):
    """Makes a tensor on torch's default device instead of the parameters' own."""

    def offset(self, params):
        return torch.zeros(params["means"].shape[0], 3)


@pytest.fixture
def slide():
    made = []

    def reg(cls):
        register_baseline("slide", cls, SlideConfig)
        made.append(cls)
    yield reg
    if made:
        unregister_baseline("slide")


@pytest.mark.slow
def test_an_outside_baseline_passes_and_the_command_exits_0(slide, capsys):
    slide(Slide)
    assert main(["slide", "--plugin", "stdr", "--quick", "--check", "identity", "device", "resume"]) == 0
    out = capsys.readouterr().out
    assert "3 of 3 checks passed" in out and "embedded_slide_stdr" in out


@pytest.mark.slow
@pytest.mark.parametrize("cls, check, said", [
    (SlideRandomCond, "identity", "start the module's cond columns at zero weight"),
    (SlideFixedDevice, "device", "meta"),
])
def test_a_baseline_that_breaks_a_guarantee_fails_that_check(slide, capsys, cls, check, said):
    slide(cls)
    assert main(["slide", "--plugin", "stdr", "--quick", "--check", check]) == 1
    out = capsys.readouterr().out
    line = next(ln for ln in out.splitlines() if f" {check} " in ln)
    assert "FAIL" in line and said in line, out
    assert f"0 of 1 checks passed; failed: {check}" in out


def test_a_name_that_is_not_registered_or_a_plugin_that_does_not_apply_is_one_line():
    with pytest.raises(SystemExit, match="'nope' is not a registered baseline"):
        run_kit("nope")
    with pytest.raises(SystemExit, match="'nope' is not a registered plug-in"):
        run_kit("deform", "nope")
