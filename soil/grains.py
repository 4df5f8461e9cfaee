"""Selecting, removing and appending grains of a state, their contact history carried along.

These work on a state's per-grain rows in model order (`grain_rows` of SoilState.to_numpy()
output), on the host, in a fixed order (bit for bit repeatable). A grain's contact history
names its partners: other grains by model index in its neighbour-list row (`neighbours`,
with `pair_touching` bits and `pair_*` history aligned with it), rigid partners by key in
`rigid_key` (boundary b, or boundary_count + body). When grains are taken out or put together,
the partners are renumbered (`renumber_history`): entries whose partner is gone are dropped,
the others keep their history, packed to the front of the row. The neighbour list is then
marked unbuilt, so the next step builds it again and carries the history of every listed pair
(docs/physics.md).

    rows = grain_rows(sim.state.to_numpy())
    kept = select_grains(rows, keep)                      # a subset, partners renumbered
    both = append_grains([kept, other_block])             # blocks stacked, histories padded
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from .errors import SoilInputError
from .state import UNBUILT, per_grain


def grain_rows(data: dict) -> dict:
    """The arrays of SoilState.to_numpy() output that have one row per grain (model order): kinematics,
    forces, the neighbour list and the pair history aligned with it, the rigid-contact history."""
    return {name: np.asarray(values) for name, values in data.items() if name != "time" and per_grain(name)}


def renumber_history(
    rows: dict, partner: Callable[[np.ndarray], np.ndarray], rigid: Callable[[np.ndarray], np.ndarray]
) -> dict:
    """Per-grain rows (grain_rows) with their contact history renamed: `partner(j)` gives the new index
    of grain j (an index array in, an index array of the same shape out; -1: gone), `rigid(key)` the new
    key of a rigid partner (-1: gone). Entries of partners that are gone are dropped, the others keep
    their history, packed to the front of the row in their order. The neighbour list is marked
    unbuilt (build_position), so the next step builds it again. Returns new arrays (rows is not
    changed)."""
    rows = {k: v.copy() for k, v in rows.items()}
    neighbours = rows["neighbours"].astype(np.int64)
    width = neighbours.shape[1]
    listed = (np.arange(width)[None, :] < rows["neighbour_count"][:, None]) & (neighbours >= 0)
    mapped = np.where(listed, partner(np.maximum(neighbours, 0)), -1)
    keep = mapped >= 0
    touching = unpack_touching(rows["pair_touching"], width)
    kept, (mapped, touching, tangential, rolling) = _compact(
        keep, mapped, touching, rows["pair_tangential"], rows["pair_rolling"]
    )
    rows["neighbours"] = np.where(kept, mapped, -1).astype(np.int32)
    rows["neighbour_count"] = kept.sum(axis=1).astype(rows["neighbour_count"].dtype)
    rows["pair_touching"] = pack_touching(touching & kept)
    rows["pair_tangential"], rows["pair_rolling"] = tangential, rolling
    key = rows["rigid_key"].astype(np.int64)
    used = (np.arange(key.shape[1])[None, :] < rows["rigid_count"][:, None]) & (key >= 0)
    new_key = np.where(used, rigid(np.maximum(key, 0)), -1)
    kept, (new_key, tangential, rolling) = _compact(
        new_key >= 0, new_key, rows["rigid_tangential"], rows["rigid_rolling"]
    )
    rows["rigid_key"] = np.where(kept, new_key, -1).astype(np.int32)
    rows["rigid_count"] = kept.sum(axis=1).astype(rows["rigid_count"].dtype)
    rows["rigid_tangential"], rows["rigid_rolling"] = tangential, rolling
    rows["build_position"] = np.full_like(rows["build_position"], UNBUILT)
    return rows


def select_grains(rows: dict, index, rigid: Callable[[np.ndarray], np.ndarray] | None = None, offset: int = 0) -> dict:
    """The grains `index` (model indices, shape (k,), in the order wanted; or a boolean mask, shape
    (n,)) of per-grain rows (grain_rows), numbered offset .. offset + k - 1 in that order (offset: the
    grains of the blocks they will be appended after, append_grains), their contacts with grains not
    selected dropped and the others renumbered (renumber_history). rigid: the new key of each rigid
    partner (default: the same key). Removing grains is selecting the others."""
    count = len(rows["neighbours"])
    index = np.asarray(index)
    if index.dtype == bool:
        if index.shape != (count,):
            raise SoilInputError(f"a grain mask must have shape ({count},), got {index.shape}")
        index = np.flatnonzero(index)
    index = index.astype(np.int64)
    if index.size and (index.min() < 0 or index.max() >= count or len(np.unique(index)) != len(index)):
        raise SoilInputError(f"grain indices must be distinct and in [0, {count}), got {index.tolist()[:10]}...")
    if offset < 0:
        raise SoilInputError(f"offset must be >= 0, got {offset!r}")
    new_index = np.full(count, -1, dtype=np.int64)
    new_index[index] = offset + np.arange(len(index))
    return renumber_history(
        {k: v[index] for k, v in rows.items()},
        lambda j: new_index[j],
        rigid if rigid is not None else (lambda key: key),
    )


def append_grains(blocks: list[dict]) -> dict:
    """Per-grain rows of several blocks stacked in order (the grains of block b after those of the
    blocks before it), their history widths made equal (padded with empty slots). Each block's
    partners must already be numbered in the stacked order (select_grains, renumber_history)."""
    if not blocks:
        raise SoilInputError("append_grains needs at least one block of grains")
    out = {}
    for name in blocks[-1]:
        arrays = [np.asarray(block[name]) for block in blocks]
        if arrays[0].ndim >= 2:
            width = max(a.shape[1] for a in arrays)
            fill = -1 if name in ("neighbours", "rigid_key") else 0
            padded = []
            for a in arrays:
                wide = np.full((a.shape[0], width, *a.shape[2:]), fill, dtype=a.dtype)
                wide[:, : a.shape[1]] = a
                padded.append(wide)
            arrays = padded
        out[name] = np.concatenate(arrays)
    return out


def rows_in_partner_order(rows: dict) -> dict:
    """Per-grain rows (model order) whose neighbour-list rows list their partners by model index, their
    history along: the order a build gives (soil.neighbours), which a list whose grains were renumbered
    (a bed opened under another order seed) has lost. A grain sums its contacts in its row's order, so
    a list in this order sums as a list rebuilt from it, whenever that happens (soil.worlds). History
    arrays the rows lack are left out (a start state of positions alone); ValueError names one whose
    width is not the list's. Returns new arrays (rows is not changed), or rows itself when every row
    already ascends."""
    neighbours = np.asarray(rows["neighbours"])
    width = neighbours.shape[1]
    counts = rows.get("neighbour_count")
    counts = (neighbours >= 0).sum(axis=1) if counts is None else np.asarray(counts)
    listed = (np.arange(width)[None, :] < counts[:, None]) & (neighbours >= 0)
    keys = np.where(listed, neighbours, np.iinfo(np.int32).max)
    if width < 2 or np.all(keys[:, 1:] >= keys[:, :-1]):
        return rows
    for name in ("pair_tangential", "pair_rolling"):
        if name in rows and np.shape(rows[name])[1] not in (0, width):
            raise ValueError(f"state/{name} has {np.shape(rows[name])[1]} entries per grain, its list {width}")
    if "pair_touching" in rows and np.shape(rows["pair_touching"])[1] < (width + 31) // 32:
        raise ValueError(f"state/pair_touching has too few words per grain for a list {width} wide")
    order = np.argsort(keys, axis=1, kind="stable")

    def moved(values: np.ndarray) -> np.ndarray:
        if values.shape[1] == 0:  # history the contact law does not use (zero width)
            return values.copy()
        return np.take_along_axis(values, order.reshape(order.shape + (1,) * (values.ndim - 2)), axis=1)

    rows = dict(rows)
    rows["neighbours"] = moved(neighbours)
    if "pair_touching" in rows:
        rows["pair_touching"] = pack_touching(moved(unpack_touching(np.asarray(rows["pair_touching"]), width)))
    for name in ("pair_tangential", "pair_rolling"):
        if name in rows:
            rows[name] = moved(np.asarray(rows[name]))
    return rows


def unpack_touching(words: np.ndarray, width: int) -> np.ndarray:
    """The `pair_touching` bits as booleans: bit k of word k // 32 of each row, shape (rows, width)."""
    k = np.arange(width)
    return ((words[:, k // 32] >> (k % 32).astype(np.uint32)) & 1).astype(bool)


def pack_touching(bits: np.ndarray) -> np.ndarray:
    """The inverse of unpack_touching: shape (rows, ceil(width / 32)) (at least 1), uint32."""
    rows, width = bits.shape
    words = np.zeros((rows, max(1, (width + 31) // 32)), dtype=np.uint64)
    for k in range(width):
        words[:, k // 32] |= bits[:, k].astype(np.uint64) << np.uint64(k % 32)
    return words.astype(np.uint32)


def _compact(keep: np.ndarray, *arrays):
    """Move the entries of each row where `keep` to its front, in their order; the rest is zeroed."""
    order = np.argsort(~keep, axis=1, kind="stable")
    kept = np.take_along_axis(keep, order, axis=1)
    out = []
    for values in arrays:
        if values.shape[1] == 0:  # history the contact law does not use (zero width)
            out.append(values.copy())
            continue
        index = order.reshape(order.shape + (1,) * (values.ndim - 2))
        moved = np.take_along_axis(values, index, axis=1).copy()
        moved[~kept] = 0
        out.append(moved)
    return kept, out
