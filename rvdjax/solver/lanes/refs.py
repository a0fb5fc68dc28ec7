"""A kernel's arrays, ``[stage][entry][problem]``: loaded and stored a stage at a time as
lists of lane vectors, entry by entry or in power-of-two blocks, or gathered from a table of
models at each lane's index."""

from __future__ import annotations

import math

import jax.numpy as jnp

from rvdjax.solver.lanes.packing import (
    tri_size,
)


class _Block:
    """A ``[stage][entry][problem]`` ref, entries flattened, whose stage is loaded and stored as
    a block (``KernelConfig.block_io``). Triton's blocks have a power-of-two size: an array of
    E entries a stage is read and written in the two overlapping power-of-two chunks that cover
    it (:func:`_chunks`), or, with ``KernelConfig.padded_blocks``, as one block of an array
    padded to a power of two of entries."""

    def __init__(self, ref, padded: bool = False):
        self.ref, self.dtype = ref, ref.dtype
        e = ref.shape[1]
        self.chunks = ((0, e),) if padded else _chunks(e)


def _chunks(e: int) -> tuple[tuple[int, int], ...]:
    """(offset, size) of the power-of-two chunks that cover ``e`` entries: the whole when e is
    a power of two, else two of the largest power of two below e, one from each end (they
    overlap; a store writes the shared entries twice with the same values). No padded copy of
    an array is then needed on either side of a kernel (on an H100 the pads and the slices
    back moved about a sixth of an accurate iteration's bytes, docs/solver.md)."""
    if e & (e - 1) == 0:
        return ((0, e),)
    c = 1 << (e.bit_length() - 1)
    return ((0, c), (e - c, c))


def _interleaved(vals):
    """(lanes, len(vals)) with vals[i] in column i, built from two-way joins (the only
    concatenation Triton has): column i*2 + j of a join holds row i of its j-th operand."""
    if len(vals) == 1:
        return vals[0].reshape(vals[0].shape[0], 1)
    a, b = _interleaved(vals[0::2]), _interleaved(vals[1::2])
    return jnp.stack([a, b], axis=-1).reshape(a.shape[0], 2 * a.shape[1])


class _Gathered:
    """The model of a tile read from a table of K models, ``[model][stage][entry...]`` (no
    problem axis), at each lane's model index (a ``(lanes,)`` int vector loaded once): one
    gather per entry, or (``block``, entries flattened) per power-of-two chunk of a stage's
    entries. The batch engine's three-phase family flies one of three models per slot: the
    kernels read the table (kilobytes, cached) instead of a [B, A] copy of every problem
    (13 KB a thesis-vbar slot, read in each of the Riccati kernels' sweeps)."""

    def __init__(self, ref, index, block: bool):
        self.ref, self.index = ref, index
        self.chunks = _chunks(ref.shape[2]) if block else None


class _Entries:
    """A ``[stage][entry][problem]`` ref, entries flattened, read and written entry by entry
    (the row kernels without block I/O): no shared memory and no barrier, where a
    :class:`_Block`'s split and join pass through both."""

    def __init__(self, ref):
        self.ref, self.dtype = ref, ref.dtype


def _block_entries(ref, t):
    """The lane vectors of stage t's entries, read chunk by chunk (a :class:`_Block`, or a
    :class:`_Gathered` with block loads, whose chunks are (lanes, size))."""
    flat = []
    for off, size in ref.chunks:
        if isinstance(ref, _Gathered):
            x = ref.ref[ref.index, t, off : off + size]
            rows = [v.reshape(v.shape[0]) for v in jnp.split(x, size, axis=1)]
        else:
            x = ref.ref[t, off : off + size]
            rows = [v.reshape(v.shape[-1]) for v in jnp.split(x, size, axis=0)]
        flat += rows[len(flat) - off :]  # an overlap's entries come from the first chunk
    return flat


def _load(ref, t, *shape):
    """The (shape) entries of stage t of a [stage][entry...][problem] ref (or of the lanes'
    models in a :class:`_Gathered` table)."""
    flat = None
    if isinstance(ref, _Block) or (isinstance(ref, _Gathered) and ref.chunks is not None):
        flat = _block_entries(ref, t)
    elif isinstance(ref, _Entries):
        flat = [ref.ref[t, k] for k in range(math.prod(shape))]
    elif isinstance(ref, _Gathered) and ref.ref.ndim == 3:  # a flattened table, by entry
        flat = [ref.ref[ref.index, t, k] for k in range(math.prod(shape))]
    if flat is not None:
        if len(shape) == 1:
            return flat[: shape[0]]
        return [flat[i * shape[1] : (i + 1) * shape[1]] for i in range(shape[0])]
    if isinstance(ref, _Gathered):
        return [[ref.ref[ref.index, t, i, j] for j in range(shape[1])] for i in range(shape[0])]
    if len(shape) == 1:
        return [ref[t, i] for i in range(shape[0])]
    return [[ref[t, i, j] for j in range(shape[1])] for i in range(shape[0])]


def _model_refs(refs, model: str, block_io: bool, padded: bool):
    """The kernel's refs with the model's first: ``model`` "batched" (a [B, A] per problem),
    "shared" (one [B, A], read entry by entry) or "tabled" (a table and the lanes' indices,
    the second ref, dropped here: :class:`_Gathered`); with ``block_io`` the per-problem
    arrays as :class:`_Block`."""
    refs = list(refs)
    if model == "tabled":
        M = _Gathered(refs[0], refs[1][...], block_io)
        refs = [refs[0], *refs[2:]]
    if block_io:
        refs = [
            r if i == 0 and model != "batched" else _Block(r, padded) for i, r in enumerate(refs)
        ]
    if model == "tabled":
        refs[0] = M
    return refs


def _store(ref, t, X):
    if isinstance(ref, _Entries):
        flat = [v for row in X for v in row] if isinstance(X[0], list) else list(X)
        like = next(v for v in flat if v is not None)
        for k, v in enumerate(flat):
            ref.ref[t, k] = jnp.zeros_like(like) if v is None else v
        return
    if isinstance(ref, _Block):
        flat = [v for row in X for v in row] if isinstance(X[0], list) else list(X)
        like = next(v for v in flat if v is not None)
        zero = jnp.zeros_like(like)
        flat = [zero if v is None else v for v in flat]
        flat += [zero] * (ref.ref.shape[1] - len(flat))
        for off, size in ref.chunks:
            ref.ref[t, off : off + size] = _interleaved(flat[off : off + size]).T
        return
    if not isinstance(X[0], list):
        for i, v in enumerate(X):
            ref[t, i] = v
        return
    for i, row in enumerate(X):
        for j, v in enumerate(row):
            ref[t, i, j] = jnp.zeros_like(X[0][0]) if v is None else v


def _tri(P):
    """The lower triangle of a symmetric list matrix as a flat tuple (the loop carry)."""
    return tuple(P[i][j] for i in range(len(P)) for j in range(i + 1))


def _untri(flat, n):
    P = [[None] * n for _ in range(n)]
    it = iter(flat)
    for i in range(n):
        for j in range(i + 1):
            P[i][j] = P[j][i] = next(it)
    return P


def _lower(L):
    """The lower triangle of a :func:`~rvdjax.solver.lanes.algebra.chol` factor as a flat tuple, row
    by row."""
    return tuple(L[i][j] for i in range(len(L)) for j in range(i + 1))


def _load_sym(ref, t, n):
    """Stage t of a symmetric matrix stored as its lower triangle (:func:`_tri`)."""
    return _untri(_load(ref, t, tri_size(n)), n)


def _load_lower(ref, t, n):
    """Stage t of a lower factor stored as its lower triangle (:func:`_lower`); the upper
    triangle None, as :func:`~rvdjax.solver.lanes.algebra.chol` leaves it."""
    flat = iter(_load(ref, t, tri_size(n)))
    return [[next(flat) if j <= i else None for j in range(n)] for i in range(n)]
