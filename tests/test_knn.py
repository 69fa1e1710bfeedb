"""The nearest-neighbour searches (stdr.knn): the direct search's compiled kernel against its
torch twin (the same bits), the twin against a float64 reading of its definition, ties and NaNs,
and SC-GS / SP-GS training through `baseline.<name>.knn=direct` with either form."""
import numpy as np
import pytest
import torch

from stdr import extension
from stdr.errors import ConfigError
from stdr.knn import KNN_MAX_K, knn, knn_direct, knn_direct_torch, nearest
from stdr.verified import VERIFIED

needs_cpu_ext = pytest.mark.skipif(not extension.available("cpu"), reason="the CPU extension does not build here")


def _truth(query: np.ndarray, points: np.ndarray, k: int, exclude_self: bool):
    """The definition, read with numpy: float32 differences, their squares added in float64
    coordinate by coordinate, the k smallest (distance, index) pairs; NaN last."""
    d2 = np.zeros((len(query), len(points)))
    for c in range(query.shape[1]):
        diff = (query[:, None, c] - points[None, :, c]).astype(np.float32)
        d2 = d2 + diff.astype(np.float64) ** 2
    if exclude_self:
        d2[np.arange(len(query)), np.arange(len(query))] = np.nan  # then dropped below
    idx = np.zeros((len(query), k), dtype=np.int64)
    for r in range(len(query)):
        order = sorted(range(len(points)), key=lambda j: (np.isnan(d2[r, j]), 0.0 if np.isnan(d2[r, j]) else d2[r, j], j))
        order = [j for j in order if not (exclude_self and j == r)]
        idx[r] = order[:k]
    return d2[np.arange(len(query))[:, None], idx].astype(np.float32), idx


def _cloud(q: int, p: int, d: int, seed: int, duplicates: bool = True):
    g = torch.Generator().manual_seed(seed)
    query, points = torch.randn(q, d, generator=g), torch.randn(p, d, generator=g)
    if duplicates and p > 6:  # exact ties: equal points, and a query equidistant from two of them
        points[5] = points[2]
        points[6] = 2 * query[0] - points[1]
    return query, points


@pytest.mark.parametrize("q,p,d,k,exclude_self", [(37, 23, 3, 4, False), (20, 20, 3, 5, True), (50, 40, 11, 3, False),
                                                  (33, 33, 1, 2, True), (5, 17, 2, 16, False)])
def test_the_twin_is_its_definition(q, p, d, k, exclude_self):
    query, points = _cloud(q, p, d, seed=q + p)
    if exclude_self:
        query = points
    dist, idx = knn_direct_torch(query, points, k, exclude_self)
    want_d, want_i = _truth(query.numpy(), points.numpy(), k, exclude_self)
    np.testing.assert_array_equal(idx.numpy(), want_i)
    np.testing.assert_array_equal(dist.numpy(), want_d)


def test_a_tie_goes_to_the_lower_index_and_a_nan_comes_last():
    points = torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [2.0, 0, 0], [-1.0, 0, 0], [float("nan"), 0, 0], [0, 0, 0.5]])
    query = torch.zeros(1, 3)
    d, i = knn_direct_torch(query, points, 6)
    assert i.tolist() == [[5, 0, 1, 3, 2, 4]] and d[0, :5].tolist() == [0.25, 1.0, 1.0, 1.0, 4.0]
    assert torch.isnan(d[0, 5])
    if extension.available("cpu"):
        dc, ic = extension.load_extension("cpu").knn_direct(query, points, 6, False)
        assert torch.equal(ic, i) and torch.equal(dc.nan_to_num(-1.0), d.nan_to_num(-1.0))


@needs_cpu_ext
@pytest.mark.parametrize("q,p,d,k,exclude_self", [(1000, 512, 11, 3, False), (999, 300, 3, 5, False),
                                                  (512, 512, 3, 10, True), (77, 15, 3, 4, False),
                                                  (64, 40, 1, KNN_MAX_K, False), (300, 130, 7, 1, False)])
@pytest.mark.parametrize("threads", [1, 2])
def test_the_kernel_gives_the_twins_bits(q, p, d, k, exclude_self, threads):
    """Blocks of 16 points and the tail after them, one query per thread: the distances and the
    indices equal the twin's exactly, ties and repeated points included, on 1 and 2 threads."""
    query, points = _cloud(q, p, d, seed=7 * q + p)
    points[p // 2] = float("nan")  # a NaN point: never among the nearest while numbers remain
    query[min(3, q - 1)] = float("nan")  # a NaN query: every distance NaN, indices in order
    if exclude_self:
        query = points
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        dc, ic = extension.load_extension("cpu").knn_direct(query, points, k, exclude_self)
    finally:
        torch.set_num_threads(before)
    dt, it = knn_direct_torch(query, points, k, exclude_self)
    assert torch.equal(ic, it), (ic != it).nonzero()[:5]
    assert torch.equal(dc.nan_to_num(-1.0), dt.nan_to_num(-1.0))


@needs_cpu_ext
def test_near_ties_are_decided_by_the_exact_distance_not_the_float_filter():
    """Points whose float32 distances tie or cross while their exact ones differ by an ulp: the
    kernel's float filter must not drop the nearer one."""
    base = torch.tensor([[1.0, 1.0, 1.0]])
    eps = torch.finfo(torch.float32).eps
    points = torch.cat([base * (1 + s * eps) for s in range(-8, 9)] * 3)  # 51 points, many equal
    points = points[torch.randperm(len(points), generator=torch.Generator().manual_seed(0))]
    query = torch.zeros(5, 3) + torch.tensor([[0.0], [1e-8], [0.5], [1.0], [2.0]])
    dc, ic = extension.load_extension("cpu").knn_direct(query, points, 7, False)
    dt, it = knn_direct_torch(query, points, 7)
    assert torch.equal(ic, it) and torch.equal(dc, dt)


@needs_cpu_ext
def test_the_kernel_runs_where_verified_and_the_twin_elsewhere(monkeypatch):
    """baseline.knn_compiled=null: the kernel on the CPU (stdr.verified.VERIFIED), the twin where
    the table does not list the device; false: the twin; true on inputs the kernel does not take:
    an error naming the key."""
    calls = []
    with extension.observe_calls(lambda name, args, result: calls.append(name)):
        query, points = _cloud(40, 30, 3, seed=1)
        a = knn_direct(query, points, 3)
        monkeypatch.setitem(VERIFIED, "baseline.knn_compiled", ())
        b = knn_direct(query, points, 3)
    assert calls == ["knn_direct"]
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    assert torch.equal(knn_direct(query.double(), points.double(), 3)[1], b[1])  # float64: the twin's order
    assert torch.equal(knn_direct(query, points, 3, compiled=False)[1], b[1])
    with pytest.raises(ValueError, match="baseline.knn_compiled=true: the compiled search takes float32"):
        knn_direct(query.double(), points.double(), 3, compiled=True)


def test_bad_inputs_name_what_is_wrong():
    with pytest.raises(ValueError, match="need at least 4 points"):  # checked in Python, before the kernel
        knn_direct(torch.zeros(3, 3), torch.zeros(3, 3), 3, exclude_self=True)
    with pytest.raises(ConfigError, match=r"knn='kd_tree': use one of cdist, direct"):
        nearest("kd_tree", torch.zeros(3, 3), torch.zeros(3, 3), 1)
    if extension.available("cpu"):
        ext = extension.load_extension("cpu")
        with pytest.raises(RuntimeError, match=r"k must be in 1\.\.16"):
            ext.knn_direct(torch.zeros(40, 3), torch.zeros(40, 3), 17, False)
        with pytest.raises(RuntimeError, match=r"must be \[N, D\] with one D"):
            ext.knn_direct(torch.zeros(4, 3), torch.zeros(4, 2), 1, False)


def test_both_searches_find_the_same_neighbours_away_from_ties():
    """cdist's and the direct search's distances differ in their last bits only: on points with
    no near-tie their neighbours are the same."""
    query, points = _cloud(500, 200, 3, seed=3, duplicates=False)
    dc, ic = knn(query, points, 4)
    dd, idd = knn_direct(query, points, 4)
    gaps = torch.sort(knn_direct_torch(query, points, 5)[0], dim=1)[0].diff(dim=1).min(dim=1)[0]
    clear = gaps > 1e-4
    assert clear.sum() > 400 and torch.equal(ic[clear], idd[clear])
    torch.testing.assert_close(dc, dd, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("name", ["scgs", "spgs"])
def test_a_bad_knn_value_is_refused_with_its_key(tmp_path, name):
    from stdr.testing import tiny_config
    from stdr.train.trainer import Trainer
    cfg = tiny_config(tmp_path, [f"experiment=embedded_{name}", f"baseline.{name}.knn=kd_tree"])
    with pytest.raises(ConfigError, match=rf"baseline\.{name}\.knn='kd_tree': use one of cdist, direct"):
        Trainer(cfg, tmp_path / "run")


@pytest.mark.slow
@needs_cpu_ext
@pytest.mark.parametrize("name", ["scgs", "spgs"])
def test_training_with_the_direct_search_is_the_same_with_the_kernel_or_the_twin(tmp_path, monkeypatch, name):
    """A short SC-GS / SP-GS+STDR run through every stage with baseline.<name>.knn=direct: the
    kernel and the twin end with the same bits (so which one a machine runs changes no result),
    and the kernel ran."""
    from stdr.testing import tiny_config
    from stdr.tools.identity_check import SCHEDULE, STDR_PHASES
    from stdr.train.trainer import Trainer
    out = {}
    for form in ("kernel", "twin"):
        if form == "twin":
            monkeypatch.setitem(VERIFIED, "baseline.knn_compiled", ())
        calls = []
        cfg = tiny_config(tmp_path / form, [f"experiment=embedded_{name}_stdr", *SCHEDULE, *STDR_PHASES,
                                            f"baseline.{name}.knn=direct"])
        with extension.observe_calls(lambda n, a, r, calls=calls: calls.append(n)):
            tr = Trainer(cfg, tmp_path / form / "run")
            tr.train()
        assert ("knn_direct" in calls) == (form == "kernel")
        out[form] = {k: v.detach().clone() for k, v in tr.state.model.params.items()}
        out[form].update({f"net.{k}": v.detach().clone() for k, v in tr.state.model.deform.state_dict().items()})
    assert out["kernel"].keys() == out["twin"].keys()
    for k in out["kernel"]:
        assert torch.equal(out["kernel"][k], out["twin"][k]), k


@pytest.mark.slow
def test_scgs_with_stdr_searches_once_a_step_and_trains_the_same_bits(tmp_path, monkeypatch):
    """SC-GS+STDR's ARAP term reads the node conditioning of the render's skinning: it reuses the
    render's nearest-node search of the same step instead of searching again (a pure speed-up:
    the same bits as searching twice), and searches afresh after any update."""
    from stdr.baselines.scgs import ControlNodeDeformation
    from stdr.testing import tiny_config
    from stdr.tools.identity_check import SCHEDULE, STDR_PHASES
    from stdr.train.trainer import Trainer
    out, searches = {}, {}
    for mode in ("reuse", "search twice"):
        if mode == "search twice":
            plain = ControlNodeDeformation.neighbours
            monkeypatch.setattr(ControlNodeDeformation, "neighbours",
                                lambda self, params, reuse=False, plain=plain: plain(self, params))
        tr = Trainer(tiny_config(tmp_path / mode, ["experiment=embedded_scgs_stdr", *SCHEDULE, *STDR_PHASES]),
                     tmp_path / mode / "run")
        deform, calls = tr.state.model.deform, []
        search = deform.search

        def counted(query, points, k, exclude_self=False, search=search, calls=calls, tr=tr):
            calls.append((tr.step, exclude_self))
            return search(query, points, k, exclude_self)
        deform.search = counted
        tr.train()
        # the steps with the ARAP term (after the node switch and its detached window): the
        # Gaussians' search (exclude_self False) once a step with reuse, twice without
        arap = range(int(tr.cfg.baseline.scgs.node_stage_end) + int(tr.cfg.baseline.scgs.main_warmup) + 1,
                     int(tr.cfg.optim.iterations))
        searches[mode] = {s: sum(1 for st, ex in calls if st == s and not ex) for s in arap}
        out[mode] = {k: v.detach().clone() for k, v in tr.state.model.params.items()}
        out[mode].update({f"net.{k}": v.detach().clone() for k, v in deform.state_dict().items()})
    assert set(searches["reuse"].values()) == {1} and set(searches["search twice"].values()) == {2}, searches
    for k in out["reuse"]:
        assert torch.equal(out["reuse"][k], out["search twice"][k]), k
