"""The CUDA backend's Gaussian-tile binning stays memory-safe when its two passes disagree.

The CUDA rasterizer counts each Gaussian's tiles in one pass and writes their keys, into slots
sized by those counts, in a second. Both evaluate one float test (raster_math.h's
`gaussian_tile_keys`); compiled twice with --use_fast_math, the test can round differently in the
two passes (an FMA in one, a multiply and an add in the other). Before the fix, a write pass that
found one tile more wrote into the next Gaussian's slot (or past the buffer), and one that found
one fewer left a slot holding whatever the allocator had there: after the sort, a garbage pair id
indexed the packed rows, an illegal memory access in long GPU runs (research/notes/2026-11-27-gpu-crash.md).

`bin_pairs_split` runs the count pass on one set of rows and the write pass on another, so these
tests force the disagreement: on the CUDA kernels where a GPU exists, and on the CPU through the
same shared function everywhere.
"""
import pytest
import torch

from stdr import extension
from stdr.render import compiled
from stdr.render.projection import project_gaussians

from helpers import look_at_camera, random_gaussians

KINDS = ["cpu"] + (["cuda"] if torch.cuda.is_available() and torch.version.cuda else [])
W, H = 61, 45


def _packed(tile: int):
    """Packed rows (depth order), their radii and the CPU forward's own lists, for a random scene."""
    cam = look_at_camera((2.5, 0.3, 0.8), width=W, height=H)
    means, quats, scales, opac, colors = random_gaussians(600, seed=4)
    p = project_gaussians(means, quats, scales, opac, cam)
    ext = extension.load_extension("cpu")
    feats = torch.cat([colors, p.depths[:, None]], -1)
    _, _, _, ids, offsets, packed, order = ext.forward(p.means2d, p.conics, p.opacities, feats, p.depths,
                                                       p.radii.to(torch.int32), W, H, tile)
    return packed, p.radii.to(torch.int32)[order], ids, offsets


def _lists(ids: torch.Tensor, offsets: torch.Tensor) -> list[list[int]]:
    ids, offsets = ids.cpu().tolist(), offsets.cpu().tolist()
    return [ids[offsets[t]:offsets[t + 1]] for t in range(len(offsets) - 1)]


def _split(kind, packed, emit, vradii, tile):
    ids, offsets = compiled.bin_pairs_split(packed.to(kind), emit.to(kind), vradii.to(kind), W, H, tile, kind)
    assert ids.dtype == torch.int32 and offsets.dtype == torch.int64
    return ids.cpu(), offsets.cpu()


def _tiles_per_row(kind, rows, vradii, tile) -> torch.Tensor:
    ids, offsets = _split(kind, rows, rows, vradii, tile)
    return torch.bincount(ids[: int(offsets[-1])].long(), minlength=rows.shape[0])


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("tile", [8, 16])
def test_agreeing_passes_give_the_forward_lists(kind, tile):
    packed, vradii, ids, offsets = _packed(tile)
    got_ids, got_off = _split(kind, packed, packed, vradii, tile)
    assert torch.equal(got_off, offsets)
    assert torch.equal(got_ids, ids)  # no padding: every slot written with a real tile
    assert int(got_off[-1]) == got_ids.numel() > 1000


@pytest.mark.parametrize("kind", KINDS)
def test_a_write_pass_that_finds_fewer_tiles_fills_its_slots_with_keys_in_no_list(kind):
    """The write pass sees smaller footprints (lower opacities: a smaller cut-off radius, some
    Gaussians below 1/255 and invisible): each Gaussian writes the tiles it finds, and the
    counted slots it does not reach hold ids outside every tile's list."""
    tile = 16
    packed, vradii, _, _ = _packed(tile)
    emit = packed.clone()
    emit[:, 5] *= 0.05
    counted = _tiles_per_row(kind, packed, vradii, tile)
    found = _tiles_per_row(kind, emit, vradii, tile)
    assert bool((found <= counted).all()) and int(found.sum()) < int(counted.sum())  # the setup disagrees
    ids, offsets = _split(kind, packed, emit, vradii, tile)
    assert ids.numel() == int(counted.sum())  # sized by the count pass
    assert _lists(ids, offsets) == _lists(*_split(kind, emit, emit, vradii, tile))  # exactly emit's lists
    pads = ids[int(offsets[-1]):].long()
    assert pads.numel() == int((counted - found).sum())
    assert torch.equal(torch.bincount(pads, minlength=packed.shape[0]), counted - found)


@pytest.mark.parametrize("kind", KINDS)
def test_a_write_pass_that_finds_more_tiles_writes_no_more_than_counted(kind):
    """The write pass sees larger footprints (opacities raised, conics shrunk): each Gaussian
    writes exactly as many keys as were counted for it (its first tiles in tile order), none
    into another Gaussian's slots; every list stays in depth order and holds valid rows."""
    tile = 8
    packed, vradii, _, _ = _packed(tile)
    emit = packed.clone()
    emit[:, 2:5] *= 0.5
    emit[:, 5] = (emit[:, 5] * 4).clamp(max=0.99)
    counted = _tiles_per_row(kind, packed, vradii, tile)
    found = _tiles_per_row(kind, emit, vradii, tile)
    assert bool((found >= counted).all()) and int(found.sum()) > int(counted.sum())  # the setup disagrees
    ids, offsets = _split(kind, packed, emit, vradii, tile)
    assert ids.numel() == int(offsets[-1]) == int(counted.sum())  # nothing padded, nothing past the buffer
    assert torch.equal(torch.bincount(ids.long(), minlength=packed.shape[0]), counted)
    full = _lists(*_split(kind, emit, emit, vradii, tile))
    for t, lst in enumerate(_lists(ids, offsets)):
        assert lst == sorted(lst) and set(lst) <= set(full[t]), t


# ---------------------------------------------------------------- the capture-safe forward
def _scene(dtype=torch.float32, spread=1.6):
    """A random scene in which some Gaussians are invisible (radius 0: behind or off camera)."""
    cam = look_at_camera((2.5, 0.3, 0.8), width=W, height=H, dtype=dtype)
    means, quats, scales, opac, colors = random_gaussians(600, seed=4, dtype=dtype, spread=spread)
    p = project_gaussians(means, quats, scales, opac, cam)
    feats = torch.cat([colors, p.depths[:, None]], -1)
    return p.means2d, p.conics, p.opacities, feats, p.depths, p.radii.to(torch.int32)


def _on(kind, xs):
    return [x.to(kind) for x in xs]


@pytest.mark.parametrize("kind,dtype", [(k, torch.float32) for k in KINDS] + [("cpu", torch.float64)])
@pytest.mark.parametrize("tile", [8, 16])
def test_the_capture_safe_forward_is_the_forward_when_the_pairs_fit(kind, dtype, tile):
    """forward_bounded with room for every pair (exactly, and with spare slots): the image, T and
    `last` are the forward's bit for bit, so are the tile lists and the visible rows' packing;
    the invisible rows follow them by index; `total` is the pair count; and the backward on its
    outputs gives the forward's gradients (bit for bit on the CPU; CUDA adds atomically)."""
    xs = _on(kind, _scene(dtype))
    radii = xs[5]
    assert 0 < int((radii > 0).sum()) < radii.numel()  # the setup: visible and invisible rows
    ext = extension.load_extension(kind)
    acc, T, last, ids, offsets, packed, order = ext.forward(*xs, W, H, tile)
    P, V, N = int(offsets[-1]), order.numel(), radii.numel()
    for capacity in (P, P + 777):
        b = compiled.forward_bounded(*xs, W, H, capacity, tile, kind)
        assert int(b["total"]) == P and b["pair_ids"].numel() == capacity
        for got, want in ((b["image"], acc), (b["T"], T), (b["last"], last), (b["tile_offsets"], offsets)):
            assert torch.equal(got, want)
        assert torch.equal(b["pair_ids"][:P], ids)
        assert torch.equal(b["order"][:V], order) and torch.equal(b["packed"][:V], packed)
        invisible = torch.nonzero(radii <= 0).squeeze(1)
        assert torch.equal(b["order"][V:], invisible) and b["order"].numel() == N
        g_acc, g_T = torch.randn_like(acc), torch.randn_like(T)
        want_g = ext.backward(packed, order, N, ids, offsets, T, last, g_acc, g_T, W, H, tile)
        got_g = ext.backward(b["packed"], b["order"], N, b["pair_ids"], b["tile_offsets"], b["T"], b["last"],
                             g_acc, g_T, W, H, tile)
        for got, want in zip(got_g, want_g):
            if kind == "cpu":
                assert torch.equal(got, want)
            else:
                torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("kind", KINDS)
def test_a_capacity_below_the_pairs_keeps_the_first_rows_pairs_and_says_how_many_were_needed(kind):
    """With fewer slots than pairs, the buffer holds the first pairs in row (depth) order, each row's
    tiles in tile order, and nothing past it (memory-safe; under memcheck in the GPU check);
    `total` is still the pair count, which is how a caller learns that the image is incomplete.
    Capacity 0 renders nothing."""
    tile = 16
    xs = _on(kind, _scene())
    ext = extension.load_extension(kind)
    _, _, _, ids, offsets, _, order = ext.forward(*xs, W, H, tile)
    P = int(offsets[-1])
    pairs = sorted((row, t) for t, lst in enumerate(_lists(ids, offsets)) for row in lst)  # by row, then tile
    for capacity in (P // 3, P - 1):
        b = compiled.forward_bounded(*xs, W, H, capacity, tile, kind)
        assert int(b["total"]) == P and int(b["tile_offsets"][-1]) == capacity
        kept = sorted((row, t) for t, lst in enumerate(_lists(b["pair_ids"], b["tile_offsets"])) for row in lst)
        assert kept == pairs[:capacity]
        assert all(lst == sorted(lst) for lst in _lists(b["pair_ids"], b["tile_offsets"]))  # depth order in a tile
    empty = compiled.forward_bounded(*xs, W, H, 0, tile, kind)
    assert int(empty["total"]) == P and int(empty["tile_offsets"][-1]) == 0
    assert bool((empty["T"] == 1).all()) and bool((empty["image"] == 0).all())
    with pytest.raises(ValueError, match="capacity >= 0"):
        compiled.forward_bounded(*xs, W, H, -1, tile, kind)
