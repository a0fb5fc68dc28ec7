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
if os.environ.get("RVDJAX_TEST_XLA_OPT", "0") != "default" and (
    "--xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", "")
):
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0"
    ).strip()

# The tests also compile with XLA's older CPU loop emitters, which compile these programs in
# about half the time (the suite: 9 min 14 s -> 6 min 28 s on this project's 2-core VM,
# 2026-12-07; XLA's compiler was 491 s of the suite's 1 127 s of test work). rvdjax itself does
# not set it for users (rvdjax.xla_options says why). The two forms round differently:
# elementwise functions agree to the ulp, but reductions and fused multiply-adds are placed
# differently, so tests that hold two programs to the same bits, or to 1e-12 after a whole
# solve, are marked ``users_compiler`` and run in a child interpreter with XLA's default
# emitters (pytest_pyfunc_call below); test_xla_options flies the default scenario with the
# users' options in a child and compares. Only for the jaxlib versions checked to have the
# option (XLA aborts on an unknown flag). RVDJAX_TEST_XLA_EMITTERS=default keeps XLA's.
EMITTERS = "--xla_cpu_use_fusion_emitters=false"
EMITTERS_CHECKED = ("0.10.",)  # jaxlib 0.10.2 (2026-12-07)


def _legacy_emitters() -> bool:
    from importlib.metadata import version

    if os.environ.get("RVDJAX_TEST_XLA_EMITTERS") == "default":
        return False
    return version("jaxlib").startswith(EMITTERS_CHECKED)


if _legacy_emitters() and "--xla_cpu_use_fusion_emitters" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + EMITTERS).strip()

import subprocess  # noqa: E402
import sys  # noqa: E402

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


# Seconds each test file took in a full run (2 xdist workers, 2-core machine, 2026-12-07, the
# older emitters above; `pytest --durations=0` summed by file; test_solver and test_xla_options
# with their child interpreters added): ``--dist loadfile`` hands whole files to the workers
# in collection order (``--no-loadscope-reorder`` in pyproject: xdist's default order is by
# number of tests, which put the slowest file, with few tests, last). The slowest files go
# first (longest processing time first), files not listed (new ones) after them, the quick
# ones last to fill the gaps.
FILE_COST_S = {
    "test_notebooks.py": 102,
    "test_kernels.py": 106,
    "test_solver.py": 60,
    "test_phases.py": 53,
    "test_engine.py": 53,
    "test_study.py": 46,
    "test_kkt.py": 44,
    "test_tune_gradients.py": 32,
    "test_paper_mode.py": 30,
    "test_xla_options.py": 24,
    "test_cli.py": 23,
    "test_verify.py": 22,
    "test_compare.py": 19,
    "test_thrusters.py": 18,
    "test_rendezvous.py": 16,
    "test_gradients.py": 14,
    "test_constraints.py": 13,
    "test_docking.py": 13,
    "test_scenario_files.py": 12,
    "test_provenance.py": 11,
    "test_gpu_sweeps.py": 9,
    "test_allocation.py": 8,
    "test_scenarios.py": 6,
    "test_idvd.py": 5,
    "test_tune.py": 5,
    "test_dual.py": 5,
    "test_flight.py": 5,
    "test_peers.py": 4,
    "test_propagate.py": 4,
    "test_navigation.py": 4,
    "test_gpu_profile.py": 4,
    "test_new_family.py": 3,
    "test_derivative_counts.py": 3,
    "test_dynamics.py": 3,
    "test_poseidyn.py": 3,
    "test_problems.py": 2,
    "test_disturbances.py": 2,
    "test_schema.py": 2,
    "test_qp.py": 1,
    "test_suite_profile.py": 0,
}
UNLISTED_FILE_COST_S = 7


def pytest_collection_modifyitems(session, config, items):
    """Order the test files by FILE_COST_S, slowest first (stable: tests keep their order
    within a file, so module fixtures are still built once)."""

    def cost(item):
        return FILE_COST_S.get(item.path.name, UNLISTED_FILE_COST_S)

    items.sort(key=lambda item: -cost(item))


@pytest.hookimpl(tryfirst=True)
def pytest_pyfunc_call(pyfuncitem):
    """A ``users_compiler`` test, while this process compiles with the older emitters: the
    same test in a child interpreter that compiles with XLA's default emitters (its fixtures
    built there), passing or failing with it."""
    if pyfuncitem.get_closest_marker("users_compiler") is None:
        return None
    if EMITTERS not in os.environ.get("XLA_FLAGS", ""):
        return None
    # a child that still holds the option fails here instead of starting another child
    assert os.environ.get("RVDJAX_TEST_XLA_EMITTERS") != "default", "the child kept " + EMITTERS
    flags = os.environ["XLA_FLAGS"].replace(EMITTERS, "").strip()
    env = dict(os.environ, XLA_FLAGS=flags, RVDJAX_TEST_XLA_EMITTERS="default")
    env.pop("PYTEST_XDIST_WORKER", None)
    root = pyfuncitem.config.rootpath
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-o", "addopts=",
           "-n", "0", pyfuncitem.nodeid]  # fmt: skip
    proc = subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True, timeout=1200)
    assert proc.returncode == 0, (
        f"{pyfuncitem.nodeid} with XLA's default emitters (child interpreter) exited with "
        f"{proc.returncode}:\n{proc.stdout[-6000:]}\n{proc.stderr[-3000:]}"
    )
    return True
