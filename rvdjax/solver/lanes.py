"""The Riccati factorisation and solves of the Newton step as GPU kernels, one problem per lane.

On a GPU the XLA form of the recursion (:mod:`rvdjax.solver.riccati`) is a ``lax.scan`` over the
horizon whose body becomes several small kernels per stage, every stage's blocks passing
through device memory between them: at 65 536 problems an iteration took ~717 ns per problem
on an H100 where its ~30 KB of traffic needs 10-20 ns (DESIGN §8a). Here the whole recursion
is one Pallas kernel (Triton lowering) per sweep, as the field's batched GPU solvers do
(GATO, CusADi: one instance per thread, the stages in a loop inside the kernel):

* the batch is the minor axis: every array is laid out `[stage][entry][problem]` and a program
  owns a tile of ``BLOCK`` consecutive problems, so each load of one matrix entry is one
  coalesced vector load across the tile;
* the 6x6, 6x3 and 3x3 algebra is written out entry by entry over those lane vectors
  (nested lists of ``(BLOCK,)`` vectors, no ``dot``: float64 MMA needs blocks of 16 and more);
  the cost-to-go P and the affine term p live in registers across the stage loop;
* the factorisation is stored as L and P alone, 27 entries a stage (the Cholesky factor
  and the symmetric P as their lower triangles, :func:`pack`), written once and read back by
  the solves' sweeps with the backward sweep's p; the kernels read the Hessian blocks Phi_x
  and Phi_u as their triangles too (21 and 6 entries). No gain is stored: a backward sweep
  forms p_t = g_x + A^T (q + P B k) (:func:`_backward_rhs_stored`) and a forward sweep solves
  each stage again, du = -H^-1 (g_u + B^T (p + P (A dx - r))) (:func:`_forward_solved`),
  where the textbook recursion stores K and B^T P A (36 more entries a stage, read in every
  sweep: on a GPU each sweep reads them from device memory).

Four kernels: :func:`factor_solve` (the backward factorisation together with the backward
sweep of the first right-hand side, then its forward sweep), :func:`apply` (one more
right-hand side with a stored factorisation), :func:`apply_refined` (that, then one step of
iterative refinement with the residual formed inside the sweeps) and :func:`factor` (no
right-hand side). The factorisation is :mod:`rvdjax.solver.riccati`'s recursion in the same
order (the Joseph form, the gain K refined once against H, kept in registers); the solves
are the same step written without the gain, so their results agree with the XLA form to
rounding (tests: 1e-10 and the same iteration counts on fastmpc-3d and the random
classes); ``interpret=True`` runs them on the CPU for the tests. They run with
``SolverSettings(kernel="pallas")`` (or another of the forms of
:data:`rvdjax.solver.types.PALLAS_FORMS`, through :class:`KernelConfig`), and
``kernel="auto"`` runs ``"pallas-carried"`` when a program is compiled for a CUDA GPU: an
accurate-mode iteration is then the factorisation with the predictor's step (the model
[B, A] read in blocks), the row work between the solves (:mod:`rvdjax.solver.rows_kernel`),
the corrector's step with its refinement, and its row work with the next iteration's Newton
blocks, every other operand entry by entry. The other forms call :func:`factor` then
:func:`apply` (and :func:`apply` again for the refinement): on one H200 (jax 0.11.2, CUDA 13,
2026-11-26) Triton compiled the entry-wise :func:`factor` in 51 s and :func:`apply` in about
3 s, where the entry-wise :func:`factor_solve` had not finished in 165 s on an H100; with
block loads and stores the factorisation compiles in seconds (docs/solver.md).

Inputs are batch-last: ``A`` (N, nx, nx[, b]), ``B`` (N, nx, nu[, b]) (without the batch
axis when the model is shared by every problem), ``Phi_u`` (N, tri(nu), b), ``Phi_x``
(N, tri(nx), b) (lower triangles, :func:`tri_pack`), right-hand sides ``g_u`` (N, nu, b),
``g_x``, ``rp`` (N, nx, b). The batch is padded to a multiple of ``BLOCK`` inside.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
from jax import lax

__all__ = [
    "KernelConfig",
    "configured",
    "default_config",
    "chol",
    "chol_solve",
    "factor",
    "factor_solve",
    "apply",
    "apply_refined",
    "pack",
    "unpack",
    "tri_size",
    "tri_pack",
    "tri_unpack",
    "tile",
]


@dataclasses.dataclass(frozen=True)
class KernelConfig:
    """Static launch configuration of the kernels.

    Attributes:
        block: problems per program (the lanes of one tile); a power of two.
        num_warps: warps per program (Triton): 4 warps = 128 threads, one problem each at
            block = 128.
        interpret: run the kernels in Pallas' interpreter (the CPU; tests).
        fused: the solver's factorisation and first step in one kernel (:func:`factor_solve`)
            instead of :func:`factor` then :func:`apply`, and a step with its refinement in
            one kernel (:func:`apply_refined`) (the solver: ``kernel="pallas-fused"``, entry
            by entry, and ``"pallas-block-fused"``, with ``block_io``). On an H200
            (2026-11-26) Triton compiled the entry-wise :func:`factor` alone in 51 s and
            :func:`apply` in about 3 s; the entry-wise fused kernel did not finish in 165 s on
            an H100. With ``block_io`` the program XLA compiles for an H100 here, Triton's
            kernels included, took 37 s instead of 14 (65 536 fastmpc-3d QPs).
        block_io: load and store a stage's block of each array at once (entries flattened,
            in at most two power-of-two chunks, split into lane vectors and joined back inside
            the kernel) instead of entry by entry (the solver: ``kernel="pallas-block-io"``).
            Triton's compile time is its coalescing pass, which costs about (loads and
            stores) x (kernel size)^2 (``sweeps/triton_compile_profile.py``); this cuts the
            loads and stores from hundreds to a few.
        solve_block_io: with ``block_io``, the solves (:func:`apply`, :func:`apply_refined`)
            load and store blocks too; without it (the solver: ``kernel="pallas-block-factor"``,
            ``"pallas-rows"`` and ``"pallas-entries"``) only the factorisation does, and the
            solves read the factorisation, the model and the right-hand sides entry by entry,
            straight from their arrays (a solve's kernel is small enough to compile in seconds
            either way). A block's split into lane vectors and join back pass through shared
            memory, with a barrier each: assembled by ptxas for an H100, the block form of the
            refined solve holds 585 barriers, the entry-wise form none
            (``sweeps/gpu_registers.py``).
        padded_blocks: with ``block_io``, the block arrays hold each stage's entries padded to a
            power of two (one load or store a stage, but a padded copy of every input and a
            slice of every output outside the kernel), instead of the entries as they are,
            read and written in two overlapping power-of-two chunks (:func:`_chunks`). The
            padded form was the only one until 2026-11-28; in the program compiled for an
            H100 its pads and slices moved 123 of an accurate iteration's 765 KB a problem
            (``sweeps/gpu_traffic.py``, docs/benchmark.md). It stays for comparison
            (``sweeps/gpu_benchmark.py --padded-blocks``).
        model_blocks_only: with ``block_io``, the factorisation reads only the model [B, A] in
            blocks and every other operand, and its outputs, entry by entry (the solver:
            ``kernel="pallas-entries"``). Assembled for an H100, the factorisation's kernel
            then holds 12 barriers instead of 369 in thesis-vbar's engine (the model from the
            phase table), 108 instead of 465 for QPs with a model each and none instead of 357
            with one model, with as many spills or fewer; read entry by entry, the model's 54
            entries a stage made it spill more (docs/benchmark.md).

    The solver takes ``fused``, ``block_io``, ``solve_block_io`` and ``model_blocks_only`` from
    its kernel name, and the rest from :func:`default_config`.
    """

    block: int = 128
    num_warps: int = 4
    interpret: bool = False
    fused: bool = False
    block_io: bool = False
    solve_block_io: bool = True
    padded_blocks: bool = False
    model_blocks_only: bool = False


_DEFAULT = [KernelConfig()]


def default_config() -> KernelConfig:
    """The launch configuration the solver's kernels are traced with."""
    return _DEFAULT[0]


@contextlib.contextmanager
def configured(**changes):
    """Trace the solver's kernels with another launch configuration inside the block (e.g.
    ``block=64`` in a benchmark). JAX's caches are cleared on entry and exit when the
    configuration changes: a jitted solve would otherwise reuse a program traced with the
    other one (the configuration is not part of its cache key)."""
    old = _DEFAULT[0]
    new = dataclasses.replace(old, **changes)
    if new != old:
        jax.clear_caches()
    _DEFAULT[0] = new
    try:
        yield new
    finally:
        _DEFAULT[0] = old
        if new != old:
            jax.clear_caches()


# ----------------------------------------------------------------------- lane-vector algebra
#
# A matrix is a list of rows, each a list of entries; an entry is anything that broadcasts
# (a lane vector, a scalar of a shared model, a traced array with trailing batch axes). Sums
# run left to right from 0, as the elementwise products of :mod:`rvdjax.solver.riccati` do.


def _dot(xs, ys):
    return sum(x * y for x, y in zip(xs, ys, strict=True))


def _col(X, j):
    return [row[j] for row in X]


def _mm(X, Y):
    """X @ Y."""
    cols = [_col(Y, j) for j in range(len(Y[0]))]
    return [[_dot(row, c) for c in cols] for row in X]


def _mtm(X, Y):
    """X^T @ Y."""
    return [[_dot(_col(X, i), _col(Y, j)) for j in range(len(Y[0]))] for i in range(len(X[0]))]


def _mv(X, v):
    return [_dot(row, v) for row in X]


def _mtv(X, v):
    return [_dot(_col(X, j), v) for j in range(len(X[0]))]


def _add(X, Y):
    return [[x + y for x, y in zip(rx, ry, strict=True)] for rx, ry in zip(X, Y, strict=True)]


def _sym(X):
    n = len(X)
    return [[0.5 * (X[i][j] + X[j][i]) for j in range(n)] for i in range(n)]


def chol(H):
    """Lower Cholesky factor of a small SPD matrix (lists), entry by entry; NaN if H is not
    positive definite. The upper triangle is None."""
    n = len(H)
    L = [[None] * n for _ in range(n)]
    for j in range(n):
        d = jnp.sqrt(H[j][j] - sum(L[j][k] * L[j][k] for k in range(j)))
        L[j][j] = d
        for i in range(j + 1, n):
            L[i][j] = (H[i][j] - sum(L[i][k] * L[j][k] for k in range(j))) / d
    return L


def chol_solve(L, b):
    """x with (L L^T) x = b for a lower factor from :func:`chol` and a vector b (list)."""
    n = len(L)
    y = []
    for i in range(n):
        y.append((b[i] - sum(L[i][k] * y[k] for k in range(i))) / L[i][i])
    x = [None] * n
    for i in reversed(range(n)):
        x[i] = (y[i] - sum(L[k][i] * x[k] for k in range(i + 1, n))) / L[i][i]
    return x


def _chol_solve_mat(L, Bm):
    """X with (L L^T) X = Bm, column by column."""
    cols = [chol_solve(L, _col(Bm, j)) for j in range(len(Bm[0]))]
    return [[c[i] for c in cols] for i in range(len(L))]


# ----------------------------------------------------------------------- one stage of a sweep


def _split(M, nu):
    """(A, B) of a stage's [B, A]."""
    return [row[nu:] for row in M], [row[:nu] for row in M]


def _factor_stage(P, M, Phu, Phx_prev):
    """(P_t, L, K) from P_{t+1}: :func:`rvdjax.solver.riccati.riccati_factor`'s stage.
    M is the stage's [B, A]; ``Phx_prev`` a function that gives Phi_x[t - 1] (called where
    it is added, last, so that a kernel's loads of it are not live through the stage)."""
    nu = len(Phu)
    A, B = _split(M, nu)
    PM = _mm(P, M)
    BPM = _mtm(B, PM)
    H = _add(Phu, _sym([row[:nu] for row in BPM]))
    L = chol(H)
    BPA = [row[nu:] for row in BPM]
    K = [[-v for v in row] for row in _chol_solve_mat(L, BPA)]
    # one refinement of K against H (the reason is in rvdjax.solver.riccati._factor)
    E = _chol_solve_mat(L, _add(_mm(H, K), BPA))
    K = [[k - e for k, e in zip(rk, re, strict=True)] for rk, re in zip(K, E, strict=True)]
    PAcl = _add([row[nu:] for row in PM], _mm([row[:nu] for row in PM], K))
    Acl = _add(A, _mm(B, K))
    joseph = (_sym(_mtm(Acl, PAcl)), _sym(_mtm(K, _mm(Phu, K))))
    P_new = _add(_add(Phx_prev(), joseph[0]), joseph[1])
    return P_new, L, K


def _backward_rhs(p, M, L, P_of, gu, r, gx_prev):
    """(p_t, k_t) from p_{t+1} with a stored factorisation:
    :func:`rvdjax.solver.riccati.riccati_apply`'s backward stage, from L and P alone
    (:func:`_backward_rhs_stored`; ``P_of()`` gives P_{t+1}, called twice)."""
    return _backward_rhs_stored(_offset(p, P_of(), r), M, L, P_of, gu, gx_prev)


def _offset(p, P, r):
    """p - P r: the part of :func:`_backward_rhs` that needs neither the stage's model and
    factorisation nor its right-hand side g."""
    return [pi - q for pi, q in zip(p, _mv(P, r), strict=True)]


def _backward_rhs_of(q, M, L, K, gu, gx_prev):
    """(p_t, k_t) from :func:`_offset`'s q = p - P r, with the stage's gain K at hand (the
    factorisation's own sweep): with v = g_u + B^T q, k = -H^-1 v and p_t = g_x + A^T q +
    K^T v, which is g_x + A^T q + (B^T P A)^T k as K = -H^-1 B^T P A
    (:func:`rvdjax.solver.riccati._apply`)."""
    nu = len(L)
    Mp = _mtv(M, q)
    v = [g + m for g, m in zip(gu, Mp[:nu], strict=True)]
    k = [-w for w in chol_solve(L, v)]
    p_new = [g + m + b for g, m, b in zip(gx_prev, Mp[nu:], _mtv(K, v), strict=True)]
    return p_new, k


def _backward_rhs_stored(q, M, L, P_of, gu, gx_prev):
    """(p_t, k_t) from q = p - P r with a stored factorisation, reading L and P only:
    p_t = g_x + A^T (q + P B k), the same as (B^T P A)^T k = A^T P B k. A solve's backward
    sweep then reads neither K nor B^T P A (18 entries a stage each), which a GPU reads from
    device memory in every sweep; P it reads for q anyway. ``P_of()`` gives P_{t+1} (a
    kernel loads it again here, from the cache, rather than hold its 21 entries through the
    stage)."""
    nu = len(L)
    A, B = _split(M, nu)
    v = [g + m for g, m in zip(gu, _mtv(B, q), strict=True)]
    k = [-w for w in chol_solve(L, v)]
    w = [a + b for a, b in zip(q, _mv(P_of(), _mv(B, k)), strict=True)]
    p_new = [g + m for g, m in zip(gx_prev, _mtv(A, w), strict=True)]
    return p_new, k


def _forward_solved(dx, M, L, gu, r, P_of, p):
    """(dx_{t+1}, du_t, nu_t) from dx_t, the stage solved again from L and P: with
    y = p + P (A dx - r), du = -H^-1 (g_u + B^T y), nu_t = -(y + P B du) (= -(P dx_{t+1} + p)):
    the same step as K dx + k, without the gain."""
    nu = len(L)
    A, B = _split(M, nu)
    Adx_r = [v - ri for v, ri in zip(_mv(A, dx), r, strict=True)]
    y = [a + b for a, b in zip(p, _mv(P_of(), Adx_r), strict=True)]
    du = [-w for w in chol_solve(L, [g + m for g, m in zip(gu, _mtv(B, y), strict=True)])]
    dx_next = [v - ri for v, ri in zip(_mv(M, du + dx), r, strict=True)]
    nu_t = [-(a + b) for a, b in zip(y, _mv(P_of(), _mv(B, du)), strict=True)]
    return dx_next, du, nu_t


def _forward(dx, M, K, k, r, P, p):
    """(dx_{t+1}, du_t, nu_t) from dx_t: the forward stage of the step."""
    du = [a + b for a, b in zip(_mv(K, dx), k, strict=True)]
    dx_next = [v - ri for v, ri in zip(_mv(M, du + dx), r, strict=True)]
    nu_t = [-(a + b) for a, b in zip(_mv(P, dx_next), p, strict=True)]
    return dx_next, du, nu_t


# ------------------------------------------------------------------------------ the kernels


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
    """The lower triangle of a :func:`chol` factor as a flat tuple, row by row."""
    return tuple(L[i][j] for i in range(len(L)) for j in range(i + 1))


def _load_sym(ref, t, n):
    """Stage t of a symmetric matrix stored as its lower triangle (:func:`_tri`)."""
    return _untri(_load(ref, t, tri_size(n)), n)


def _load_lower(ref, t, n):
    """Stage t of a lower factor stored as its lower triangle (:func:`_lower`); the upper
    triangle None, as :func:`chol` leaves it."""
    flat = iter(_load(ref, t, tri_size(n)))
    return [[next(flat) if j <= i else None for j in range(n)] for i in range(n)]


def tri_size(n: int) -> int:
    """Entries of an n x n symmetric (or triangular) matrix's lower triangle."""
    return n * (n + 1) // 2


def pack(L, P):
    """The kernels' storage of a factorisation from (L, P), batch last (L (N, nu,
    nu, b), P (N, nx, nx, b)): L's and P's lower triangles, row by row ((N, tri(nu), b),
    (N, tri(nx), b); :func:`tri_pack`). P is symmetric and L's upper
    triangle zero, so nothing is lost; the solves read 21 entries of P a stage instead of 36
    (P's upper triangle was about a quarter of an accurate iteration's reads of the
    factorisation: docs/benchmark.md)."""
    return tri_pack(L, 1), tri_pack(P, 1)


def unpack(L, P):
    """(L, P) as full matrices, batch last, from :func:`pack`'s storage (L's upper
    triangle 0, P mirrored)."""
    return tri_unpack(L, 1, False), tri_unpack(P, 1, True)


def _tri_pairs(n):
    return [(i, j) for i in range(n) for j in range(i + 1)]


def tri_pack(X, axis: int = -2):
    """The lower triangle, row by row, of the n x n matrices whose axes are ``axis`` and the
    next: one axis of n (n + 1) / 2 entries in their place."""
    axis = axis % X.ndim
    flat = jnp.stack([X[(slice(None),) * axis + (i, j)] for i, j in _tri_pairs(X.shape[axis])])
    return jnp.moveaxis(flat, 0, axis)


def tri_unpack(flat, axis: int, symmetric: bool):
    """The matrices of :func:`tri_pack`'s triangles at ``axis``: mirrored (``symmetric``) or
    with a zero upper triangle."""
    axis = axis % flat.ndim
    n = (math.isqrt(8 * flat.shape[axis] + 1) - 1) // 2
    at = {ij: k for k, ij in enumerate(_tri_pairs(n))}
    entries = jnp.moveaxis(flat, axis, 0)
    zero = jnp.zeros_like(entries[0])

    def entry(i, j):
        if (i, j) in at:
            return entries[at[(i, j)]]
        return entries[at[(j, i)]] if symmetric else zero

    rows = jnp.stack([jnp.stack([entry(i, j) for j in range(n)]) for i in range(n)])
    return jnp.moveaxis(rows, (0, 1), (axis, axis + 1))


def _kernel(N, nx, nu, lanes, with_rhs, factorise, block_io, padded, model, model_only, *refs):
    """One program: the sweeps for a tile of ``lanes`` problems (module docstring).

    refs: M = [B, A] (N, nx, nu + nx[, lanes]), then (factorise) Phi_u, Phi_x (their lower
    triangles, :func:`_tri`) or (not factorise) L, P; then (with_rhs) g_u, g_x, rp;
    outputs: (factorise) L, P; (with_rhs) du, dx, nu. The backward sweep keeps p_{t+1} in
    nu's rows until the forward sweep overwrites them. ``model``
    as :func:`_model_refs`;
    ``model_only``: with ``block_io``, the model alone in blocks, the rest entry by entry
    (:attr:`KernelConfig.model_blocks_only`).
    """
    refs = _model_refs(refs, model, block_io, padded)
    if model_only:
        refs = [refs[0], *(_Entries(r.ref) if isinstance(r, _Block) else r for r in refs[1:])]
    M_ref = refs[0]
    pos = 1
    if factorise:
        Phu_ref, Phx_ref = refs[pos : pos + 2]
        pos += 2
    else:
        L_in, P_in = refs[pos : pos + 2]
        pos += 2
    if with_rhs:
        gu_ref, gx_ref, rp_ref = refs[pos : pos + 3]
        pos += 3
    outs = refs[pos:]
    if factorise:
        L_ref, P_ref = outs[:2]
        outs = outs[2:]
    else:
        L_ref, P_ref = L_in, P_in
    if with_rhs:
        du_ref, dx_ref, nu_ref = outs
    dtype = (Phx_ref if factorise else P_ref).dtype
    zero = jnp.zeros((lanes,), dtype)

    def backward(i, carry):
        t = N - 1 - i
        M = _load(M_ref, t, nx, nu + nx)
        # P_{t+1} and p_{t+1} stored and the right-hand side's p - P r formed first, and Phi_x
        # read last (Phx_prev): past its product with [B, A] the factorisation needs nothing
        # else of P, so fewer entries are live at once (ptxas for sm_90a, the factorisation
        # in thesis-vbar's engine: 1.7 / 2.2 KB of spill stores / loads instead of 2.6 / 3.2;
        # docs/benchmark.md)
        if factorise:
            P = _untri(carry[0], nx)
            _store(P_ref, t, list(carry[0]))
        else:
            P = _load_sym(P_ref, t, nx)
        if with_rhs:
            p = list(carry[-1])
            _store(nu_ref, t, p)
            q = _offset(p, P, _load(rp_ref, t, nx))
        if factorise:
            Phu = _load_sym(Phu_ref, t, nu)
            prev = jnp.maximum(t - 1, 0)
            on = t > 0

            def Phx_prev():
                Phx = _load(Phx_ref, prev, tri_size(nx))
                return _untri([jnp.where(on, v, 0.0) for v in Phx], nx)

            P_new, L, K = _factor_stage(P, M, Phu, Phx_prev)
            _store(L_ref, t, list(_lower(L)))
            new = (_tri(P_new),)
        else:
            L = _load_lower(L_ref, t, nu)
            new = ()
        if with_rhs:
            prev = jnp.maximum(t - 1, 0)
            on = t > 0
            gx_prev = [jnp.where(on, v, 0.0) for v in _load(gx_ref, prev, nx)]
            gu = _load(gu_ref, t, nu)
            if factorise:  # the gain is at hand
                p_new, _ = _backward_rhs_of(q, M, L, K, gu, gx_prev)
            else:  # the stored P again (cached): no gain is stored
                P_of = functools.partial(_load_sym, P_ref, t, nx)
                p_new, _ = _backward_rhs_stored(q, M, L, P_of, gu, gx_prev)
            new = new + (tuple(p_new),)
        return new

    carry = ()
    if factorise:
        carry += (tuple(_load(Phx_ref, N - 1, tri_size(nx))),)
    if with_rhs:
        carry += (tuple(_load(gx_ref, N - 1, nx)),)
    lax.fori_loop(0, N, backward, carry)
    if not with_rhs:
        return

    out = (du_ref, dx_ref, nu_ref)
    _forward_sweep((N, nx, nu), zero, M_ref, L_ref, P_ref, gu_ref, rp_ref, nu_ref, out)


def _forward_sweep(dims, zero, M_ref, L_ref, P_ref, g_ref, r_ref, p_ref, out, add=False):
    """The forward sweep of one right-hand side, whose input gradient g_u, affine term p and
    dynamics residual r are stored a stage each (each stage solved again,
    :func:`_forward_solved`): (du, dx, nu) written to the refs ``out``, or (``add``) added to
    the step they hold (a refinement's correction). ``dims``: (N, nx, nu)."""
    N, nx, nu = dims

    def stage(t, dx):
        dx_next, du, nu_t = _forward_solved(
            list(dx),
            _load(M_ref, t, nx, nu + nx),
            _load_lower(L_ref, t, nu),
            _load(g_ref, t, nu),
            _load(r_ref, t, nx),
            functools.partial(_load_sym, P_ref, t, nx),
            _load(p_ref, t, nx),
        )
        for ref, v in zip(out, (du, dx_next, nu_t), strict=True):
            if add:
                v = [a + b for a, b in zip(_load(ref, t, len(v)), v, strict=True)]
            _store(ref, t, v)
        return tuple(dx_next)

    lax.fori_loop(0, N, stage, tuple(zero for _ in range(nx)))


def _refined_kernel(N, nx, nu, lanes, block_io, padded, model, *refs):
    """One program of :func:`apply_refined`: the step of one right-hand side, then one step of
    iterative refinement against the KKT matrix (:func:`rvdjax.solver.kkt.kkt_refine`), whose
    residual is formed stage by stage inside the sweeps instead of in a pass of its own.

    refs: M, L, P, Phi_u, Phi_x, g_u, g_x, rp; outputs du, dx, nu (the first step,
    then the refined one), and g2, p2, rp2 (the correction's right-hand side g_u, its affine
    term p and its dynamics residual, kept between its sweeps). ``model`` as :func:`_model_refs`.
    """
    refs = _model_refs(refs, model, block_io, padded)
    M_ref, L_ref, P_ref, Phu_ref, Phx_ref, gu_ref, gx_ref, rp_ref = refs[:8]
    du_ref, dx_ref, nu_ref, g2_ref, p2_ref, rp2_ref = refs[8:]
    zero = jnp.zeros((lanes,), Phx_ref.dtype)

    def backward(g_ref, p_ref, rhs, p0):
        """The backward sweep of rhs(t, M_t) -> (g_u[t], r[t], g_x[t-1]): p_{t+1} stored, and
        g_u[t] where it is formed here (``g_ref`` not None), for the forward sweep."""

        def stage(i, p):
            t = N - 1 - i
            M = _load(M_ref, t, nx, nu + nx)
            gu, r, gx_prev = rhs(t, M)
            P_of = functools.partial(_load_sym, P_ref, t, nx)  # twice: read again, cached
            p_new, _ = _backward_rhs(list(p), M, _load_lower(L_ref, t, nu), P_of, gu, r, gx_prev)
            if g_ref is not None:
                _store(g_ref, t, gu)
            _store(p_ref, t, p)
            return tuple(p_new)

        lax.fori_loop(0, N, stage, tuple(p0))

    def first_rhs(t, M):
        on = t > 0
        gx_prev = _load(gx_ref, jnp.maximum(t - 1, 0), nx)
        return _load(gu_ref, t, nu), _load(rp_ref, t, nx), [jnp.where(on, v, 0.0) for v in gx_prev]

    backward(None, nu_ref, first_rhs, _load(gx_ref, N - 1, nx))

    step = (du_ref, dx_ref, nu_ref)
    _forward_sweep((N, nx, nu), zero, M_ref, L_ref, P_ref, gu_ref, rp_ref, nu_ref, step)

    # The residual K z + (g, rp) of the first step z (kkt.kkt_residual), stage by stage.
    def r_x(t, A_next=None):
        """Phi_x dx_t + g_x + nu_t - A_{t+1}^T nu_{t+1} (``A_next`` = A_{t+1}; none at the last
        stage)."""
        Phx = _load_sym(Phx_ref, t, nx)
        g = [
            a + b for a, b in zip(_mv(Phx, _load(dx_ref, t, nx)), _load(gx_ref, t, nx), strict=True)
        ]
        out = [a + b for a, b in zip(g, _load(nu_ref, t, nx), strict=True)]
        if A_next is None:
            return out
        At_nu = _mtv(A_next, _load(nu_ref, jnp.minimum(t + 1, N - 1), nx))
        return [o - v for o, v in zip(out, At_nu, strict=True)]

    def residual_rhs(t, M):
        A, B = _split(M, nu)
        du, dx, nu_t = _load(du_ref, t, nu), _load(dx_ref, t, nx), _load(nu_ref, t, nx)
        g_u = [
            a + b
            for a, b in zip(_mv(_load_sym(Phu_ref, t, nu), du), _load(gu_ref, t, nu), strict=True)
        ]
        r_u = [a - b for a, b in zip(g_u, _mtv(B, nu_t), strict=True)]
        on = t > 0
        prev = jnp.maximum(t - 1, 0)
        dx_prev = [jnp.where(on, v, 0.0) for v in _load(dx_ref, prev, nx)]
        r_p = [
            a - b - c + d
            for a, b, c, d in zip(
                dx, _mv(B, du), _mv(A, dx_prev), _load(rp_ref, t, nx), strict=True
            )
        ]
        _store(rp2_ref, t, r_p)
        return r_u, r_p, [jnp.where(on, v, 0.0) for v in r_x(prev, A)]  # A = A_{prev + 1}

    backward(g2_ref, p2_ref, residual_rhs, r_x(N - 1))

    _forward_sweep((N, nx, nu), zero, M_ref, L_ref, P_ref, g2_ref, rp2_ref, p2_ref, step, True)


def _compiler_params(cfg: KernelConfig):
    if cfg.interpret:
        return None
    from jax.experimental.pallas import triton as pltr

    return pltr.CompilerParams(num_warps=cfg.num_warps, num_stages=1)


def tile(b: int, block: int) -> tuple[int, int]:
    """(problems a program, the batch padded to whole programs) for a batch of ``b``: tiles
    of ``block`` problems, or, for a batch smaller than a tile, one tile of the next power of
    two (Triton's blocks are powers of two). A problem alone is a tile of one: every launch
    of a padded batch pads each input and slices each output, 59 launches an iteration of
    one fastmpc-3d QP beside the kernels' 8 (``sweeps/gpu_traffic.py solve --batch 1``)."""
    lanes = min(block, 1 << max(b - 1, 0).bit_length())
    return lanes, -(-b // lanes) * lanes


def _pad(a, b_pad):
    """Pad the trailing batch axis to ``b_pad`` by repeating the last problem (padding lanes
    then compute a real problem's numbers: no NaN, nothing to mask)."""
    b = a.shape[-1]
    if b == b_pad:
        return a
    return jnp.concatenate([a, jnp.broadcast_to(a[..., -1:], (*a.shape[:-1], b_pad - b))], -1)


def _call(
    cfg: KernelConfig, factorise: bool, with_rhs: bool, M, mats, rhs, refine=False, index=None
):
    """The kernel's launch. ``M``: the stages' [B, A] of each problem (N, nx, nu + nx, b), of
    all (N, nx, nu + nx), or (``index``, (b,) int) a table (K, N, nx, nu + nx) of K models
    and the one each problem runs."""
    from jax.experimental import pallas as pl

    tabled = index is not None
    if tabled:
        M_table, M = M, M[0]
    N, nx, nu = M.shape[0], M.shape[1], M.shape[2] - M.shape[1]
    b = mats[-1].shape[-1]
    block_io = cfg.block_io and (factorise or cfg.solve_block_io)
    lanes, b_pad = tile(b, cfg.block)
    model_batched = M.ndim == 4
    if model_batched:
        M = _pad(M, b_pad)
    mats = [_pad(m, b_pad) for m in mats]
    rhs = [_pad(r, b_pad) for r in rhs]
    dtype = mats[-1].dtype

    def spec(shape, batched=True):
        n = len(shape)
        if not batched:
            return pl.BlockSpec(tuple(shape), lambda i: (0,) * n)
        return pl.BlockSpec((*shape[:-1], lanes), lambda i: (0,) * (n - 1) + (i,))

    out_shapes = []
    if factorise:  # L and P as their lower triangles (pack)
        out_shapes += [(N, tri_size(nu)), (N, tri_size(nx))]
    if with_rhs:
        out_shapes += [(N, nu), (N, nx), (N, nx)]
    if refine:  # the correction's g_u, p and dynamics residual between its sweeps
        out_shapes += [(N, nu), (N, nx), (N, nx)]
    entries = [s[1:] for s in out_shapes]
    padded = cfg.padded_blocks
    if block_io:  # [stage][entry][problem] (the entries padded to a power of two: padded)
        flat = functools.partial(_flat, padded=padded)
        M = flat(M) if model_batched else M
        mats, rhs = [flat(m) for m in mats], [flat(r) for r in rhs]
        out_shapes = [(N, _entries(math.prod(e), padded)) for e in entries]
    out_shapes = [jax.ShapeDtypeStruct((*s, b_pad), dtype) for s in out_shapes]
    model = "tabled" if tabled else "batched" if model_batched else "shared"
    ins = [M, *mats, *rhs]
    specs = [spec(M.shape, model_batched)] + [spec(a.shape) for a in ins[1:]]
    if tabled:  # the table, flattened as a block array's stages are, then the indices
        K = M_table.shape[0]
        M_table = M_table.reshape(K, N, nx * (nu + nx)) if block_io else M_table
        ins = [M_table, _pad(index.astype(jnp.int32), b_pad), *ins[1:]]
        specs = [spec(M_table.shape, False), spec((b_pad,)), *specs[1:]]
    if refine:
        kernel = functools.partial(_refined_kernel, N, nx, nu, lanes, block_io, padded, model)
    else:
        model_only = block_io and cfg.model_blocks_only
        kernel = functools.partial(
            _kernel, N, nx, nu, lanes, with_rhs, factorise, block_io, padded, model, model_only
        )
    res = pl.pallas_call(
        kernel,
        out_shape=out_shapes,
        grid=(b_pad // lanes,),
        in_specs=specs,
        out_specs=[spec(s.shape) for s in out_shapes],
        interpret=cfg.interpret,
        compiler_params=_compiler_params(cfg),
        name="rvdjax_riccati"
        + ("_factor" if factorise else "")
        + ("_solve" if with_rhs else "")
        + ("_refined" if refine else ""),
    )(*ins)
    if refine:
        res, entries = res[:3], entries[:3]
    if block_io:
        res = [
            r[:, : math.prod(e)].reshape(N, *e, b_pad) for r, e in zip(res, entries, strict=True)
        ]
    return [r[..., :b] for r in res]


def _entries(n: int, padded: bool) -> int:
    """Entries a stage of a block array holds: n, or n padded to a power of two."""
    return 1 << (n - 1).bit_length() if padded else n


def _flat(a, padded: bool = False):
    """(N, entries..., b) -> (N, E, b): a reshape, or a padded copy (``padded``)."""
    e = math.prod(a.shape[1:-1])
    a = a.reshape(a.shape[0], e, a.shape[-1])
    return jnp.pad(a, ((0, 0), (0, _entries(e, padded) - e), (0, 0)))


def factor(M, Phi_u, Phi_x, cfg: KernelConfig = KernelConfig(), index=None):
    """Backward Riccati factorisation: (L, P), each ``[stage][entry][problem]``, L
    and P as their lower triangles (:func:`pack`; :func:`unpack` gives the matrices).

    Args:
        M: (N, nx, nu + nx[, b]) the stages' [B_t, A_t] (no batch axis: shared), or with
            ``index`` a table (K, N, nx, nu + nx) of K models.
        Phi_u: (N, tri(nu), b), Phi_x: (N, tri(nx), b) the Hessian blocks' lower triangles
            (:func:`tri_pack`; symmetric, so nothing is lost).
        index: (b,) int, the model of each problem in the table ``M`` (the same arithmetic
            as ``M[index]`` moved batch last, without that copy).
    """
    return tuple(_call(cfg, True, False, M, [Phi_u, Phi_x], [], index=index))


def factor_solve(M, Phi_u, Phi_x, g_u, g_x, rp, cfg: KernelConfig = KernelConfig(), index=None):
    """Factorisation and the step of one right-hand side in one kernel:
    ((L, P), (du, dx, nu)); g_u (N, nu, b), g_x and rp (N, nx, b); ``M`` and
    ``index`` as :func:`factor`."""
    out = _call(cfg, True, True, M, [Phi_u, Phi_x], [g_u, g_x, rp], index=index)
    return tuple(out[:2]), tuple(out[2:])


def apply(M, L, P, g_u, g_x, rp, cfg: KernelConfig = KernelConfig(), index=None):
    """The step (du, dx, nu) of one right-hand side with a stored factorisation (L,
    P as :func:`factor` returns them, packed; ``M`` and ``index`` as :func:`factor`)."""
    return tuple(_call(cfg, False, True, M, [L, P], [g_u, g_x, rp], index=index))


def apply_refined(
    M, L, P, Phi_u, Phi_x, g_u, g_x, rp, cfg: KernelConfig = KernelConfig(), index=None
):
    """The step (du, dx, nu) of one right-hand side with a stored factorisation (packed, as
    :func:`factor` returns it), plus one step of iterative refinement
    (:func:`rvdjax.solver.kkt.kkt_refine`) in the same kernel: the residual needs the Hessian
    blocks Phi_u and Phi_x too, as :func:`factor` takes them (``M`` and ``index`` as
    :func:`factor`)."""
    mats = [L, P, Phi_u, Phi_x]
    return tuple(_call(cfg, False, True, M, mats, [g_u, g_x, rp], True, index=index))
