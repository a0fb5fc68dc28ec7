"""The structured KKT solve: the same step unbatched, in small batches (batch-last elementwise
form), in large batches (batch first) and with a shared model; derivatives of the dot form."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rvdjax.solver import kkt as K
from rvdjax.solver import lanes
from rvdjax.solver.riccati import BATCH_LAST_MAX

N, NX, NU = 6, 4, 2


def _problems(batch, seed=0):
    rng = np.random.default_rng(seed)

    def spd(n):
        X = rng.standard_normal((batch, N, n, n))
        return X @ np.swapaxes(X, -1, -2) + n * np.eye(n)

    A = np.eye(NX) + 0.2 * rng.standard_normal((batch, N, NX, NX))
    B = rng.standard_normal((batch, N, NX, NU))
    vec = lambda n: rng.standard_normal((batch, N, n))  # noqa: E731
    return tuple(jnp.asarray(a) for a in (A, B, spd(NU), spd(NX), vec(NU), vec(NX), vec(NX)))


def _dense_matrix(A, B, Phi_u, Phi_x):
    """The KKT matrix assembled densely in NumPy, unknowns (u_0, x_1, u_1, ..., nu)."""
    A, B, Phi_u, Phi_x = (np.asarray(a) for a in (A, B, Phi_u, Phi_x))
    ns = NU + NX
    nz = N * ns
    H = np.zeros((nz, nz))
    C = np.zeros((N * NX, nz))
    for t in range(N):
        z = slice(t * ns, t * ns + NU), slice(t * ns + NU, (t + 1) * ns)
        H[z[0], z[0]], H[z[1], z[1]] = Phi_u[t], Phi_x[t]
        C[t * NX : (t + 1) * NX, z[0]] = -B[t]
        C[t * NX : (t + 1) * NX, z[1]] = np.eye(NX)
        if t > 0:
            C[t * NX : (t + 1) * NX, (t - 1) * ns + NU : t * ns] = -A[t]
    return np.block([[H, C.T], [C, np.zeros((N * NX, N * NX))]])


def _dense_kkt(A, B, Phi_u, Phi_x, g_u, g_x, rp):
    """The KKT system assembled densely in NumPy and solved by LAPACK: the reference."""
    KKT = _dense_matrix(A, B, Phi_u, Phi_x)
    nz = N * (NU + NX)
    ns = NU + NX
    g = np.concatenate([np.asarray(g_u), np.asarray(g_x)], axis=1).reshape(-1)
    sol = np.linalg.solve(KKT, -np.concatenate([g, np.asarray(rp).reshape(-1)]))
    dz = sol[:nz].reshape(N, ns)
    return dz[:, :NU], dz[:, NU:], sol[nz:].reshape(N, NX)


def _solve(A, B, Phi_u, Phi_x, g_u, g_x, rp, kernel="auto"):
    """The factorisation and a first step in one call, then a second right-hand side with
    the stored factorisation: the two ways the solver uses the recursion."""
    f, s1 = K.riccati_factor_solve(A, B, Phi_u, Phi_x, g_u, g_x, rp, kernel)
    s2 = K.riccati_apply(K.riccati_factor(A, B, Phi_u, Phi_x, kernel), g_u, g_x, rp, kernel)
    return K.NewtonStep(*(0.5 * (a + b) for a, b in zip(s1, s2, strict=True))), s1, s2


def _compiled(kernel):
    fn = functools.partial(_solve, kernel=kernel)
    return (
        jax.jit(fn),
        jax.jit(jax.vmap(fn)),
        jax.jit(jax.vmap(fn, in_axes=(None, None, 0, 0, 0, 0, 0))),
    )


FORMS = {k: _compiled(k) for k in ("xla", "pallas-block-factor")}


@pytest.fixture(autouse=True, scope="module")
def _small_tiles():
    """Every kernel of this module traced with tiles of 8 lanes. Set once for the module: a
    change of the launch configuration clears JAX's caches, and with them every program the
    module (and the library's setup code) compiled before it."""
    with lanes.configured(block=8):
        yield


@pytest.mark.parametrize(
    "kernel, batch", [("xla", 3), ("xla", BATCH_LAST_MAX + 5), ("pallas-block-factor", 11)]
)
def test_every_form_solves_the_kkt_system(kernel, batch):
    """Unbatched, a small batch (XLA: batch last) and a large one (XLA: batch first, above
    BATCH_LAST_MAX; the GPU kernels, interpreted, the factorisation in blocks and the solves
    entry by entry as the default GPU form runs them: more than one tile of lanes, the last
    padded) against the dense NumPy solve, for the fused
    factorisation + step and for a step with a stored factorisation; a model shared by the batch
    gives the same steps as the model repeated per problem."""
    SOLVE, SOLVE_BATCH, SOLVE_SHARED = FORMS[kernel]
    data = _problems(batch)
    out = SOLVE_BATCH(*data)  # the kernels: two tiles of 8 lanes, the last padded
    for i in (0, batch - 1):
        ref = _dense_kkt(*(a[i] for a in data))
        one = SOLVE(*(a[i] for a in data))
        for step, single in zip(out, one, strict=True):
            for got, s, want in zip(step, single, ref, strict=True):
                np.testing.assert_allclose(np.asarray(got[i]), want, rtol=1e-9, atol=1e-9)
                np.testing.assert_allclose(np.asarray(s), want, rtol=1e-9, atol=1e-9)
    A, B = data[0][0], data[1][0]
    shared = SOLVE_SHARED(A, B, *data[2:])[0]
    repeated = SOLVE_BATCH(
        jnp.broadcast_to(A, data[0].shape), jnp.broadcast_to(B, data[1].shape), *data[2:]
    )[0]
    for a, b in zip(shared, repeated, strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-12)


def test_derivatives_match_central_differences_batched_or_not():
    """Reverse mode goes through the dot form's derivative (custom_jvp); central differences
    of the solve itself (whichever form runs) agree, alone and under vmap."""
    data = _problems(2, seed=1)

    def loss(scale, args):
        A, B, Phi_u, Phi_x, g_u, g_x, rp = args
        step = _solve(A, B, Phi_u * scale, Phi_x, g_u, g_x, rp)[0]
        return jnp.sum(step.du**2) + jnp.sum(step.dx * step.nu)

    one = tuple(a[0] for a in data)
    g = float(jax.grad(loss)(1.3, one))
    h = 1e-5
    fd = (float(loss(1.3 + h, one)) - float(loss(1.3 - h, one))) / (2 * h)
    assert g == pytest.approx(fd, rel=1e-6)
    g_batch = jax.vmap(jax.grad(loss), in_axes=(None, 0))(1.3, data)
    assert float(g_batch[0]) == pytest.approx(g, rel=1e-10)


def test_residual_and_refinement_against_the_dense_system():
    """kkt_residual is the dense KKT matrix times the step plus the right-hand side; one
    refinement step takes a perturbed solution back to the dense solve's."""
    A, B, Phi_u, Phi_x, g_u, g_x, rp = (a[0] for a in _problems(1, seed=2))
    kkt = K.kkt_factor(A, B, Phi_u, Phi_x, "riccati")
    rng = np.random.default_rng(3)
    z = K.NewtonStep(*(jnp.asarray(rng.standard_normal(s)) for s in ((N, NU), (N, NX), (N, NX))))
    r_u, r_x, r_p = K.kkt_residual(kkt, g_u, g_x, rp, z)
    flat = np.concatenate([np.concatenate([z.du, z.dx], axis=1).reshape(-1), np.ravel(z.nu)])
    g = np.concatenate([np.asarray(g_u), np.asarray(g_x)], axis=1).reshape(-1)
    want = _dense_matrix(A, B, Phi_u, Phi_x) @ flat + np.concatenate([g, np.ravel(rp)])
    got = np.concatenate([np.concatenate([r_u, r_x], axis=1).reshape(-1), np.ravel(r_p)])
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)

    ref = _dense_kkt(A, B, Phi_u, Phi_x, g_u, g_x, rp)
    off = K.NewtonStep(*(jnp.asarray(w) * (1 + 1e-4 * rng.standard_normal(w.shape)) for w in ref))
    fixed = K.kkt_refine(kkt, g_u, g_x, rp, off, "riccati")
    for a, want in zip(fixed, ref, strict=True):
        np.testing.assert_allclose(np.asarray(a), want, rtol=1e-9, atol=1e-9)


def test_block_chunks_cover_every_entry():
    """The block kernels read and write a stage of E entries as they are, in at most two
    overlapping power-of-two chunks (lanes.refs._chunks): every entry covered, none past the end.
    The solver's iterates with these kernels are test_kernels.py's; the same numbers as the
    padded form, to the bit, the slow test below."""
    for e in range(1, 70):
        chunks = lanes.refs._chunks(e)
        assert len(chunks) <= 2
        assert all(s & (s - 1) == 0 and 0 <= o and o + s <= e for o, s in chunks)
        assert set().union(*(range(o, o + s) for o, s in chunks)) == set(range(e))


def test_factor_storage_keeps_the_lower_triangles():
    """The kernels store L and P as their lower triangles, row by row (lanes.pack): the
    entries land where the kernels' loads look for them (P[2][1] is entry 4 of 21), and
    unpack gives back a symmetric P and a lower L exactly, the matrices last (as the XLA
    forms' factor carries them beside the matrices) or batch last. That the kernels' solves
    with the packed factorisation agree with XLA's to rounding is test_kernels.py's."""
    rng = np.random.default_rng(5)
    N, nx, nu, b = 2, 6, 3, 4
    X = rng.standard_normal((N, nx, nx, b))
    P = jnp.asarray(X + np.swapaxes(X, 1, 2))
    L = jnp.asarray(np.tril(rng.standard_normal((N, b, nu, nu))).transpose(0, 2, 3, 1))
    packed = lanes.pack(L, P)
    assert packed[0].shape == (N, 6, b) and packed[1].shape == (N, 21, b)
    np.testing.assert_array_equal(np.asarray(packed[1][:, 4]), np.asarray(P[:, 2, 1]))
    np.testing.assert_array_equal(np.asarray(packed[0][:, 5]), np.asarray(L[:, 2, 2]))
    for got, want in zip(lanes.unpack(*packed), (L, P), strict=True):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    first = lanes.tri_pack(jnp.moveaxis(P, -1, 0))  # (b, N, 21): the matrices' axes last
    np.testing.assert_array_equal(np.asarray(first), np.moveaxis(np.asarray(packed[1]), -1, 0))
    # the kernels' reads of a stage (here from the arrays themselves)
    P_t, L_t = lanes.refs._load_sym(packed[1], 1, nx), lanes.refs._load_lower(packed[0], 1, nu)
    np.testing.assert_array_equal(np.stack([np.stack(r) for r in P_t]), np.asarray(P[1]))
    assert all(L_t[i][j] is None for i in range(nu) for j in range(i + 1, nu))
    for i in range(nu):
        for j in range(i + 1):
            np.testing.assert_array_equal(np.asarray(L_t[i][j]), np.asarray(L[1, i, j]))


@pytest.mark.slow  # interpreted kernels, 15 s
def test_block_kernels_read_and_write_the_arrays_as_they_are():
    """The block kernels on the arrays as they are give the numbers of the form that pads every
    array to a power of two of entries, to the bit: the factorisation, a step with it stored
    and both in one kernel, the model per problem or shared (interpreted; fastmpc-3d's stage
    sizes, none of them a power of two)."""
    n, nx, nu, b = 3, 6, 3, 8
    rng = np.random.default_rng(3)

    def spd(k):
        X = rng.standard_normal((n, b, k, k))
        return jnp.asarray(np.moveaxis(X @ np.swapaxes(X, -1, -2) + k * np.eye(k), 1, -1))

    A = np.eye(nx)[None, :, :, None] + 0.2 * rng.standard_normal((n, nx, nx, b))
    M = jnp.asarray(np.concatenate([rng.standard_normal((n, nx, nu, b)), A], 2))
    mats = tuple(lanes.tri_pack(spd(k), 1) for k in (nu, nx))  # the kernels' storage
    rhs = tuple(jnp.asarray(rng.standard_normal((n, k, b))) for k in (nu, nx, nx))

    def run(padded, model):
        cfg = lanes.KernelConfig(block=b, interpret=True, block_io=True, padded_blocks=padded)
        f = lanes.factor(model, *mats, cfg=cfg)
        return (
            f,
            lanes.apply(model, *f, *rhs, cfg=cfg),
            lanes.factor_solve(model, *mats, *rhs, cfg=cfg),
        )

    for model in (M, M[..., 0]):
        got, want = run(False, model), run(True, model)
        for g, w in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
            np.testing.assert_array_equal(np.asarray(g), np.asarray(w))


def _refined(kernel, axes=None):
    fn = functools.partial(K.kkt_solve_refined, method="riccati", kernel=kernel)
    return jax.jit(fn if axes is None else jax.vmap(fn, in_axes=(axes, 0, 0, 0)))


@pytest.mark.parametrize("shared", [False, True])
def test_the_corrector_step_and_its_refinement_in_one_kernel(shared):
    """``kkt_solve_refined``: a step and one step of iterative refinement. With the kernel
    that forms the refinement's residual inside its sweeps ("pallas-rows", as the default on a
    GPU runs it, entry by entry, interpreted: two tiles of 8 lanes, the last padded; and one problem
    alone), the model
    per problem or shared by the batch, it gives XLA's two solves with the residual between
    them to 1e-12, and the dense solve to 1e-9, from a factorisation whose first step is
    about 1e-8 off."""
    batch = 11
    data = _problems(batch, seed=4)
    if shared:
        data = (data[0][:1].repeat(batch, 0), data[1][:1].repeat(batch, 0), *data[2:])
    kkt = jax.vmap(lambda A, B, Pu, Px: K.kkt_factor(A, B, Pu, Px, "riccati", "xla"))(*data[:4])
    # The cost-to-go P perturbed by 1e-8 (symmetrically: the kernels read its lower triangle,
    # XLA's loops all of it; the kernels' solves read no gain): every form's first step is
    # then off by about that much and the refinement moves it (a kernel that skipped it would
    # fail by 1e-8). P is in every stage of both sweeps: perturbed by 1e-7, one refinement
    # step left the two forms 2e-12 apart, the square of a worse preconditioner.
    f = kkt.factor
    c = np.cos(np.arange(f.P.shape[-1]))
    kkt = kkt._replace(factor=f._replace(P=f.P * (1 + 1e-8 * (c[:, None] + c[None, :]))))
    model = None if shared else 0
    if shared:  # one model for the batch, as the engine's slots share it
        kkt = kkt._replace(A=kkt.A[0], B=kkt.B[0], factor=kkt.factor._replace(M=kkt.factor.M[0]))
    axes = K.KKT(model, model, 0, 0, K.RiccatiFactor(model, 0, 0, 0))
    rhs = data[4:]
    got = _refined("pallas-rows", axes)(kkt, *rhs)
    first = jax.tree.map(lambda a, x: a if x is None else a[x], kkt, axes)
    alone = _refined("pallas-rows")(first, *(r[0] for r in rhs))
    want = _refined("xla", axes)(kkt, *rhs)
    plain = jax.vmap(
        functools.partial(K.kkt_solve, method="riccati", kernel="xla"), (axes, 0, 0, 0)
    )
    assert np.max(np.abs(np.asarray(plain(kkt, *rhs).du - want.du))) > 1e-9  # it moved
    for g, a, w in zip(got, alone, want, strict=True):
        np.testing.assert_allclose(np.asarray(g), np.asarray(w), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(np.asarray(a), np.asarray(w[0]), rtol=1e-12, atol=1e-12)
    for i in (0, batch - 1):
        ref = _dense_kkt(*(a[i] for a in data))
        for g, r in zip(got, ref, strict=True):
            np.testing.assert_allclose(np.asarray(g[i]), r, rtol=1e-9, atol=1e-9)


def test_the_refined_step_differentiates_as_its_dot_form():
    """Reverse mode through ``riccati_apply_refined`` (the kernel interpreted, or XLA's
    loops) is the derivative of the dot form of the two solves and the residual: central
    differences of the step itself agree."""
    A, B, Phi_u, Phi_x, g_u, g_x, rp = (a[0] for a in _problems(1, seed=5))
    f = K.riccati_factor(A, B, Phi_u, Phi_x, "xla")

    def loss(scale, kernel):
        s = K.riccati_apply_refined(f, Phi_u, Phi_x, g_u * scale, g_x, rp, kernel)
        return jnp.sum(s.du**2) + jnp.sum(s.dx * s.nu)

    h = 1e-5
    for kernel in ("xla", "pallas-rows"):  # "unrolled": test_kernels' gradient check
        g = float(jax.grad(loss)(1.3, kernel))
        fd = (float(loss(1.3 + h, kernel)) - float(loss(1.3 - h, kernel))) / (2 * h)
        assert g == pytest.approx(fd, rel=1e-6), kernel


@pytest.mark.parametrize("shared", [False, True])
def test_the_kernels_factor_carries_the_gain_they_do_not_store(shared):
    """The kernels store L and P alone and solve without the gain; the factor they return
    still carries K = -H^-1 B^T P A, formed from their storage, for any other use: XLA's
    K (refined once against H), L and P to 1e-10, the model per problem or shared."""
    batch = 5
    A, B, Phi_u, Phi_x = _problems(batch, seed=8)[:4]
    axes = (None, None, 0, 0) if shared else (0, 0, 0, 0)
    if shared:
        A, B = A[0], B[0]

    def factor(kernel):
        fn = lambda a, b, pu, px: K.riccati_factor(a, b, pu, px, kernel)  # noqa: E731
        return jax.jit(jax.vmap(fn, in_axes=axes))(A, B, Phi_u, Phi_x)

    got = factor("pallas-entries")
    want = factor("xla")
    assert got.Lp is not None  # the kernels' storage came back with it
    for name in ("K", "L", "P"):
        np.testing.assert_allclose(
            np.asarray(getattr(got, name)), np.asarray(getattr(want, name)), rtol=1e-10, atol=1e-10
        )
