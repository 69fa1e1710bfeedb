"""The compiled training loss (optim.fused_loss) pinned to its torch twin, to the direct 2D SSIM
and to finite differences; and the trainer's choice between the two."""
import pytest
import torch
from stdr.metrics import fused_loss, image_loss, l1, psnr, ssim_2d
from stdr import extension
from stdr.metrics import image_loss_compiled

pytestmark = pytest.mark.skipif(not extension.available("cpu"), reason="the CPU extension cannot be built here")
CUDA = torch.cuda.is_available() and bool(torch.version.cuda)
BACKENDS = ["cpu"] + (["cuda"] if CUDA else [])

# (H, W, C): odd sizes, an image smaller than the window, one channel, a wide one
SHAPES = [(37, 23, 3), (5, 7, 3), (24, 16, 1), (9, 64, 3)]


def _pair(shape, dtype, seed):
    g = torch.Generator().manual_seed(seed)
    a = torch.rand(*shape, generator=g, dtype=torch.float64)
    b = (a + 0.3 * torch.randn(*shape, generator=g, dtype=torch.float64)).clamp(0, 1)
    b[0, :3] = a[0, :3]  # exact ties: the L1 gradient there is 0 (sgn), in both
    b[-1, -1] = a[-1, -1]
    return a.to(dtype), b.to(dtype)


def _run(fn, a, b, lam, w):
    x = a.clone().requires_grad_(True)
    out = fn(x, b, lam)
    (out[0] * w).backward()
    return [o.detach().double() for o in out], x.grad.double()


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("lam", [0.0, 0.2, 1.0])
@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_the_loss_matches_the_torch_twin(backend, shape, lam, dtype, tol):
    if backend == "cuda" and dtype == torch.float64:
        pytest.skip("the CUDA kernel is float32")
    a, b = _pair(shape, dtype, seed=len(shape) + shape[0])
    ref, ref_g = _run(image_loss, a.double(), b.double(), lam, 1.7)  # the oracle: the twin in float64
    out, grad = _run(image_loss_compiled, a.to(backend), b.to(backend), lam, 1.7)
    out, grad = [o.cpu() for o in out], grad.cpu()
    for name, o, r in zip(("loss", "l1", "dssim", "psnr"), out, ref):
        assert abs(float(o - r)) <= tol * max(1.0, abs(float(r))), name
    assert ref_g.abs().max() > 0
    assert (grad - ref_g).abs().max() <= tol * ref_g.abs().max()
    if lam == 1.0:  # no L1 term: the gradient is D-SSIM's alone, nonzero at the tied pixels too
        assert grad[0, 0].abs().max() > 0


@pytest.mark.skipif(not CUDA, reason="no CUDA device on this machine (torch.cuda.is_available() is False)")
def test_the_cuda_loss_is_deterministic_and_matches_the_cpu_one_at_training_size():
    a, b = _pair((400, 400, 3), torch.float32, seed=4)
    cpu = _run(image_loss_compiled, a, b, 0.2, 1.0)
    runs = [_run(image_loss_compiled, a.cuda(), b.cuda(), 0.2, 1.0) for _ in range(2)]
    assert all(torch.equal(x, y) for x, y in zip(runs[0][0], runs[1][0])) and torch.equal(runs[0][1], runs[1][1])
    for o, r in zip(runs[0][0], cpu[0]):
        assert abs(float(o.cpu() - r)) <= 1e-5 * max(1.0, abs(float(r)))
    assert (runs[0][1].cpu() - cpu[1]).abs().max() <= 1e-5 * cpu[1].abs().max()


def test_its_ssim_is_the_direct_2d_window_and_its_stats_the_metrics():
    """Independent of the twin's separable form: 1 - dssim equals the 2D-window SSIM (the 3DGS
    code's form), l1 and psnr equal the metrics' functions."""
    a, b = _pair((31, 27, 3), torch.float64, seed=5)
    _, l1_, dssim, p = image_loss_compiled(a, b, 0.2)
    assert abs(float(1 - dssim) - float(ssim_2d(a, b))) < 1e-12
    assert abs(float(l1_) - float(l1(a, b))) < 1e-14
    assert abs(float(p) - float(psnr(a, b))) < 1e-10


def test_its_gradient_matches_finite_differences():
    a, b = _pair((9, 12, 2), torch.float64, seed=7)
    b = b + 0.05  # no ties: |a - b| is differentiable at every pixel
    x = a.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: image_loss_compiled(t, b, 0.3)[0], (x,), eps=1e-6, atol=1e-7)


def test_it_is_deterministic_whatever_the_threads():
    a, b = _pair((400, 300, 3), torch.float32, seed=3)
    threads = torch.get_num_threads()
    try:
        runs = []
        for n in (1, 2, 1):
            torch.set_num_threads(n)
            runs.append(_run(image_loss_compiled, a, b, 0.2, 1.0))
    finally:
        torch.set_num_threads(threads)
    for out, grad in runs[1:]:
        assert all(torch.equal(o, r) for o, r in zip(out, runs[0][0]))
        assert torch.equal(grad, runs[0][1])


def test_only_the_loss_has_a_gradient():
    a, b = _pair((8, 8, 3), torch.float32, seed=1)
    x = a.clone().requires_grad_(True)
    loss, l1_, dssim, p = image_loss_compiled(x, b, 0.2)
    assert loss.requires_grad and not (l1_.requires_grad or dssim.requires_grad or p.requires_grad)


def test_bad_inputs_are_rejected_with_what_is_wrong():
    a, b = _pair((8, 8, 3), torch.float32, seed=1)
    with pytest.raises(ValueError, match="one shape"):
        image_loss_compiled(a, b[:4], 0.2)
    with pytest.raises(ValueError, match=r"\[H, W, C\]"):
        image_loss_compiled(a[0], b[0], 0.2)
    with pytest.raises(ValueError, match="gt is torch.float64"):
        image_loss_compiled(a, b.double(), 0.2)
    with pytest.raises(ValueError, match="float16"):
        image_loss_compiled(a.half(), b.half(), 0.2)
    with pytest.raises(ValueError, match="gt needs a gradient"):
        image_loss_compiled(a, b.clone().requires_grad_(True), 0.2)
    with pytest.raises(ValueError, match="window=10"):
        image_loss_compiled(a, b, 0.2, window=10)


def test_the_key_resolves_by_device_and_names_itself_when_it_cannot_run():
    from stdr.verified import VERIFIED
    assert VERIFIED["optim.fused_loss"] == ("cpu",)  # CUDA: once a GPU check has run these tests there
    cpu, cuda = torch.device("cpu"), torch.device("cuda")
    assert fused_loss(None, cpu) and fused_loss(True, cpu) and not fused_loss(False, cpu)
    assert not fused_loss(None, cuda)  # null: the torch twin there, until verified
    assert not fused_loss(False, cuda)
    with pytest.raises(ValueError, match="optim.fused_loss=true"):
        fused_loss(True, cuda, torch.float64)  # the CUDA kernel is float32
    with pytest.raises(ValueError, match="optim.fused_loss=true"):
        fused_loss(True, cpu, torch.float16)
    if CUDA:
        assert fused_loss(True, cuda)
    else:
        with pytest.raises(RuntimeError, match="optim.fused_loss=true"):
            fused_loss(True, cuda)  # no CUDA extension here: the key is named


def test_training_takes_it_by_default_and_the_twin_on_request(tmp_path):
    """A few steps with each: the compiled loss under the default, the twin under
    optim.fused_loss=false; every step's loss, L1, D-SSIM and PSNR agree to float rounding."""
    from stdr.testing import tiny_config
    from stdr.train.trainer import Trainer
    sched = ["optim.iterations=20", "baseline.warmup=2", "densify.refine_start=1000", "train.checkpoint_every=0",
             "train.eval_at_warmup_end=false"]
    runs = {}
    for key in ("null", "false"):
        tr = Trainer(tiny_config(tmp_path, sched + [f"optim.fused_loss={key}"]), tmp_path / key)
        runs[key] = (tr.image_loss, [tr.train_step() for _ in range(6)])
    assert runs["null"][0] is image_loss_compiled and runs["false"][0] is image_loss
    for fused, twin in zip(runs["null"][1], runs["false"][1]):
        for k in ("loss", "l1", "dssim", "psnr"):
            assert abs(float(fused[k]) - float(twin[k])) <= 1e-4 * max(1.0, abs(float(twin[k]))), k
