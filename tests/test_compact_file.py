"""The compact model file (stdr.compression.file) and its codecs (stdr.compression.codecs): each codec's
promise (exact where it says exact, within its bound where not), the file's round trip through
load_model for a model with every kind of tensor (SP-GS's association table, STDR's mask and
field), and the refusal of a file from a newer version."""
import pytest
import torch

from stdr.compression import codecs
from stdr.compression.file import FORMAT, VERSION, decode_model, encode_model
from stdr.compact.pack import write_compact


def test_raw_and_f32_are_exact():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(50, 7, generator=g)
    for t in (x, x.double(), (x * 40).to(torch.uint8), torch.tensor(True)):
        y = codecs.decode(codecs.encode(t, "raw"))
        assert y.dtype == t.dtype and torch.equal(y, t)
    assert torch.equal(codecs.decode(codecs.encode(x, "f32")), x)
    with pytest.raises(ValueError, match="'raw'"):
        codecs.encode(torch.zeros(3, dtype=torch.int64), "f32")


def test_f16_is_within_half_precision_and_refuses_what_it_cannot_hold():
    g = torch.Generator().manual_seed(1)
    x = torch.randn(4000, generator=g) * torch.logspace(-4, 4, 4000)
    e = codecs.encode(x, "f16")
    assert e["data"].dtype == torch.float16 and codecs.nbytes(e) == 2 * x.numel()
    y = codecs.decode(e)
    normal = x.abs() >= 6.104e-5
    assert ((y - x).abs()[normal] <= x.abs()[normal] * 2.0 ** -11).all()
    assert ((y - x).abs()[~normal] <= 2.0 ** -25).all()
    with pytest.raises(ValueError, match="float16's range"):
        codecs.encode(torch.tensor([1.0, 7e4]), "f16")
    with pytest.raises(ValueError, match="non-finite"):
        codecs.encode(torch.tensor([1.0, float("nan")]), "f16")


def test_q8_and_q16_are_within_half_a_step_per_column():
    g = torch.Generator().manual_seed(2)
    x = torch.randn(300, 15, 3, generator=g) * torch.tensor([0.1, 1.0, 5.0])  # columns of different ranges
    x[:, 0, 0] = 0.25  # one constant column: exact
    e = codecs.encode(x, "q8")
    assert e["data"].dtype == torch.uint8 and e["lo"].shape == (3,) and codecs.nbytes(e) == x.numel() + 24
    y = codecs.decode(e)
    assert y.shape == x.shape
    bound = (x.reshape(-1, 3).amax(0) - x.reshape(-1, 3).amin(0)) / 510
    assert ((y - x).abs().reshape(-1, 3) <= bound * (1 + 1e-5) + 1e-7).all()
    # the error reaches a good part of its bound (it is a quantization, not an identity)
    assert float(((y - x).abs().reshape(-1, 3) / bound).max()) > 0.9
    e16 = codecs.encode(x, "q16")
    assert e16["data"].dtype == torch.int16 and codecs.nbytes(e16) == 2 * x.numel() + 24
    err16 = (codecs.decode(e16) - x).abs().reshape(-1, 3)
    # half a step of 65 535, plus float32's rounding of lo + q * step (a few ulps of the column's values)
    ulps = 4 * torch.finfo(torch.float32).eps * x.reshape(-1, 3).abs().amax(0)
    assert (err16 <= bound * 255 / 65535 + ulps).all() and float((err16 / bound).max()) < 0.01
    v = torch.linspace(-2, 3, 101)  # a vector is one column
    ev = codecs.encode(v, "q8")
    assert ev["lo"].shape == (1,) and float((codecs.decode(ev) - v).abs().max()) <= 5 / 510 + 1e-6


def test_cols_keeps_the_given_columns_exactly_and_fills_the_rest():
    g = torch.Generator().manual_seed(3)
    x = torch.randn(40, 300, generator=g)
    cols = torch.stack([torch.randperm(300, generator=g)[:5] for _ in range(40)])
    e = codecs.encode(x, "cols", cols)
    assert e["cols"].dtype == torch.int16 and codecs.nbytes(e) < x.numel() * 4 // 20
    y = codecs.decode(e)
    assert torch.equal(y.gather(1, cols), x.gather(1, cols))
    rest = torch.ones_like(x, dtype=torch.bool).scatter_(1, cols, False)
    assert (y[rest] == float(e["fill"])).all() and float(e["fill"]) < float(x.gather(1, cols).min()) - 20
    # a softmax over the kept columns is the original's
    assert torch.equal(torch.softmax(y.gather(1, cols), -1), torch.softmax(x.gather(1, cols), -1))
    with pytest.raises(ValueError, match="outside"):
        codecs.encode(x, "cols", cols + 300)


def test_q4_is_within_half_a_step_of_fifteen_per_column_in_half_a_byte():
    g = torch.Generator().manual_seed(4)
    x = torch.randn(301, 5, generator=g) * torch.tensor([0.01, 0.1, 1.0, 10.0, 0.0])  # odd count, a constant column
    e = codecs.encode(x, "q4")
    assert e["data"].dtype == torch.uint8 and e["data"].numel() == (x.numel() + 1) // 2
    y = codecs.decode(e)
    assert y.shape == x.shape
    bound = (x.amax(0) - x.amin(0)) / 30
    assert ((y - x).abs() <= bound * (1 + 1e-5) + 1e-7).all()
    assert float(((y - x).abs()[:, :4] / bound[:4]).max()) > 0.9 and torch.equal(y[:, 4], x[:, 4])


def test_vq_reads_each_row_as_its_nearest_codeword_and_is_exact_for_few_distinct_rows():
    g = torch.Generator().manual_seed(5)
    distinct = torch.randint(-64, 64, (10, 3, 3), generator=g).float() / 8  # exact in float16
    x = distinct[torch.randint(0, 10, (500,), generator=g)]
    e = codecs.encode(x, "vq:16")
    assert e["data"].dtype == torch.int16 and e["codebook"].dtype == torch.float16
    assert torch.equal(codecs.decode(e), x)
    assert codecs.nbytes(e) == 2 * 500 + 2 * 10 * 9 + 8 * 3  # indices, the 10 codewords used, the shape
    # many distinct rows: every row reads the codeword nearest to it, and the codebook's error is
    # well below that of one codeword (the mean) for all
    y = torch.randn(2000, 12, generator=g) + 4 * torch.randint(0, 8, (2000, 1), generator=g).float()
    e = codecs.encode(y, "vq:32")
    book = e["codebook"].float()
    d = torch.cdist(y, book)
    picked = d.gather(1, e["data"].long().unsqueeze(1)).squeeze(1)
    assert (picked <= d.min(1).values + 1e-4).all()
    err = (codecs.decode(e) - y).pow(2).sum()
    assert err < 0.5 * (y - y.mean(0)).pow(2).sum()
    with pytest.raises(ValueError, match="at most 32767"):
        codecs.encode(y, "vq:40000")


def test_lowrank_is_the_truncated_svd_and_exact_for_a_low_rank_matrix():
    g = torch.Generator().manual_seed(6)
    low = torch.randn(400, 3, generator=g) @ torch.randn(3, 60, generator=g) + torch.randn(60, generator=g)
    e = codecs.encode(low, "lowrank:3")
    assert e["data"].shape == (400, 3) and e["data"].dtype == torch.float16 and e["basis"].shape == (3, 60)
    y = codecs.decode(e)
    # exact up to A's float16 rounding (2^-11 of each factor, summed over 3 terms)
    assert float((y - low).abs().max()) < 3 * 2.0 ** -11 * float(e["data"].float().abs().max()) * 1.01
    # a full-rank matrix: the error is the SVD's tail (Eckart-Young), up to the same rounding
    x = torch.randn(300, 40, generator=g)
    sv = torch.linalg.svdvals((x - x.mean(0)).double())
    for r in (1, 5, 20):
        err = float((codecs.decode(codecs.encode(x, f"lowrank:{r}")) - x).double().norm())
        tail = float(sv[r:].pow(2).sum().sqrt())
        assert tail - 1e-3 <= err <= tail * 1.01 + 1e-2, (r, err, tail)
    with pytest.raises(ValueError, match="2-D"):
        codecs.encode(torch.randn(4, 4, 4), "lowrank:2")
    for bad in ("lowrank", "lowrank:0", "q8:3", "zstd"):
        with pytest.raises(ValueError):
            codecs.parse(bad)


def _trained(tmp_path, experiment, extra=()):
    from stdr.testing import tiny_config
    from stdr.train.trainer import Trainer
    cfg = tiny_config(tmp_path, [f"experiment={experiment}", "model.init_num=400", "optim.iterations=30",
                                 "baseline.warmup=10", "stdr.warmup_end=12", "stdr.freeze_at=20",
                                 "densify.refine_start=1000", "baseline.spgs.num_superpoints=50", *extra])
    t = Trainer(cfg, tmp_path / "run", splits=("train", "test"))
    t.train()
    return t


@pytest.mark.parametrize("experiment", ["embedded_spgs_stdr", "embedded_deform_stdr"])
def test_the_compact_file_round_trips_through_load_model(tmp_path, experiment):
    """Write, load, render: the model read back renders within 0.05 dB PSNR of the full model on
    every test frame, in fewer bytes; means, integer tensors and float64 knots come back exact."""
    from stdr.eval.evaluate import evaluate_model
    from stdr.model import load_model
    t = _trained(tmp_path, experiment)
    full = t.state.model
    path = tmp_path / "model.stdrc"
    rec = write_compact(full, path)
    assert rec["bytes"] < rec["full_bytes"]
    # the per-Gaussian part (networks are kept in float32 by default): SH rest in 8 bits, the rest
    # of the attributes in half precision, SP-GS's table at its 5 read columns of 50
    per_gaussian = codecs.nbytes(encode_model(full)["model"]["params"]) / codecs.nbytes(full.state_dict()["params"])
    assert per_gaussian < 0.45, per_gaussian
    small = load_model(path, "cpu")
    assert small.step == full.step and set(small.params) == set(full.params)
    assert torch.equal(small.params["means"], full.params["means"])
    knots = [p for p in small.plugins if p.name == "stdr"][0].state_dict()["knots"]
    assert knots.dtype == torch.float64
    # STDR's training caches (the regularizer's neighbours, its generator) are not in the file
    trained_state = [p for p in full.plugins if p.name == "stdr"][0].state_dict()
    assert trained_state["knn"] is not None and trained_state["gen"] is not None
    stored = encode_model(full)["model"]["plugins"]["stdr"]
    assert stored["knn"] is None and stored["gen"] is None and stored["field"] is not None
    frames = t.scene.frames("test")
    a, b = evaluate_model(full, frames, fps_warmup=0), evaluate_model(small, frames, fps_warmup=0)
    for pa, pb in zip(a["per_frame_psnr"], b["per_frame_psnr"]):
        assert abs(pa - pb) < 0.05, (pa, pb)
    if experiment.startswith("embedded_spgs"):
        from stdr.baselines.spgs import ASSOC_KEY
        assert rec["spec"][ASSOC_KEY] == "cols"
        idx, G, hard = full.deform.assignment(full.params)
        idx2, G2, hard2 = small.deform.assignment(small.params)
        assert torch.equal(idx, idx2) and torch.equal(G, G2) and torch.equal(hard, hard2)


def test_stdr_mask_codecs_read_back_as_the_8_bit_mask(tmp_path):
    """A codec named for STDR's mask encodes the activated mask, and the file reads it back in the
    8-bit form (stdr.mask_bits=8): `q8` is exactly mask.quantize of the trained logits; a low-rank
    form is within its SVD error of it, renders, and costs fewer bytes."""
    from stdr.model import load_model
    from stdr.plugins.stdr.mask import quantize
    from stdr.plugins.stdr.mask import MASK_KEY
    t = _trained(tmp_path, "embedded_deform_stdr")
    full = t.state.model
    assert full.params[MASK_KEY].is_floating_point()
    write_compact(full, tmp_path / "m8.stdrc", {MASK_KEY: "q8"})
    m8 = load_model(tmp_path / "m8.stdrc", "cpu").params[MASK_KEY]
    assert m8.dtype == torch.uint8 and torch.equal(m8, quantize(full.params[MASK_KEY]))
    rec = write_compact(full, tmp_path / "lr.stdrc", {MASK_KEY: "lowrank:2"})
    assert rec["spec"][MASK_KEY] == "lowrank:2"
    small = load_model(tmp_path / "lr.stdrc", "cpu")
    lr = small.params[MASK_KEY]
    assert lr.dtype == torch.uint8 and lr.shape == m8.shape
    payload = encode_model(full, {MASK_KEY: "lowrank:2"})
    assert codecs.nbytes(payload["model"]["params"][MASK_KEY]) < m8.numel()
    a = torch.sigmoid(full.params[MASK_KEY].detach())
    tail = torch.linalg.svdvals((a - a.mean(0)).double())[2:].pow(2).sum().sqrt()
    # rounding to 1/255 adds at most half a level per entry
    assert float((lr.float() / 255 - a).double().norm()) <= float(tail) + 0.5 / 255 * a.numel() ** 0.5 + 1e-3
    f = t.scene.frames("test")[0]
    small.eval()
    assert torch.isfinite(small.render(f.camera, f.time).image).all()


def test_the_derived_mask_stores_the_fields_output_and_renders_the_same(tmp_path):
    """stdr_mask=derived on a model trained with stdr.mask_after_freeze=false: the file holds the
    separated field's output [N, cond_dim] in place of the N x K mask and no field weights; read
    back in float32 (and every other tensor too) it renders every test frame bit-identically, in
    the default spec (half precision) within 0.05 dB.
    A model whose mask still gates opacity, or one without STDR, is refused by name."""
    from stdr.eval.evaluate import evaluate_model
    from stdr.model import load_model
    from stdr.plugins.stdr.mask import COND_KEY, MASK_KEY
    t = _trained(tmp_path, "embedded_deform_stdr", ["stdr.mask_after_freeze=false"])
    full = t.state.model
    n, k = full.params[MASK_KEY].shape
    cond_dim = full.plugin("stdr").cond_dim
    payload = encode_model(full, {MASK_KEY: "derived", COND_KEY: "f32", "entropy": "none"})  # the codecs' bytes
    stored = payload["model"]["params"]
    assert MASK_KEY not in stored and codecs.nbytes(stored[COND_KEY]) == 4 * n * cond_dim
    assert payload["model"]["plugins"]["stdr"]["field"] is None and payload["spec"][MASK_KEY] == "derived"
    m8 = encode_model(full, {MASK_KEY: "q8", "entropy": "none"})
    saved = codecs.nbytes(m8["model"]) - codecs.nbytes(payload["model"])
    assert saved > n * k - 4 * n * cond_dim  # the mask's bytes go, and the field's weights with them
    exact = {k: "f32" for k in ("scales", "quats", "opacities", "sh0", "shN", "*")}  # every other tensor as it is
    write_compact(full, tmp_path / "d32.stdrc", {**exact, MASK_KEY: "derived", COND_KEY: "f32"})
    write_compact(full, tmp_path / "d16.stdrc", {MASK_KEY: "derived"})
    frames = t.scene.frames("test")
    full.eval()
    for name in ("d32", "d16"):
        small = load_model(tmp_path / f"{name}.stdrc", "cpu")
        small.eval()
        assert MASK_KEY not in small.params and small.params[COND_KEY].shape == (n, cond_dim)
        from stdr.view.core import render_view
        f0 = t.scene.frames("test")[0]
        with pytest.raises(ValueError, match=r"view 'mask': this compact file .*stdr_mask: derived.*stdr_mask=q8"):
            render_view(small, f0.camera, f0.time, "mask")
        if name == "d32":
            with torch.no_grad():
                for f in frames:
                    assert torch.equal(small.render(f.camera, f.time).image, full.render(f.camera, f.time).image)
        else:
            a, b = evaluate_model(full, frames, fps_warmup=0), evaluate_model(small, frames, fps_warmup=0)
            for pa, pb in zip(a["per_frame_psnr"], b["per_frame_psnr"]):
                assert abs(pa - pb) < 0.05, (pa, pb)
    gated = _trained(tmp_path / "gated", "embedded_deform_stdr", ["stdr.mask_after_freeze=true"]).state.model
    with pytest.raises(ValueError, match=r"stdr_mask=derived.*stdr.mask_after_freeze=true"):
        encode_model(gated, {MASK_KEY: "derived"})
    # one spec serves every method (the compact preset's): a model without the mask stores no mask
    # entry and writes what the spec's other codecs make of it
    plain = _trained(tmp_path / "plain", "embedded_deform").state.model
    with_mask_key, without = encode_model(plain, {MASK_KEY: "derived"}), encode_model(plain)
    assert MASK_KEY not in with_mask_key["spec"] and MASK_KEY not in with_mask_key["model"]["params"]
    assert with_mask_key["spec"] == without["spec"]
    assert with_mask_key["model"]["params"].keys() == without["model"]["params"].keys()
    from stdr.compression.entropy import unpack_tree  # the streams as the codecs made them
    ours, theirs = unpack_tree(with_mask_key["model"]["params"]), unpack_tree(without["model"]["params"])
    for k, e in theirs.items():
        got = ours[k]
        assert got.keys() == e.keys(), k
        for f, v in e.items():
            assert torch.equal(got[f], v) if isinstance(v, torch.Tensor) else got[f] == v, (k, f)


def test_state_rules_quantize_4dgs_grid_planes_per_channel_and_leave_the_networks(tmp_path):
    """spec state:grids=q4: every HexPlane plane [C, H, W] within half a step of 15 of its own
    channel's range; the networks, under `state` f32, read back exactly."""
    from stdr.model import load_model
    t = _trained(tmp_path, "embedded_4dgs")
    full = t.state.model
    rec = write_compact(full, tmp_path / "g4.stdrc", {"state": "f32", "state:grids": "q4"})
    assert rec["spec"]["state:grids"] == "q4"
    small = load_model(tmp_path / "g4.stdrc", "cpu")
    a, b = full.deform.state_dict(), small.deform.state_dict()
    planes = [k for k in a if ".grids." in k]
    assert planes and all(a[k].dim() == 3 for k in planes)
    for k in a:
        if k in planes:
            x = a[k].reshape(a[k].shape[0], -1)
            bound = (x.amax(1) - x.amin(1)) / 30
            err = (b[k] - a[k]).abs().reshape(a[k].shape[0], -1)
            assert (err <= bound.unsqueeze(1) * (1 + 1e-5) + 1e-7).all(), k
            assert float(err.max()) > 0  # quantized, not kept
        else:
            assert torch.equal(a[k], b[k]), k


def test_the_codebook_fine_tune_lowers_the_training_loss_and_moves_only_the_codewords(tmp_path):
    """shN=vq:8 with finetune: the file's other tensors are those of the file without it, every
    shN row is still one of the (float16) codewords, and the training frames' loss of the model
    read back is lower than with the k-means codebook."""
    from stdr.metrics import image_loss
    from stdr.model import load_model
    t = _trained(tmp_path, "embedded_deform", ["model.sh_interval=5"])
    frames = t.scene.frames("train")
    spec = {"shN": "vq:8", "entropy": "none"}  # the codecs' bytes (entropy coding would see the moved codewords)
    plain = write_compact(t.state.model, tmp_path / "vq.stdrc", spec)
    tuned = write_compact(t.state.model, tmp_path / "ft.stdrc", {**spec, "finetune": 60}, frames)
    assert tuned["spec"]["finetune"] == 60 and tuned["finetune"]["steps"] == 60 and tuned["bytes"] == plain["bytes"]
    a, b = load_model(tmp_path / "vq.stdrc", "cpu"), load_model(tmp_path / "ft.stdrc", "cpu")
    for k in a.params:
        if k != "shN":
            assert torch.equal(a.params[k], b.params[k]), k
    assert not torch.equal(a.params["shN"], b.params["shN"])
    rows = b.params["shN"].reshape(b.params["shN"].shape[0], -1)
    assert torch.unique(rows, dim=0).shape[0] <= 8
    assert torch.equal(rows.half().float(), rows)

    def loss(m):
        m.eval()
        with torch.no_grad():
            return sum(float(image_loss(m.render(f.camera, f.time).image, f.image, 0.2)[0]) for f in frames)
    assert loss(b) < loss(a)
    with pytest.raises(ValueError, match="nothing to fine-tune"):
        write_compact(t.state.model, tmp_path / "x.stdrc", {"finetune": 10}, frames)


def test_the_fine_tune_leaves_a_codebook_no_gradient_reaches_and_tunes_the_others(tmp_path):
    """STDR's derived conditioning as vq codewords next to shN's (the study's `derivedvq` with the
    fine-tune): the render reads the conditioning as a constant, so its codebook stays exactly as
    k-means placed it and is reported `fixed`; shN's codewords are tuned as without it."""
    from stdr.model import load_model
    from stdr.plugins.stdr.mask import COND_KEY, MASK_KEY
    t = _trained(tmp_path, "embedded_deform_stdr", ["stdr.mask_after_freeze=false", "model.sh_interval=5"])
    frames = t.scene.frames("train")
    spec = {"shN": "vq:8", MASK_KEY: "derived", COND_KEY: "vq:16"}
    write_compact(t.state.model, tmp_path / "vq.stdrc", spec)
    rec = write_compact(t.state.model, tmp_path / "ft.stdrc", {**spec, "finetune": 20}, frames)
    assert rec["finetune"]["keys"] == ["shN"] and rec["finetune"]["fixed"] == [COND_KEY]
    a, b = load_model(tmp_path / "vq.stdrc", "cpu"), load_model(tmp_path / "ft.stdrc", "cpu")
    assert torch.equal(a.params[COND_KEY], b.params[COND_KEY])
    assert not torch.equal(a.params["shN"], b.params["shN"])


def test_stdr_train_with_pack_enabled_writes_the_compact_file_with_the_configured_codecs(tmp_path):
    """pack.enabled (what compact=on sets): after the final evaluation the run folder holds
    model.stdrc in the configured codecs and pack.json with both models' renders of the eval split."""
    import json

    from stdr.train.run import run_training as run
    from stdr.model import load_model
    from stdr.testing import tiny_config
    cfg = tiny_config(tmp_path, ["experiment=embedded_deform", "model.init_num=300", "optim.iterations=20",
                                 "baseline.warmup=10", "densify.refine_start=1000", "model.sh_interval=5",
                                 "pack.enabled=true", "+pack.codecs.shN=vq:8", "+pack.codecs.state=f16",
                                 "pack.finetune=5"])
    run(cfg, tmp_path / "run")
    rec = json.loads((tmp_path / "run" / "pack.json").read_text())
    assert rec["spec"]["shN"] == "vq:8" and rec["spec"]["state"] == "f16" and rec["spec"]["finetune"] == 5
    assert rec["finetune"]["steps"] == 5 and rec["split"] == cfg.data.eval_split
    assert rec["bytes"] < rec["full_bytes"] and abs(rec["delta_psnr"]) < 1.0
    m = load_model(tmp_path / "run" / "model.stdrc", "cpu")
    assert torch.unique(m.params["shN"].reshape(m.params["shN"].shape[0], -1), dim=0).shape[0] <= 8
    bad = tiny_config(tmp_path, ["experiment=embedded_deform", "pack.enabled=true", "+pack.codecs.shN=vq"])
    with pytest.raises(ValueError, match="pack.codecs: compact spec shN='vq'"):
        run(bad, tmp_path / "bad")
    assert not (tmp_path / "bad" / "checkpoints").exists()  # refused before any training
    gated = tiny_config(tmp_path, ["experiment=embedded_deform_stdr", "pack.enabled=true",
                                   "stdr.mask_after_freeze=true", "+pack.codecs.stdr_mask=derived"])
    with pytest.raises(ValueError, match=r"pack.codecs: stdr_mask=derived .*stdr.mask_after_freeze=false"):
        run(gated, tmp_path / "gated")
    assert not (tmp_path / "gated" / "checkpoints").exists()


def test_the_sh_rest_kept_to_a_lower_degree_renders_as_that_degree(tmp_path):
    """spec sh_degree=1: the file keeps 3 of the 15 SH rest rows; the model read back has the
    higher bands at zero, so it renders as the full model with those bands zeroed."""
    from stdr.model import load_model
    t = _trained(tmp_path, "embedded_deform", ["model.sh_interval=5"])
    full = t.state.model
    exact = {k: "f32" for k in ("means", "scales", "quats", "opacities", "sh0", "shN", "*", "state")}
    rec = write_compact(full, tmp_path / "d1.stdrc", {**exact, "sh_degree": 1})
    assert rec["spec"]["sh_degree"] == 1
    small = load_model(tmp_path / "d1.stdrc", "cpu")
    want = full.params["shN"].detach().clone()
    want[:, 3:] = 0
    assert torch.equal(small.params["shN"], want)
    with torch.no_grad():
        full.params["shN"].copy_(want)
    f = t.scene.frames("test")[0]
    full.eval()
    small.eval()
    assert torch.equal(full.render(f.camera, f.time).image, small.render(f.camera, f.time).image)
    with pytest.raises(ValueError, match="sh_degree=4"):
        encode_model(full, {"sh_degree": 4})


def test_a_file_from_a_newer_version_is_refused_with_a_clear_error(tmp_path):
    from stdr.model import load_model
    from stdr.io.checkpoint import load_checkpoint, save_checkpoint
    t = _trained(tmp_path, "embedded_deform")
    payload = encode_model(t.state.model)
    assert payload["format"] == FORMAT and payload["version"] == VERSION
    payload["version"] = VERSION + 1
    save_checkpoint(tmp_path / "new.stdrc", payload)
    with pytest.raises(ValueError, match=f"version {VERSION + 1}, written by a newer stdr"):
        load_model(tmp_path / "new.stdrc", "cpu")
    with pytest.raises(ValueError, match="unknown codec"):
        p = load_checkpoint(tmp_path / "new.stdrc")
        p["version"] = VERSION
        p["model"]["params"]["scales"]["codec"] = "zstd"
        decode_model(p)
    with pytest.raises(ValueError, match="compact spec shN='q3'"):
        encode_model(t.state.model, {"shN": "q3"})
    with pytest.raises(ValueError, match="write vq:<C codewords>"):
        encode_model(t.state.model, {"shN": "vq"})


def test_quantizing_in_a_given_range_is_the_codec_and_its_device_twin_reads_what_the_file_reads():
    """encode_in_range with the tensor's own min and max is `encode` bit for bit; in a narrower
    range the values outside read back as its ends; `dequantized` (the fine-tune's on-device form)
    equals decode(encode_in_range(...)) exactly, a constant column included."""
    g = torch.Generator().manual_seed(7)
    x = torch.randn(301, 4, generator=g) * torch.tensor([0.1, 1.0, 3.0, 0.0])
    for codec in ("q4", "q8", "q16"):
        own = codecs.encode(x, codec)
        again = codecs.encode_in_range(x, codec, x.amin(0), x.amax(0))
        assert all(torch.equal(own[k], again[k]) for k in own if isinstance(own[k], torch.Tensor)), codec
        lo, hi = x.amin(0) / 2, x.amax(0) / 2
        e = codecs.encode_in_range(x, codec, lo, hi)
        y = codecs.decode(e)
        assert torch.equal(codecs.dequantized(x, codec, lo, hi), y), codec
        assert (y >= lo - 1e-6).all() and (y <= hi + 1e-6).all(), codec
        below = x < lo
        assert below.any() and torch.equal(y[below], lo.expand_as(x)[below]), codec
        assert torch.equal(y[:, 3], x[:, 3]), codec  # lo == hi: the constant itself


def test_the_quantization_aware_fine_tune_of_4dgs_grid_lowers_the_loss_and_keeps_the_file_honest(tmp_path):
    """state:grids=q4 with finetune_state=grids: the planes are still 4 bits in the range of the
    file without it (each plane reads back as lo + k (hi - lo) / 15), they moved, the networks
    are as in the codebook-only file, the model read back renders the training frames with a
    lower loss, and what the fine-tune rendered last is what the file holds."""
    from stdr.compression.file import decode_model
    from stdr.io.checkpoint import load_checkpoint
    from stdr.metrics import image_loss
    from stdr.model import load_model
    t = _trained(tmp_path, "embedded_4dgs", ["model.sh_interval=5"])
    frames = t.scene.frames("train")
    spec = {"shN": "vq:8", "state": "f32", "state:grids": "q4", "entropy": "none", "finetune": 40}
    books = write_compact(t.state.model, tmp_path / "books.stdrc", spec, frames)
    rec = write_compact(t.state.model, tmp_path / "grid.stdrc", {**spec, "finetune_state": "grids"}, frames)
    assert rec["spec"]["finetune_state"] == "grids" and rec["finetune"]["state"] and rec["bytes"] == books["bytes"]
    assert all(".grids." in k for k in rec["finetune"]["state"]) and "finetune_state" not in books["spec"]
    a, b = load_model(tmp_path / "books.stdrc", "cpu"), load_model(tmp_path / "grid.stdrc", "cpu")
    sa, sb = a.deform.state_dict(), b.deform.state_dict()
    raw = decode_model(load_checkpoint(tmp_path / "books.stdrc"))["deform"]
    assert set(rec["finetune"]["state"]) == {k for k in sa if ".grids." in k}
    for k in sa:
        if k in rec["finetune"]["state"]:
            x = sb[k].movedim(0, -1).reshape(-1, sb[k].shape[0])
            ref = raw[k].movedim(0, -1).reshape(-1, sb[k].shape[0])
            lo, hi = ref.amin(0), ref.amax(0)  # the codebook-only file's range: lo and hi are levels 0 and 15
            k15 = (x - lo) / ((hi - lo) / 15)
            assert (k15 - k15.round()).abs().max() < 1e-3 and k15.min() > -1e-3 and k15.max() < 15 + 1e-3, k
        else:
            assert torch.equal(sa[k], sb[k]), k
    assert any(not torch.equal(sa[k], sb[k]) for k in rec["finetune"]["state"])

    def loss(m):
        m.eval()
        with torch.no_grad():
            return sum(float(image_loss(m.render(f.camera, f.time).image, f.image, 0.2)[0]) for f in frames)
    assert loss(b) < loss(a)


def test_finetune_state_changes_nothing_in_a_model_without_that_state_or_without_the_fine_tune(tmp_path):
    """One spec serves every method: on deform (no grid) finetune_state=grids writes the same
    file, byte for byte, and so does a spec without fine-tune steps (`compact=on pack.finetune=0`
    on 4dgs: nothing is tuned, the planes are the plain 4-bit ones); stdr-train accepts both."""
    from stdr.compact.pack import check_pack_config
    from stdr.testing import tiny_config
    t = _trained(tmp_path / "d", "embedded_deform", ["model.sh_interval=5"])
    frames = t.scene.frames("train")
    spec = {"shN": "vq:8", "finetune": 10, "state:grids": "q4"}
    write_compact(t.state.model, tmp_path / "a.stdrc", spec, frames)
    write_compact(t.state.model, tmp_path / "b.stdrc", {**spec, "finetune_state": "grids"}, frames)
    assert (tmp_path / "a.stdrc").read_bytes() == (tmp_path / "b.stdrc").read_bytes()
    g = _trained(tmp_path / "g", "embedded_4dgs")
    plain = write_compact(g.state.model, tmp_path / "c.stdrc", {"state:grids": "q4"})
    off = write_compact(g.state.model, tmp_path / "e.stdrc", {"state:grids": "q4", "finetune_state": "grids"}, frames)
    assert "finetune" not in off and "finetune_state" not in off["spec"]
    assert (tmp_path / "c.stdrc").read_bytes() == (tmp_path / "e.stdrc").read_bytes() and plain["bytes"] == off["bytes"]
    cfg = tiny_config(tmp_path, ["experiment=embedded_4dgs", "compact=on", "pack.finetune=0"])
    assert check_pack_config(cfg)["finetune_state"] == "grids"


def test_a_finetune_state_part_the_spec_gives_no_codec_is_refused_by_name(tmp_path):
    """A typo in finetune_state (a part no state:<part> entry names) would fine-tune nothing and
    say nothing: stdr-train refuses it before training, naming the key, the part and the parts
    the spec has; stdr-tool pack says the same in one line."""
    from stdr.compact.pack import check_pack_config
    from stdr.errors import ConfigError
    from stdr.testing import tiny_config
    from stdr.tools.pack_file import main as pack_main
    cfg = tiny_config(tmp_path, ["experiment=embedded_4dgs", "compact=on", "pack.finetune_state=gridz"])
    with pytest.raises(ConfigError, match=r"pack\.finetune_state.*'gridz' is no state:<part>.*bias, grids, weight"):
        check_pack_config(cfg)
    from stdr.train.run import run_training
    run_training(tiny_config(tmp_path, ["experiment=embedded_4dgs", "model.init_num=300", "optim.iterations=20",
                                        "baseline.warmup=10", "densify.refine_start=1000"]), tmp_path / "run")
    with pytest.raises(SystemExit, match=r"^stdr-tool pack: .*'grid' is no state:<part>"):
        pack_main([str(tmp_path / "run"), "--no-eval", "--codec", "state:grids=q4", "finetune=5", "finetune_state=grid"])
    with pytest.raises(SystemExit, match=r"^stdr-tool pack: .*not a trained run"):
        pack_main([str(tmp_path / "nothing"), "--no-eval"])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine (torch.cuda.is_available() is False)")
def test_the_quantization_aware_fine_tune_on_cuda_tunes_the_grid(tmp_path):
    """The fine-tune of a model on the GPU (codebooks and 4DGS's grid through the quantizer's
    on-device twin): the planes are still 4 bits in the file's range, and the file renders the
    training frames with a lower loss than the codebook-only file."""
    from stdr.metrics import image_loss
    from stdr.model import load_model
    t = _trained(tmp_path, "embedded_4dgs", ["model.sh_interval=5", "device=cuda", "render.backend=cuda"])
    model = t.state.model
    assert next(model.deform.parameters()).device.type == "cuda"
    frames = t.scene.frames("train")
    spec = {"shN": "vq:8", "state:grids": "q4", "finetune": 40}
    write_compact(model, tmp_path / "books.stdrc", spec, frames)
    rec = write_compact(model, tmp_path / "grid.stdrc", {**spec, "finetune_state": "grids"}, frames)
    assert rec["finetune"]["state"]
    a, b = load_model(tmp_path / "books.stdrc", "cuda"), load_model(tmp_path / "grid.stdrc", "cuda")
    for k in rec["finetune"]["state"]:
        x = b.deform.get_parameter(k).detach().cpu().movedim(0, -1).reshape(-1, b.deform.get_parameter(k).shape[0])
        ref = a.deform.get_parameter(k).detach().cpu().movedim(0, -1).reshape(-1, x.shape[1])
        lo, hi = ref.amin(0), ref.amax(0)
        k15 = (x - lo) / ((hi - lo) / 15)
        assert (k15 - k15.round()).abs().max() < 1e-3, k

    def loss(m):
        m.eval()
        with torch.no_grad():
            return sum(float(image_loss(m.render(f.camera, f.time).image, f.image, 0.2)[0]) for f in frames)
    assert loss(b) < loss(a)
