import torch

from stdr.deform import DeformMLP, Deltas, apply_post_activation, apply_pre_activation
from stdr.encoding import positional_encoding
from stdr.scene.gaussians import init_params


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
