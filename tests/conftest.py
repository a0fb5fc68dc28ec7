"""Shared test fixtures: float64 JAX (via ``import rvdjax``) and a Clarabel reference solve."""

from __future__ import annotations

import os

# The suite compiles several hundred distinct XLA programs and runs most of them for
# milliseconds: LLVM's optimisation dominates its time. Tests compile at optimisation level 0
# (1.6-2.6x faster compiles; the programs and what each test asserts are the same, the code
# is only less optimised). Every worker and every child process (notebooks, multi-process
# studies) inherits it. test_xla_options flies a scenario at the default level in a child
# process and compares it with this level. RVDJAX_TEST_XLA_OPT=default runs the suite at the
# default level.
if os.environ.get("RVDJAX_TEST_XLA_OPT", "0") != "default":
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0"
    ).strip()

import clarabel  # noqa: E402
import jax  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
import scipy.sparse as sp  # noqa: E402

import rvdjax  # noqa: E402, F401  (enables jax_enable_x64 before any array is created)

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


# Seconds each test file took in a full run (2 xdist workers, 2-core machine, 2026-11-29,
# `pytest --durations=0` summed by file): ``--dist loadfile`` hands whole files to the workers
# in collection order (``--no-loadscope-reorder`` in pyproject: xdist's default order is by
# number of tests, which put the slowest file, with few tests, last). The slowest files go
# first (longest processing time first), files not listed (new ones) after them, the quick
# ones last to fill the gaps.
FILE_COST_S = {
    "test_notebooks.py": 187,
    "test_kernels.py": 120,
    "test_study.py": 85,
    "test_engine.py": 78,
    "test_phases.py": 76,
    "test_solver.py": 70,
    "test_tune_gradients.py": 61,
    "test_thrusters.py": 53,
    "test_kkt.py": 55,
    "test_paper_mode.py": 49,
    "test_cli.py": 45,
    "test_compare.py": 33,
    "test_verify.py": 32,
    "test_docking.py": 28,
    "test_rendezvous.py": 28,
    "test_gradients.py": 24,
    "test_constraints.py": 21,
    "test_provenance.py": 20,
    "test_scenario_files.py": 16,
    "test_tune.py": 14,
    "test_allocation.py": 11,
    "test_dual.py": 11,
    "test_flight.py": 11,
    "test_navigation.py": 10,
    "test_xla_options.py": 9,
    "test_dynamics.py": 9,
    "test_scenarios.py": 8,
    "test_idvd.py": 7,
    "test_poseidyn.py": 7,
    "test_gpu_sweeps.py": 6,
    "test_propagate.py": 6,
    "test_problems.py": 6,
    "test_new_family.py": 4,
    "test_peers.py": 4,
    "test_disturbances.py": 4,
    "test_derivative_counts.py": 3,
    "test_schema.py": 1,
    "test_gpu_profile.py": 1,
    "test_qp.py": 1,
}
UNLISTED_FILE_COST_S = 10


def pytest_collection_modifyitems(session, config, items):
    """Order the test files by FILE_COST_S, slowest first (stable: tests keep their order
    within a file, so module fixtures are still built once)."""

    def cost(item):
        return FILE_COST_S.get(item.path.name, UNLISTED_FILE_COST_S)

    items.sort(key=lambda item: -cost(item))
