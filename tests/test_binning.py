"""The CUDA backend's Gaussian-tile binning stays memory-safe when its two passes disagree.

The CUDA rasterizer counts each Gaussian's tiles in one pass and writes their keys, into slots
sized by those counts, in a second. Both evaluate one float test (raster_math.h's
`gaussian_tile_keys`); compiled twice with --use_fast_math, the test can round differently in the
two passes (an FMA in one, a multiply and an add in the other). Before the fix, a write pass that
found one tile more wrote into the next Gaussian's slot (or past the buffer), and one that found
one fewer left a slot holding whatever the allocator had there: after the sort, a garbage pair id
indexed the packed rows, an illegal memory access in long GPU runs (docs/notes/2026-11-27-gpu-crash.md).

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
