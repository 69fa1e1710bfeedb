"""stdr.train.optim: several fused Adams stepped at once equal each one's own step(), bit for bit."""
import copy

import pytest
import torch

from stdr.train.optim import adam_step, clear_grads
from stdr.syncs import OpCounter


def _setup(seed: int, fused: bool = True):
    g = torch.Generator().manual_seed(seed)
    shapes = {"means": (50, 3), "quats": (50, 4), "opacities": (50, 1), "sh0": (50, 1, 3)}
    params = {k: torch.randn(*s, generator=g).requires_grad_() for k, s in shapes.items()}
    lrs = {"means": 1.6e-4, "quats": 1e-3, "opacities": 5e-2, "sh0": 2.5e-3}
    opts = [torch.optim.Adam([{"params": [p], "lr": lrs[k], "name": k}], eps=1e-15, fused=fused)
            for k, p in params.items()]
    w1, w2 = torch.randn(8, 3, generator=g).requires_grad_(), torch.randn(8, generator=g).requires_grad_()
    w3 = torch.randn(3, 8, generator=g).requires_grad_()
    net = torch.optim.Adam([{"params": [w1, w2], "lr": 8e-4}, {"params": [w3], "lr": 2e-4, "weight_decay": 0.1}],
                           eps=1e-15, fused=fused)
    return params, opts, [w1, w2, w3], net


def _grads(params, net_params, step, skip=()):
    g = torch.Generator().manual_seed(100 + step)
    for k, p in params.items():
        p.grad = None if k in skip else torch.randn(p.shape, generator=g)
    for p in net_params:
        p.grad = torch.randn(p.shape, generator=g)


def _state(params, opts, net_params, net):
    out = [p.detach().clone() for p in [*params.values(), *net_params]]
    for o in [*opts, net]:
        for s in o.state.values():
            out += [s[k].clone() for k in sorted(s)]
    return out


@pytest.mark.parametrize("fused", [True, False])
def test_adam_step_equals_each_optimizers_step(fused):
    a = _setup(0, fused)
    b = copy.deepcopy(a)
    flags = [0.0, 0.0, 1.0, 0.0, 1.0, 0.0]  # 1: fused Adam skips the step (found_inf)
    for step, f in enumerate(flags):
        skip = ("quats",) if step == 0 else ()  # a parameter without a gradient gets no update and no state
        found = torch.tensor(f) if fused else None
        _grads(a[0], a[2], step, skip)
        _grads(b[0], b[2], step, skip)
        for o in [*a[1], a[3]]:
            o.found_inf = found
            o.step()
            o.zero_grad(set_to_none=True)
        adam_step([*b[1], b[3]], found)
        clear_grads([*b[1], b[3]])
        sa, sb = _state(a[0], a[1], a[2], a[3]), _state(b[0], b[1], b[2], b[3])
        assert len(sa) == len(sb)
        for x, y in zip(sa, sb):
            assert torch.equal(x, y)
        assert all(p.grad is None for p in [*b[0].values(), *b[2]])
    # fused: the two flagged steps did not count, 4 of 6 applied (3 for quats, without a gradient at
    # first); unfused optimizers take no flag (the guard then reads its check every step)
    applied = 4 if fused else 6
    assert int(b[1][0].state[b[0]["means"]]["step"]) == applied
    assert int(b[1][1].state[b[0]["quats"]]["step"]) == applied - 1
    # and the parameters moved
    assert not torch.equal(b[0]["means"], _setup(0, fused)[0]["means"])


def test_adam_step_launches_fewer_operators():
    a = _setup(1)
    b = copy.deepcopy(a)
    found = torch.tensor(0.0)
    for tr in (a, b):  # the first step creates the state
        _grads(tr[0], tr[2], 0)
        adam_step([*tr[1], tr[3]], found)
    _grads(a[0], a[2], 1)
    _grads(b[0], b[2], 1)
    with OpCounter() as each:
        for o in [*a[1], a[3]]:
            o.found_inf = found
            o.step()
            o.zero_grad(set_to_none=True)
    with OpCounter() as once:
        adam_step([*b[1], b[3]], found)
        clear_grads([*b[1], b[3]])
    # 5 optimizers, 6 parameter groups: one kernel per group, one increment and one decrement
    assert once.by_op["aten._fused_adam_"] == 6 and once.by_op["aten._foreach_add_"] == 1
    assert once.by_op["aten._foreach_sub_"] == 1 and once.ops == 8
    assert each.ops > 3 * once.ops
