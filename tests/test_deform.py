import torch

from stdr.baselines import DeformMLP, Deltas, apply_post_activation, apply_pre_activation
from stdr.encoding import positional_encoding
from stdr.gaussians import init_params


def test_positional_encoding_layout():
    x = torch.tensor([[0.5, -1.0, 2.0]])
    e = positional_encoding(x, 10)
    assert e.shape == (1, 63)
    assert torch.equal(e[:, :3], x)
    assert torch.allclose(e[0, 3:6], torch.sin(x[0]))          # band 2^0, sin
    assert torch.allclose(e[0, 6:9], torch.cos(x[0]))          # band 2^0, cos
    assert torch.allclose(e[0, -3:], torch.cos(x[0] * 2 ** 9))  # band 2^9, cos


def test_deform_mlp_architecture_matches_paper():
    net = DeformMLP(depth=8, width=256, skips=(4,), xyz_freqs=10, t_freqs=6, time_net=True)
    assert net.layers[0].in_features == 63 + 30          # 93 on synthetic data
    assert net.layers[5].in_features == 256 + 93          # skip after layer 4
    assert net.time_net[0].in_features == 13
    real = DeformMLP(time_net=False, t_freqs=10)
    assert real.layers[0].in_features == 63 + 21          # 84 on real data


def test_deform_input_is_detached_and_cond_is_used():
    p = init_params(torch.rand(10, 3), sh_degree=0)
    net = DeformMLP(depth=3, width=16, skips=(1,), cond_dim=2)
    cond = torch.randn(10, 2)
    d1 = net(p, 0.3, cond)
    (d1.means.sum() + d1.scales.sum() + d1.quats.sum()).backward()
    assert p["means"].grad is None                         # canonical xyz detached
    # cond columns start at zero weight (no jump when STDR's field switches on) but train
    assert torch.equal(net(p, 0.3, cond + 1).means, d1.means)
    assert net.layers[0].weight.grad[:, -2:].abs().sum() > 0
    with torch.no_grad():
        net.layers[0].weight[:, -2:] = 0.5
    d2 = net(p, 0.3, cond + 1)
    assert not torch.allclose(net(p, 0.3, cond).means, d2.means)  # conditioning reaches the network
    d3 = net(p, 0.7, cond)
    assert not torch.allclose(d1.means, d3.means)           # time too


def test_apply_rules_differ_as_documented():
    p = init_params(torch.rand(4, 3), sh_degree=0)
    d = Deltas(means=torch.full((4, 3), 0.1), quats=torch.zeros(4, 4), scales=torch.full((4, 3), 0.5))
    post, pre = apply_post_activation(p, d), apply_pre_activation(p, d)
    assert torch.allclose(post.scales, torch.exp(p["scales"]) + 0.5)     # Deformable 3DGS
    assert torch.allclose(pre.scales, torch.exp(p["scales"] + 0.5))      # 4DGS
    assert torch.allclose(post.means, p["means"] + 0.1)


def _concatenated_trunk(net, xyz, t, cond=None):
    """DeformMLP's function written as the published code runs it: one Linear on the
    concatenated input [PE(xyz), time embedding, cond], the input re-concatenated after a skip."""
    n = xyz.shape[0]
    t_emb = positional_encoding(torch.full((1, 1), float(t), dtype=xyz.dtype), net.t_freqs)
    if net.time_net is not None:
        t_emb = net.time_net(t_emb)
    x0 = torch.cat([positional_encoding(xyz, net.xyz_freqs), t_emb.expand(n, -1)] + ([cond] if net.cond_dim else []), -1)
    h = x0
    for i, layer in enumerate(net.layers):
        h = torch.relu(layer(h))
        if i in net.skips:
            h = torch.cat([h, x0], -1)
    return h


def test_blockwise_trunk_equals_the_concatenated_mlp_with_gradients():
    """The trunk multiplies the input's column blocks separately (the time embedding once); the
    function and every gradient (weights, time net, conditioning) equal the concatenated form."""
    torch.manual_seed(0)
    for kw in (dict(depth=6, width=32, skips=(3,)), dict(depth=4, width=16, skips=(1,), cond_dim=5, time_net=False,
                                                         t_freqs=10)):
        net = DeformMLP(**kw, head_init_std=None).double()
        xyz = torch.randn(300, 3, dtype=torch.float64)
        cond = torch.randn(300, 5, dtype=torch.float64, requires_grad=True) if kw.get("cond_dim") else None
        a, b = net.trunk(xyz, 0.37, cond), _concatenated_trunk(net, xyz, 0.37, cond)
        assert float((a - b).detach().abs().max()) <= 1e-12
        wrt = [p for n, p in net.named_parameters() if not n.startswith("head")] + ([cond] if cond is not None else [])
        ga = torch.autograd.grad(a.square().sum(), wrt)
        gb = torch.autograd.grad(b.square().sum(), wrt)
        for x, y in zip(ga, gb):
            assert float((x - y).abs().max()) <= 1e-10 * max(1.0, float(y.abs().max()))


def test_bf16_precision_is_an_option_with_fp32_deltas():
    import pytest

    from stdr.baselines.base import check_precision
    torch.manual_seed(0)
    net = DeformMLP(depth=3, width=64, skips=(1,), head_init_std=None)
    params = init_params(torch.rand(200, 3), torch.rand(200, 3), sh_degree=0)
    full = net.deltas(params, 0.4)
    net.precision = "bf16"
    half = net.deltas(params, 0.4)
    for k in ("means", "quats", "scales"):
        x, y = getattr(half, k), getattr(full, k)
        assert x.dtype == torch.float32
        assert 0 < float((x - y).detach().abs().max()) <= 0.05 * float(y.detach().abs().max())  # bf16: ~3 significant digits
    with pytest.raises(ValueError, match="baseline.precision='fp16'"):
        check_precision("fp16")
