"""Shared test fixtures: float64 JAX (via ``import rvdjax``) and a Clarabel reference solve."""

from __future__ import annotations

import clarabel
import jax
import numpy as np
import pytest
import scipy.sparse as sp

import rvdjax  # noqa: F401  (enables jax_enable_x64 before any array is created)

# No persistent JAX compilation cache in the tests: one CI run of three died with a
# segmentation fault inside XLA's serialisation of a compiled CPU executable for that cache
# (jax 0.10, compilation_cache.put_executable_and_time), and the suite takes the same time
# without it (11 min 9 s against 11 min 12 s on a fresh clone, 2026-11-23).
jax.config.update("jax_enable_compilation_cache", False)


def _clarabel_solve(qp, tight: bool = True):
    """Solve a :class:`rvdjax.qp.QP` with Clarabel.

    Equalities first (ZeroCone), then the inequalities G z <= h (NonnegativeCone); P is
    passed as its upper triangle in CSC form.

    Args:
        qp: the standard-form QP.
        tight: use 1e-12 gap and feasibility tolerances (default Clarabel's otherwise).

    Returns:
        (z, objective including ``qp.const``, status string, e.g. "Solved").
    """
    n_eq, n_in = qp.A_eq.shape[0], qp.G.shape[0]
    A = sp.vstack([qp.A_eq, qp.G]).tocsc()
    b = np.concatenate([qp.b_eq, qp.h])
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    if tight:
        settings.tol_gap_abs = 1e-12
        settings.tol_gap_rel = 1e-12
        settings.tol_feas = 1e-12
        settings.max_iter = 400
    cones = [clarabel.ZeroConeT(n_eq), clarabel.NonnegativeConeT(n_in)]
    P = sp.triu(qp.P).tocsc()
    sol = clarabel.DefaultSolver(P, np.asarray(qp.q, float), A, b, cones, settings).solve()
    z = np.array(sol.x)
    objective = float(sol.obj_val) + float(qp.const)
    return z, objective, str(sol.status)


@pytest.fixture(scope="session")
def clarabel_solve():
    """``clarabel_solve(qp, tight=True) -> (z, objective incl. qp.const, status string)``."""
    return _clarabel_solve
