"""Thruster allocation: exact, direction-preserving, least-thrust forces for on/off thrusters.

A set of T thrusters has the effectiveness matrix ``M`` (k, T): column i is the body-frame
force (and torque) that thruster i gives per newton of thrust (k = 2 or 3: e.g. (Fx, Fy),
(Fx, Fy, torque_z) or (Fx, Fy, Fz)). Thruster i delivers a thrust ``0 <= f_i <= F_i`` [N]
(``F_i = 0``: failed or unavailable). For a demand ``d`` (k,) [N, N m] :func:`allocate` returns

1. if ``d`` is attainable, the least total thrust meeting it exactly::

       min sum(f)  s.t.  M f = d,  0 <= f <= F

2. otherwise (saturation) the largest fraction ``s`` of the demand that can be met in the
   demand's own direction, then the least total thrust meeting ``s d``::

       s* = max s  s.t.  M f = s d,  0 <= f <= F,  0 <= s <= 1
       min sum(f)  s.t.  M f = s* d,  0 <= f <= F

Both cases are one lexicographic LP over x = (f, s): minimise ``-s`` first and ``sum(f)``
second subject to ``M f - s d = 0`` and the bounds (``s = 1`` whenever ``d`` is attainable).

Algorithm (exact, fixed shape, jittable and vmappable). The LP is solved by enumerating its
bases; the k x k basis matrices are inverted in closed form (k <= 3). The columns are those of
``[M, -d, m I]``: the k extra columns (``m = max |M|``) belong to artificial variables fixed at
0, so the LP and its solutions are unchanged but a nonsingular basis always exists, also for a
rank-deficient ``M``. For every basis B the duals of the three stacked costs
``c1 = -e_s``, ``c2 = (1, .., 1, 0, 0..)`` (total thrust) and ``c3`` (fixed generic numbers, a
symbolic tie-break) give lexicographic reduced costs ``r(eps) = r1 + eps r2 + eps^2 r3``; each
non-basic variable is put at its upper bound if ``r(eps) < 0`` for small ``eps > 0`` and at 0
otherwise (reduced costs within a rounding tolerance of 0 count as 0 and defer to the next
level). The basic variables then follow from ``B x_B = -A_N x_N``. Every candidate built this
way is dual feasible for the cost ``c1 + eps c2 + eps^2 c3`` by construction, so a candidate
that is also primal feasible (bounds respected) is optimal for that cost for all small
``eps``, hence lexicographically optimal: it maximises s and then minimises sum(f). Such a
candidate exists because the perturbed LP is feasible (x = 0), bounded and, ``c3`` being
generic, dual non-degenerate, so its optimal basis with its (unique) bound pattern is among the
candidates. The candidate with the least bound violation is returned (clipped to the bounds,
which moves it by rounding errors only). The cost is ``C(T + 1 + k, k)`` basis solves (220 for
T = 8, k = 3; 560 for T = 12, k = 3) of O((T + k) k) operations each, with no iterations. In
the bases without s (``C(T + k, k)`` of them) the level-1 duals are 0, so s sits at 1 and the
bound pattern and the basis inverse depend on ``M`` and ``F`` only: vmapped over ``d`` alone,
those bases cost one k x k solve per demand.

:func:`allocate_pairs` is the closed form for thrusters in opposing pairs along independent
axes through the centre of mass (e.g. six thrusters +-x, +-y, +-z); :func:`allocate` returns the
same for such a set.
"""

from __future__ import annotations

import functools
import itertools
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

__all__ = ["Allocation", "allocate", "allocate_pairs"]

# |r| <= _TIE_TOL * (|c| + |a|^T |y|): a reduced cost that is zero up to rounding (a tie).
_TIE_TOL = 1e-10
# |det B| <= _SING_TOL * prod ||b_j|| (Hadamard bound): the basis is singular, not a candidate.
_SING_TOL = 1e-12


class Allocation(NamedTuple):
    """Thruster forces of an allocation.

    Attributes:
        f: (T,) thrust of each thruster [N], ``0 <= f <= F``.
        scale: () fraction ``s`` in [0, 1] of the demand that is met, ``M f = s d``
            (1: unsaturated).
    """

    f: jnp.ndarray
    scale: jnp.ndarray


class _Tables(NamedTuple):
    """Static tables of one group of bases (numpy, built once per (k, T))."""

    combos: np.ndarray  # (nb, k) int: the columns of every basis, in the group's columns
    basic: np.ndarray  # (nb, n) bool: whether a column of the group is basic
    place: np.ndarray  # (nb, k, T + 1 + k): place[b, j] = e_(LP column of basic variable j)
    costs: np.ndarray  # (n, L): the stacked costs of the group's columns, most important first


def _group(combos, columns, costs) -> _Tables:
    """Tables of the bases ``combos`` of the LP columns ``columns`` (the group's columns)."""
    combos = np.asarray(combos, dtype=np.int64)
    nb, k = combos.shape
    n_lp = columns[-1] + 1
    rows, slots = np.arange(nb)[:, None], np.arange(k)[None, :]
    basic = np.zeros((nb, len(columns)), dtype=bool)
    basic[rows, combos] = True
    place = np.zeros((nb, k, n_lp))
    place[rows, slots, np.asarray(columns)[combos]] = 1.0
    tables = _Tables(combos, basic, place, costs)
    for a in tables:
        a.setflags(write=False)
    return tables


@functools.lru_cache(maxsize=32)
def _tables(k: int, n_thrusters: int) -> tuple[_Tables, _Tables]:
    """The two groups of bases of the LP for (k, T) thrusters.

    The LP columns are [f_0 .. f_{T-1}, s, a_0 .. a_{k-1}]. Its stacked costs are c1 = -e_s,
    c2 = total thrust and c3 = a generic tie-break.

    Returns:
        unsaturated: the bases without s (s non-basic, at 1), over the columns
            [f_0 .. f_{T-1}, a_0 .. a_{k-1}] with the costs (c2, c3): c1 plays no part there.
        saturated: the bases that contain s, over all the columns, with (c1, c2, c3).
    """
    T = n_thrusters
    n = T + 1 + k
    costs = np.zeros((n, 3))
    costs[T, 0] = -1.0
    costs[:T, 1] = 1.0
    # generic tie-break: no linear relation among these numbers holds by accident
    costs[:, 2] = np.random.default_rng(20240607).uniform(1.0, 2.0, n)
    others = np.r_[0:T, T + 1 : n]  # the columns other than s
    unsaturated = _group(list(itertools.combinations(range(n - 1), k)), others, costs[others, 1:])
    saturated = _group(
        [(T, *others[list(c)]) for c in itertools.combinations(range(n - 1), k - 1)],
        np.arange(n),
        costs,
    )
    return unsaturated, saturated


def _inverse(B):
    """Inverses of a batch of k x k matrices B (nb, k, k) and their singularity flags.

    Closed form (adjugate) for k <= 3. Singular matrices (relative to the Hadamard bound) are
    flagged and given a finite placeholder inverse, so nothing is NaN.
    """
    k = B.shape[-1]
    hadamard = jnp.prod(jnp.linalg.norm(B, axis=-2), axis=-1)
    if k == 1:
        det = B[:, 0, 0]
        adj = jnp.ones_like(B)
    elif k == 2:
        det = B[:, 0, 0] * B[:, 1, 1] - B[:, 0, 1] * B[:, 1, 0]
        adj = jnp.stack(
            [
                jnp.stack([B[:, 1, 1], -B[:, 0, 1]], axis=-1),
                jnp.stack([-B[:, 1, 0], B[:, 0, 0]], axis=-1),
            ],
            axis=-2,
        )
    elif k == 3:
        c0, c1, c2 = B[:, :, 0], B[:, :, 1], B[:, :, 2]
        r0, r1, r2 = jnp.cross(c1, c2), jnp.cross(c2, c0), jnp.cross(c0, c1)
        det = jnp.sum(c0 * r0, axis=-1)
        adj = jnp.stack([r0, r1, r2], axis=-2)  # rows of the inverse times det
    else:
        det = jnp.linalg.det(B)
        singular = jnp.abs(det) <= _SING_TOL * hadamard
        eye = jnp.broadcast_to(jnp.eye(k, dtype=B.dtype), B.shape)
        return jnp.linalg.inv(jnp.where(singular[:, None, None], eye, B)), singular
    singular = jnp.abs(det) <= _SING_TOL * hadamard
    det = jnp.where(singular, 1.0, det)
    return adj / det[:, None, None], singular


def _candidates(A, upper, rhs0, vscale, tables: _Tables):
    """The best candidate of a group of bases and its bound violation.

    For each basis B of the columns of ``A`` (k, n): the lexicographic reduced costs of the
    stacked costs decide the bound of every non-basic variable (upper if negative), then
    ``B x_B = rhs0 - A_N x_N``. The non-basic variables sit on their bounds, so the violation
    is that of x_B (in units of ``vscale``; inf for a singular basis).

    Returns:
        the non-basic values (n,) and basic values (k,) of the least violating basis, its
        index and its violation.
    """
    k = A.shape[0]
    combos = tables.combos
    costs = jnp.asarray(tables.costs, dtype=A.dtype)
    B = A[:, combos].transpose(1, 0, 2)  # (nb, k, k), column j = A[:, combos[b, j]]
    Binv, singular = _inverse(B)
    # The contractions over the small k axis are unrolled sums of k elementwise products (XLA
    # fuses them into one loop; its CPU dot kernels are slow for these shapes).
    # duals of the stacked costs, y = B^-T c_B, and the reduced costs r = c - A^T y
    c_b = costs[combos]  # (nb, k, L)
    Y = sum(Binv[:, i, :, None] * c_b[:, i, None, :] for i in range(k))  # (nb, k, L)
    R = costs[None] - sum(A[j][None, :, None] * Y[:, j, None, :] for j in range(k))  # (nb, n, L)
    tol = _TIE_TOL * (
        jnp.abs(costs)[None]
        + sum(jnp.abs(A[j])[None, :, None] * jnp.abs(Y[:, j, None, :]) for j in range(k))
    )
    at_upper = jnp.zeros(R.shape[:2], dtype=bool)
    decided = jnp.zeros(R.shape[:2], dtype=bool)
    for level in range(costs.shape[1]):  # lexicographic sign of r1 + eps r2 + eps^2 r3 ...
        r = R[..., level]
        nonzero = jnp.abs(r) > tol[..., level]
        at_upper = jnp.where(decided | ~nonzero, at_upper, r < 0.0)
        decided = decided | nonzero
    x_n = jnp.where(at_upper & ~tables.basic, upper[None], 0.0)  # (nb, n) non-basic values
    rhs = rhs0[None] - x_n @ A.T  # (nb, k)
    x_b = sum(Binv[:, :, j] * rhs[:, j, None] for j in range(k))  # (nb, k)
    u_b, v_b = upper[combos], jnp.broadcast_to(vscale, upper.shape)[combos]
    violation = jnp.max(jnp.maximum(jnp.maximum(-x_b, x_b - u_b), 0.0) / v_b, axis=1)
    violation = jnp.where(singular, jnp.inf, violation)
    best = jnp.argmin(violation)
    return x_n[best], x_b[best], best, violation[best]


def allocate(M, d, F) -> Allocation:
    """Exact least-thrust thruster allocation with direction-preserving saturation.

    Solves, exactly (basis enumeration, see the module docstring), the LP

        max s, then min sum(f)   s.t.  M f = s d,  0 <= f <= F,  0 <= s <= 1

    i.e. ``min sum(f) s.t. M f = d, 0 <= f <= F`` when ``d`` is attainable (``s = 1``), and
    otherwise the largest fraction ``s`` of ``d`` attainable along ``d``, met with the least
    total thrust. Jittable and vmappable over ``d``, ``M`` and ``F``; no NaN for any finite
    input (``d = 0``, zero columns, ``F_i = 0``, rank-deficient ``M``).

    Args:
        M: (k, T) effectiveness matrix, column i = force [N/N] (and torque [m], i.e. N m per
            N) of thruster i per newton of thrust. Its shape is static.
        d: (k,) demanded force [N] (and torque [N m]) in the same components.
        F: (T,) maximum thrust of each thruster [N], >= 0 (0: failed).

    Returns:
        :class:`Allocation` with ``f`` (T,) [N], ``0 <= f <= F`` and ``M f = scale * d``, and
        ``scale`` () in [0, 1].
    """
    M = jnp.asarray(M, dtype=jnp.float64)
    d = jnp.asarray(d, dtype=M.dtype)
    F = jnp.maximum(jnp.asarray(F, dtype=M.dtype), 0.0)
    k, T = M.shape
    unsaturated, saturated = _tables(k, T)

    m_ref = jnp.max(jnp.abs(M))
    m_ref = jnp.where(m_ref > 0.0, m_ref, 1.0)
    f_ref = jnp.max(F, initial=0.0)
    f_ref = jnp.where(f_ref > 0.0, f_ref, 1.0)
    art = m_ref * jnp.eye(k, dtype=M.dtype)  # artificial columns, variables fixed at 0
    zeros, one = jnp.zeros(k, M.dtype), jnp.ones(1, M.dtype)

    # Bases without s: s = 1 (its level-1 reduced cost is -1), so M f + art a = d; the
    # level-1 reduced costs of f and a are 0 and their bounds follow (c2, c3). Only the
    # right-hand side depends on d.
    xn_u, xb_u, i_u, v_u = _candidates(
        jnp.concatenate([M, art], axis=1), jnp.concatenate([F, zeros]), d, f_ref, unsaturated
    )
    xn_u = jnp.concatenate([xn_u[:T], one, xn_u[T:]])
    # Bases with s: M f - s d + art a = 0 (s is dimensionless, f and a in newtons).
    xn_s, xb_s, i_s, v_s = _candidates(
        jnp.concatenate([M, -d[:, None], art], axis=1),
        jnp.concatenate([F, one, zeros]),
        zeros,
        jnp.concatenate([jnp.full(T, f_ref), one, jnp.full(k, f_ref)]),
        saturated,
    )
    x_u = xn_u + xb_u @ jnp.asarray(unsaturated.place)[i_u]
    x_s = xn_s + xb_s @ jnp.asarray(saturated.place)[i_s]
    x = jnp.where(v_u <= v_s, x_u, x_s)
    return Allocation(f=jnp.clip(x[:T], 0.0, F), scale=jnp.clip(x[T], 0.0, 1.0))


def allocate_pairs(d, F_pos, F_neg) -> Allocation:
    """Closed-form allocation for opposing thruster pairs along independent axes.

    Thrusters in pairs along n axes through the centre of mass (e.g. six thrusters +-x, +-y,
    +-z): the effectiveness matrix is ``[e_0, -e_0, e_1, -e_1, ...]``. The least-thrust
    allocation fires only the thruster on the demand's side, ``f_pos = max(d, 0)``,
    ``f_neg = max(-d, 0)``; under saturation the whole demand is scaled by the single factor
    ``s = min(1, min_j F_j / |d_j|)`` (``F_j`` the limit of the side that fires), which keeps its
    direction. This is the solution of the LP of :func:`allocate` for this set.

    Args:
        d: (n,) demanded force along each axis [N].
        F_pos: (n,) maximum thrust of the thruster pushing along +axis j [N], >= 0.
        F_neg: (n,) maximum thrust of the thruster pushing along -axis j [N], >= 0.

    Returns:
        :class:`Allocation` with ``f`` (2 n,) [N] ordered ``[+axis0, -axis0, +axis1, ...]`` and
        ``scale`` () in [0, 1].
    """
    d = jnp.asarray(d, dtype=jnp.float64)
    F_pos = jnp.maximum(jnp.asarray(F_pos, dtype=d.dtype), 0.0)
    F_neg = jnp.maximum(jnp.asarray(F_neg, dtype=d.dtype), 0.0)
    mag = jnp.abs(d)
    cap = jnp.where(d >= 0.0, F_pos, F_neg)
    active = mag > 0.0
    ratio = jnp.where(active, cap / jnp.where(active, mag, 1.0), jnp.inf)
    scale = jnp.clip(jnp.min(ratio, initial=jnp.inf), 0.0, 1.0)
    f_pos = jnp.minimum(scale * jnp.maximum(d, 0.0), F_pos)
    f_neg = jnp.minimum(scale * jnp.maximum(-d, 0.0), F_neg)
    return Allocation(f=jnp.stack([f_pos, f_neg], axis=-1).reshape(-1), scale=scale)
