"""One stage of the Riccati recursion's sweeps, over lane vectors: the factorisation's
stage, the backward sweep's affine term and the forward sweep's step (the kernels' and the
unrolled form's, :mod:`rvdjax.solver.unrolled`)."""

from __future__ import annotations

from rvdjax.solver.lanes.algebra import (
    _add,
    _chol_solve_mat,
    _mm,
    _mtm,
    _mtv,
    _mv,
    _sym,
    chol,
    chol_solve,
)


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
    # one refinement of K against H (the reason is in rvdjax.solver.riccati.recursion._factor)
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
    (:func:`rvdjax.solver.riccati.recursion._apply`)."""
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
