"""Learning-rate schedules."""
from __future__ import annotations

import math


def exp_lr(step: int, lr_init: float, lr_final: float, max_steps: int) -> float:
    """Log-linear interpolation from lr_init (step 0) to lr_final (step >= max_steps), as in 3DGS."""
    if max_steps <= 0 or lr_init == lr_final:
        return lr_final
    s = min(max(step / max_steps, 0.0), 1.0)
    return math.exp(math.log(lr_init) * (1 - s) + math.log(lr_final) * s)
