"""soil.grains: selecting, removing and appending grains keeps exactly the contact history whose
two partners stay, renumbered, and nothing else."""

import numpy as np
import pytest
from test_macro_step import soil

from soil import SoilInputError
from soil.grains import append_grains, grain_rows, pack_touching, select_grains, unpack_touching
from soil.state import UNBUILT


@pytest.fixture(scope="module")
def rows():
    """Per-grain rows of grains that settled onto each other and the container (contacts with history)."""
    sim = soil("cpu").sim
    sim.run(0.03, 1e-4)
    data = grain_rows(sim.state.to_numpy())
    assert len(contacts(data)[0]) > 20 and len(contacts(data)[1]) > 10, "grains touch grains and walls"
    return data


def contacts(rows):
    """({(i, j): tangential history} of touching grain pairs, {(i, key): tangential history} of rigid contacts)."""
    width = rows["neighbours"].shape[1]
    touching = unpack_touching(rows["pair_touching"], width)
    pairs = {}
    for i, row in enumerate(rows["neighbours"]):
        for k in range(int(rows["neighbour_count"][i])):
            if touching[i, k]:
                pairs[i, int(row[k])] = tuple(rows["pair_tangential"][i, k])
    rigid = {}
    for i, keys in enumerate(rows["rigid_key"]):
        for s in range(int(rows["rigid_count"][i])):
            rigid[i, int(keys[s])] = tuple(rows["rigid_tangential"][i, s])
    return pairs, rigid


def expected(rows, blocks):
    """The contacts that survive when the grains of `blocks` (index arrays, in order) are stacked:
    pairs inside one block, renumbered by their place in the stack; every rigid contact."""
    pairs, rigid = contacts(rows)
    new, block_of = {}, {}
    start = 0
    for b, index in enumerate(blocks):
        for place, i in enumerate(index):
            new[int(i)], block_of[int(i)] = start + place, b
        start += len(index)
    kept_pairs = {
        (new[i], new[j]): t for (i, j), t in pairs.items() if i in new and j in new and block_of[i] == block_of[j]
    }
    kept_rigid = {(new[i], key): t for (i, key), t in rigid.items() if i in new}
    return kept_pairs, kept_rigid


def check_rows(out, count):
    width = out["neighbours"].shape[1]
    used = np.arange(width)[None, :] < out["neighbour_count"][:, None]
    assert len(out["position"]) == count
    assert np.all((out["neighbours"] >= 0) == used), "entries are packed to the front, -1 after"
    assert np.all(out["neighbours"][used] < count)
    assert np.all(out["build_position"] == UNBUILT), "the list is built again at the next step"


def test_removing_grains_drops_their_contacts_and_renumbers_the_rest(rows):
    n = len(rows["position"])
    keep = np.ones(n, dtype=bool)
    keep[::3] = False  # every third grain leaves
    keep[rows["position"][:, 0] > 0.06] = False  # and every grain past x = 6 cm
    out = select_grains(rows, keep)
    check_rows(out, int(keep.sum()))
    assert contacts(out) == expected(rows, [np.flatnonzero(keep)])
    for name in ("position", "velocity", "angular_velocity"):
        np.testing.assert_array_equal(out[name], rows[name][keep])


def test_appending_blocks_keeps_each_blocks_own_contacts(rows):
    n = len(rows["position"])
    order = np.random.default_rng(4).permutation(n)
    first, second = order[: n // 2], order[n // 2 :]
    out = append_grains([select_grains(rows, first), select_grains(rows, second, offset=len(first))])
    check_rows(out, n)
    assert contacts(out) == expected(rows, [first, second])
    np.testing.assert_array_equal(out["position"], rows["position"][order])


def test_selecting_every_grain_in_its_order_keeps_every_contact(rows):
    n = len(rows["position"])
    out = select_grains(rows, np.arange(n))
    assert contacts(out) == contacts(rows)


def test_touching_bits_pack_and_unpack():
    bits = np.random.default_rng(1).random((5, 70)) < 0.5
    words = pack_touching(bits)
    assert words.shape == (5, 3) and words.dtype == np.uint32
    np.testing.assert_array_equal(unpack_touching(words, 70), bits)


def test_bad_selections_are_input_errors(rows):
    n = len(rows["position"])
    for bad in (np.array([0, 0]), np.array([n]), np.ones(n + 1, dtype=bool)):
        with pytest.raises(SoilInputError):
            select_grains(rows, bad)
