"""Shared test fixtures: float64 JAX (via ``import rvdjax``) and a Clarabel reference solve."""

from __future__ import annotations

import os
import shutil
import tempfile

import clarabel
import jax
import numpy as np
import pytest
import scipy.sparse as sp

import rvdjax  # noqa: F401  (enables jax_enable_x64 before any array is created)

# One JAX compilation cache per test session, shared by the pytest-xdist workers (they
# inherit the environment of the process that imported this file first): tests that jit the
# same closed loop through different wrappers compile it once. A fresh directory every session,
# so no test ever runs a program compiled by another version of the code.
_CACHE_ENV = "RVDJAX_TEST_JAX_CACHE"
if _CACHE_ENV not in os.environ:
    os.environ[_CACHE_ENV] = tempfile.mkdtemp(prefix="rvdjax-test-jax-cache-")
    _OWN_CACHE = True
else:
    _OWN_CACHE = False
jax.config.update("jax_compilation_cache_dir", os.environ[_CACHE_ENV])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


def pytest_unconfigure(config):
    if _OWN_CACHE and not hasattr(config, "workerinput"):
        shutil.rmtree(os.environ[_CACHE_ENV], ignore_errors=True)


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
