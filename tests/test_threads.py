"""The same numbers on any core count: the compiled rasterizer, stdr.ops.sigmoid, oneMKL's products
(MKL_CBWR=AUTO,STRICT, set on import) and a short training run give the same bits with 1, 2 and 4
threads (docs/performance.md, "Determinism")."""
import os

import pytest
import torch

from stdr.ops import BatchNorm1d, sigmoid
from stdr import extension
from stdr.render import compiled, rasterize
from stdr.render.projection import project_gaussians

from helpers import look_at_camera, random_gaussians

THREADS = (1, 2, 4)


@pytest.fixture
def restore_threads():
    n = torch.get_num_threads()
    yield
    torch.set_num_threads(n)


def _each_thread_count(fn):
    out = {}
    for n in THREADS:
        torch.set_num_threads(n)
        out[n] = fn()
    return out


def _assert_same(results: dict, what: str):
    first = results[THREADS[0]]
    for n in THREADS[1:]:
        for i, (a, b) in enumerate(zip(first, results[n])):
            assert torch.equal(a, b), f"{what}: output {i} differs between {THREADS[0]} and {n} threads"


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_compiled_rasterizer_gives_the_same_bits_on_any_thread_count(restore_threads, dtype):
    """Forward (image, transmittance), backward (all four input gradients) and the contribution
    score: each per-slot partial sum covers a fixed set of tiles (REDUCE_SLOTS), whatever the
    number of threads that run the slots."""
    if not extension.available("cpu"):
        pytest.skip("the CPU extension cannot be built here")
    cam = look_at_camera((2.5, 0.3, 0.8), width=97, height=75, dtype=dtype)
    means, quats, scales, opac, colors = random_gaussians(3000, seed=7, dtype=dtype)
    p = project_gaussians(means, quats, scales, opac, cam)
    feats = torch.cat([colors, p.depths[:, None]], -1)
    g = torch.Generator().manual_seed(1)
    w = torch.randn(75, 97, 4, generator=g, dtype=dtype)

    def run():
        xs = [x.detach().clone().requires_grad_(True) for x in (p.means2d, p.conics, p.opacities, feats)]
        acc, T = rasterize(*xs, p.depths, p.radii, 97, 75, tile_size=8, backend="cpu")
        ((acc * w).sum() + (T * w[..., 0]).sum()).backward()
        score = compiled.contribution_compiled(p.means2d, p.conics, p.opacities, p.depths, p.radii, 97, 75, 8)
        return (acc.detach(), T.detach(), *[x.grad for x in xs], score)

    res = _each_thread_count(run)
    _assert_same(res, "rasterizer")
    assert float(res[1][2].abs().sum()) > 0 and float(res[1][-1].sum()) > 0  # gradients and scores exist


def test_sigmoid_gives_the_same_bits_on_any_thread_count_and_matches_torch(restore_threads):
    x = torch.randn(1500, 40, generator=torch.Generator().manual_seed(0)) * 6
    g = torch.randn(1500, 40, generator=torch.Generator().manual_seed(1))

    def run():
        xx = x.clone().requires_grad_(True)
        y = sigmoid(xx)
        y.backward(g)
        return y.detach(), xx.grad

    res = _each_thread_count(run)
    _assert_same(res, "sigmoid")
    y, gx = res[1]
    ref = torch.sigmoid(x)
    assert (y - ref).abs().max() <= 2.5e-7  # a few float32 ulps of values in (0, 1)
    s64 = torch.sigmoid(x.double())
    # y (1 - y) g with y within a few ulps of the truth: |error| <= ~3e-7 |g| (as torch.sigmoid's backward)
    assert ((gx.double() - g.double() * s64 * (1 - s64)).abs() <= 3e-7 * g.double().abs() + 1e-12).all()
    ends = sigmoid(torch.tensor([-float("inf"), -200.0, 0.0, 200.0, float("inf"), float("nan")]))
    assert ends[:5].tolist() == [0.0, 0.0, 0.5, 1.0, 1.0] and ends[5].isnan()
    x64 = torch.randn(1000, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(sigmoid, (x64[:20].detach().requires_grad_(True),))
    assert torch.allclose(sigmoid(x64), torch.sigmoid(x64), rtol=1e-15, atol=1e-16)


def _seeded_batch_norm(cls):
    """A 64-channel batch norm of class `cls` with seeded, non-trivial weight and bias."""
    torch.manual_seed(0)
    bn = cls(64)
    with torch.no_grad():
        bn.weight.uniform_(0.5, 1.5)
        bn.bias.uniform_(-1, 1)
    return bn


def test_batch_norm_gives_the_same_bits_on_any_thread_count_and_matches_torch(restore_threads):
    """STDR's separated field normalizes each step's Gaussians with it: a drop-in nn.BatchNorm1d
    (same state dict), whose training statistics do not split by thread."""
    g = torch.Generator().manual_seed(0)
    x, gy = torch.randn(4725, 64, generator=g) * 3 + 1, torch.randn(4725, 64, generator=g)

    def run(cls):
        bn = _seeded_batch_norm(cls)
        xx = x.clone().requires_grad_(True)
        y = bn(xx)
        y.backward(gy)
        bn(x * 0.5)  # a second batch: the running statistics' update again
        return y.detach(), xx.grad, bn.weight.grad, bn.bias.grad, bn.running_mean, bn.running_var, bn.num_batches_tracked

    res = _each_thread_count(lambda: run(BatchNorm1d))
    _assert_same(res, "BatchNorm1d")
    ref = run(torch.nn.BatchNorm1d)
    for i, (a, b) in enumerate(zip(res[1], ref)):
        assert torch.allclose(a.double(), b.double(), rtol=1e-4, atol=1e-5), i
    assert set(BatchNorm1d(8).state_dict()) == set(torch.nn.BatchNorm1d(8).state_dict())
    bn = BatchNorm1d(64).eval()
    assert torch.equal(bn(x), torch.nn.BatchNorm1d(64).eval()(x))  # evaluation: torch's own form


def test_norm_relu_dropout_gives_the_same_bits_on_any_thread_count(restore_threads):
    """The bf16 field's batch norm, ReLU and dropout in one function: its statistics, its dropout
    draws and its backward."""
    from stdr.ops import norm_relu_dropout
    g = torch.Generator().manual_seed(0)
    x, gy = torch.randn(20000, 64, generator=g) * 3 + 1, torch.randn(20000, 64, generator=g)

    def run():
        bn = _seeded_batch_norm(BatchNorm1d)
        xx = x.clone().requires_grad_(True)
        y = norm_relu_dropout(xx, bn, 0.1)
        y.backward(gy)
        return y.detach(), xx.grad, bn.weight.grad, bn.bias.grad, bn.running_mean, bn.running_var

    _assert_same(_each_thread_count(run), "norm_relu_dropout")


def test_mkl_products_sum_alike_on_any_thread_count(restore_threads):
    """A weight gradient sums over every Gaussian (K = 20000): without oneMKL's strict CNR mode
    its sums split by thread count."""
    if "blas_info=mkl" not in torch.__config__.show().lower():
        pytest.skip("this torch does not use MKL for BLAS")
    assert os.environ.get("MKL_CBWR") == "AUTO,STRICT"  # set by `import stdr` unless the user set it
    g = torch.Generator().manual_seed(0)
    a, b = torch.randn(20000, 90, generator=g), torch.randn(20000, 256, generator=g)
    _assert_same(_each_thread_count(lambda: (a.t() @ b,)), "a.t() @ b")


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_a_short_stdr_run_trains_to_the_same_bits_on_one_and_two_threads(tmp_path, restore_threads, precision):
    """deform+STDR through densification, an opacity reset and STDR's regularized phase (its
    temporal loss takes the sigmoid of the whole mask), on 1 and 2 threads; the deformation network
    in fp32 and in bf16 (on a CPU with bf16 matrix instructions, where baseline.precision=auto picks
    it: elsewhere bf16 is emulated, never a default, and not claimed thread-invariant)."""
    from stdr.device import cpu_bf16_flags
    from stdr.testing import tiny_config
    from stdr.tools import identity_check as ic
    from stdr.train.trainer import Trainer

    if precision == "bf16" and not cpu_bf16_flags():
        pytest.skip("this CPU has no AVX512-BF16 or AMX: bf16 is emulated here and never the default")
    sched = [s for s in ic.SCHEDULE if not s.startswith("optim.iterations=")] + ic.STDR_PHASES + \
        ["optim.iterations=60", "train.stop_at=40", "experiment=embedded_deform_stdr", f"baseline.precision={precision}",
         f"stdr.field_precision={precision}"]
    params = {}
    for n in (1, 2):
        torch.set_num_threads(n)
        t = Trainer(tiny_config(tmp_path, sched), tmp_path / f"t{n}", splits=("train",))
        t.train()
        params[n] = {k: v.detach().clone() for k, v in t.state.model.params.items()}
        # the networks too: the deformation's and STDR's separated field (bf16 with the network)
        params[n].update({f"net.{k}": v.detach().clone() for k, v in t.state.model.deform.state_dict().items()})
        s = t.state.model.plugin("stdr")
        assert s.field_precision == precision
        params[n].update({f"field.{k}": v.detach().clone() for k, v in s.field.state_dict().items()})
    assert params[1].keys() == params[2].keys()
    for k in params[1]:
        assert torch.equal(params[1][k], params[2][k]), k


def test_image_metrics_give_the_same_bits_on_any_thread_count(restore_threads):
    """PSNR, SSIM, L1 and LPIPS of a 200x200 image: their means add in an order fixed by the
    shape (stdr.ops.fixed_mean), within float rounding of the float64 truth."""
    from stdr.metrics import l1, psnr, ssim
    from stdr.ops import fixed_mean
    g = torch.Generator().manual_seed(2)
    a, b = torch.rand(200, 200, 3, generator=g), torch.rand(200, 200, 3, generator=g)
    metrics = [lambda: (psnr(a, b), ssim(a, b), l1(a, b), fixed_mean(a, (0, 1)))]
    try:
        from stdr.eval.lpips import LPIPS
        lp = LPIPS("alex")
        metrics.append(lambda: (lp(a, b).reshape(()),))
    except FileNotFoundError:
        pass  # no LPIPS weights here: the other metrics still count
    for fn in metrics:
        _assert_same(_each_thread_count(fn), "metrics")
    assert float(psnr(a, b)) == pytest.approx(float(10 * torch.log10(1 / ((a.double() - b.double()) ** 2).mean())), abs=1e-5)
    assert torch.allclose(fixed_mean(a, (0, 1)).double(), a.double().mean((0, 1)), atol=1e-6)
