"""Thruster allocation (rvdjax.actuators.allocation) against scipy's HiGHS LP solver."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from scipy.optimize import linprog

import rvdjax  # noqa: F401  (float64)
from rvdjax.actuators.allocation import allocate, allocate_pairs

# one compilation per (k, T), reused by every test: vmapped over demands, and over everything
_BATCH = jax.jit(jax.vmap(allocate, in_axes=(None, 0, None)))
_FULL = jax.jit(jax.vmap(allocate))
_PAIRS = jax.jit(jax.vmap(allocate_pairs, in_axes=(0, None, None)))

_HIGHS = {"primal_feasibility_tolerance": 1e-10, "dual_feasibility_tolerance": 1e-10}


def _spot():
    """SPOT-like planar vehicle: 8 thrusters on a 0.3 m square, demand (Fx, Fy, torque_z)."""
    pos = np.array(
        [
            [0.15, 0.083],
            [0.15, -0.083],
            [-0.15, 0.083],
            [-0.15, -0.083],
            [0.083, 0.15],
            [-0.083, 0.15],
            [0.083, -0.15],
            [-0.083, -0.15],
        ]
    )
    u = np.array([[-1, 0], [-1, 0], [1, 0], [1, 0], [0, -1], [0, -1], [0, 1], [0, 1]], float)
    M = np.vstack([u.T, pos[:, 0] * u[:, 1] - pos[:, 1] * u[:, 0]])
    return M, np.full(8, 0.15)


def _axis_set():
    """Six thrusters +x, -x, +y, -y, +z, -z through the centre of mass."""
    return np.kron(np.eye(3), np.array([[1.0, -1.0]]))


def _reference(M, d, F):
    """(s*, min sum f) by HiGHS: max s s.t. M f = s d, then min sum f s.t. M f = s* d."""
    k, T = M.shape
    bounds = [(0.0, Fi) for Fi in F]
    r1 = linprog(
        np.r_[np.zeros(T), -1.0],
        A_eq=np.c_[M, -d],
        b_eq=np.zeros(k),
        bounds=[*bounds, (0.0, 1.0)],
        method="highs",
        options=_HIGHS,
    )
    assert r1.status == 0, r1.message
    s = r1.x[-1]
    r2 = linprog(np.ones(T), A_eq=M, b_eq=s * d, bounds=bounds, method="highs", options=_HIGHS)
    if r2.status != 0:  # s* d on the boundary, infeasible by rounding: relax s by 1e-9
        r2 = linprog(
            np.r_[np.ones(T), 0.0],
            A_eq=np.c_[M, -d],
            b_eq=np.zeros(k),
            bounds=[*bounds, (s * (1.0 - 1e-9), s)],
            method="highs",
            options=_HIGHS,
        )
        assert r2.status == 0, r2.message
    return s, r2.fun


def _check(M, D, F, out, f_tol=1e-10):
    """The allocation is feasible and its s and sum f are HiGHS's optimum."""
    M, D, F = (np.broadcast_to(np.asarray(a), shape) for a, shape in _shapes(M, D, F))
    f, s = np.asarray(out.f), np.asarray(out.scale)
    assert np.all(np.isfinite(f)) and np.all(np.isfinite(s))
    assert np.all(f >= 0.0) and np.all(f <= F)
    assert np.all(s >= 0.0) and np.all(s <= 1.0)
    np.testing.assert_allclose(np.einsum("bkt,bt->bk", M, f), s[:, None] * D, rtol=0, atol=f_tol)
    ref = [_reference(Mi, di, Fi) for Mi, di, Fi in zip(M, D, F, strict=True)]
    s_ref = np.array([r[0] for r in ref])
    obj_ref = np.array([r[1] for r in ref])
    np.testing.assert_allclose(s, s_ref, rtol=0, atol=1e-8)
    np.testing.assert_allclose(f.sum(axis=1), obj_ref, rtol=1e-8, atol=1e-12)
    return s_ref


def _shapes(M, D, F):
    n = np.shape(D)[0]
    k, T = np.shape(M)[-2:]
    return ((M, (n, k, T)), (D, (n, k)), (F, (n, T)))


def _demands(rng, n, scale, spread, sparse=0.2):
    """n random demands, components scaled by ``scale``; a fraction has zero components."""
    D = rng.normal(size=(n, len(scale))) * scale * rng.uniform(0.0, spread, (n, 1))
    zero = rng.uniform(size=D.shape) < 0.5
    zero[rng.uniform(size=n) > sparse] = False
    return np.where(zero, 0.0, D)


def test_spot_matches_linprog():
    M, F = _spot()
    D = _demands(np.random.default_rng(0), 1000, np.array([0.3, 0.3, 0.025]), 1.3)
    s_ref = _check(M, D, F, _BATCH(M, D, F))
    assert 0.2 < np.mean(s_ref < 1.0 - 1e-9) < 0.5  # saturated and unsaturated demands


def test_spot_failed_thruster_matches_linprog():
    M, F = _spot()
    F = F.copy()
    F[3] = 0.0
    D = _demands(np.random.default_rng(1), 200, np.array([0.3, 0.3, 0.025]), 1.3)
    out = _BATCH(M, D, F)
    s_ref = _check(M, D, F, out)
    assert np.all(np.asarray(out.f)[:, 3] == 0.0)
    assert 0.2 < np.mean(s_ref < 1.0 - 1e-9) < 0.8


def test_random_3d_twelve_thrusters_match_linprog():
    rng = np.random.default_rng(2)
    M = rng.normal(size=(3, 12))
    M /= np.linalg.norm(M, axis=0)
    F = rng.uniform(0.5, 1.5, 12)
    D = _demands(rng, 200, np.ones(3), 3.5)
    s_ref = _check(M, D, F, _BATCH(M, D, F))
    assert 0.2 < np.mean(s_ref < 1.0 - 1e-9) < 0.8


def test_planar_forces_match_linprog():
    rng = np.random.default_rng(3)
    M = rng.normal(size=(2, 5))
    F = rng.uniform(0.2, 1.0, 5)
    D = _demands(rng, 200, np.ones(2), 3.0)
    s_ref = _check(M, D, F, _BATCH(M, D, F))
    assert 0.2 < np.mean(s_ref < 1.0 - 1e-9) < 0.8


def test_axis_pairs_closed_form_matches_allocate_and_linprog():
    rng = np.random.default_rng(4)
    M = _axis_set()
    F_pos, F_neg = rng.uniform(0.5, 1.0, 3), rng.uniform(0.5, 1.0, 3)
    F_neg[1] = 0.0  # -y failed
    F = np.stack([F_pos, F_neg], axis=1).reshape(-1)
    D = _demands(rng, 200, np.ones(3), 2.0)
    pairs = _PAIRS(D, F_pos, F_neg)
    general = _BATCH(M, D, F)
    s_ref = _check(M, D, F, pairs, f_tol=1e-12)
    np.testing.assert_allclose(pairs.f, general.f, rtol=0, atol=1e-12)
    np.testing.assert_allclose(pairs.scale, general.scale, rtol=0, atol=1e-12)
    assert np.any(s_ref == 0.0) and 0.2 < np.mean(s_ref < 1.0 - 1e-9) < 0.9
    # the closed form itself: one thruster per axis, s = min(1, min F_axis / |d_axis|)
    d = np.array([0.5, -2.0, 0.0])
    one = allocate_pairs(d, np.ones(3), np.ones(3))
    np.testing.assert_allclose(one.scale, 0.5)
    np.testing.assert_allclose(one.f, [0.25, 0.0, 0.0, 1.0, 0.0, 0.0])
    zero = allocate_pairs(np.zeros(3), np.ones(3), np.zeros(3))
    np.testing.assert_array_equal(zero.f, 0.0)
    np.testing.assert_array_equal(zero.scale, 1.0)


def test_zero_demand_and_degenerate_inputs():
    """d = 0 gives f = 0, s = 1; zero columns, failed thrusters, rank-deficient M, duplicate
    columns: no NaN, and still HiGHS's optimum (vmapped over M, d and F)."""
    rng = np.random.default_rng(5)
    M, F = _spot()
    no_torque = M.copy()
    no_torque[2] = 0.0  # rank 2: every thruster through the centre of mass
    dead = M.copy()
    dead[:, [1, 6]] = 0.0  # zero columns
    twin = M.copy()
    twin[:, 2] = twin[:, 3]  # duplicate columns
    line = np.outer([1.0, 0.0, 0.1], np.where(np.arange(8) % 2, 1.0, -1.0))  # rank 1
    cases = [
        (no_torque, F),
        (dead, F),
        (twin, np.where(np.arange(8) == 5, 0.0, F)),
        (line, F),
        (np.zeros_like(M), F),
        (M, np.zeros(8)),
        (M, np.where(np.arange(8) < 4, F, 0.0)),  # no y authority
    ]
    Ms, Fs, Ds = [], [], []
    for Mi, Fi in cases:
        D = _demands(rng, 12, np.array([0.3, 0.3, 0.025]), 1.5, sparse=0.5)
        D[0] = 0.0
        D[1] = Mi @ (Fi * rng.uniform(0.0, 1.0, 8))  # attainable, also for a rank-deficient M
        D[2] = 1e3 * D[1] + 1e-3 * rng.normal(size=3)  # far out, a little off the range
        Ms += [Mi] * len(D)
        Fs += [Fi] * len(D)
        Ds.append(D)
    Ms, Fs, Ds = np.array(Ms), np.array(Fs), np.concatenate(Ds)
    out = _FULL(Ms, Ds, Fs)
    _check(Ms, Ds, Fs, out)
    np.testing.assert_array_equal(np.asarray(out.scale)[::12], 1.0)  # d = 0


if __name__ == "__main__":
    pytest.main([__file__, "-q"])
