"""HPIPM (Frison & Diehl, IFAC 2020), the structure-exploiting interior-point solver of acados, as a
peer: its OCP QP interface called through ``ctypes`` on a standard-form QP whose stages it
recovers (:func:`ocp_stages`).

HPIPM is not on PyPI by itself. Its library and BLASFEO's ship in the ``comma-deps-acados``
wheel, which also vendors a CasADi that would overwrite the one of the ``nmpc`` extra, so it
is installed into a folder of its own and found from there::

    pip install --no-deps --target ~/.hpipm comma-deps-acados
    export RVDJAX_HPIPM_LIB=~/.hpipm/acados/install/lib

(:func:`hpipm_library` also looks in an importable ``acados`` package.) That BLASFEO is built
for ``X64_INTEL_HASWELL`` (AVX2 and FMA); on a CPU without them the peer is unavailable
(:func:`hpipm_unavailable` says why) instead of stopping the process on an illegal
instruction.

The OCP QP HPIPM solves (stages k = 0 .. N; HPIPM's documentation of its OCP QP)::

    min sum_k 1/2 [u;x]' [R S; S' Q] [u;x] + [r;q]' [u;x] + zl' sl + zu' su
    s.t. x_{k+1} = A_k x_k + B_k u_k + b_k,   lg - sl <= C_k x_k + D_k u_k <= ug + su,
         sl, su >= 0

The standard form's plan (u_0, x_1, ..., u_{N-1}, x_N) maps to HPIPM's stages with no state
at stage 0 (x_0 given: b_0 = A_0 x_0 + c_0, as ``to_qp`` writes the first dynamics row) and no
input at stage N. An input row of u_t is a general row of stage t; a state row of x_{t+1}
is a general row of stage t + 1, softened where the standard form gives it a slack (the exact
L1 penalty: zu = rho, Zu = 0). The rows are one-sided (``lg`` masked off); the lower slacks,
which no row binds, carry the same linear cost so that they stay at zero.
"""

from __future__ import annotations

import ctypes
import functools
import importlib.util
import os
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp

from rvdjax.peers_host import PeerResult, _ms
from rvdjax.qp import QP, qp_objective

__all__ = ["HPIPM_ENV", "hpipm_library", "hpipm_unavailable", "ocp_stages", "solve_hpipm"]

HPIPM_ENV = "RVDJAX_HPIPM_LIB"

# HPIPM's settings, chosen in its favour on the benchmark's QPs (8 fastmpc-3d first steps,
# hard form, 2026-12-07; mean iterations): from its own cold start (zero states, the
# dynamics unmet) it took 47.6 / 50.1 / 67.9 / 73.0 at mu0 = 10 / 1e3 / 1e5 / 1e7 in its
# "balance" mode; from the drift of x0 (the start rvdjax's solver takes cold) 33.0 / 15.8 /
# 14.0 / 13.9. Its "speed" mode (Riccati by Cholesky, no LQ fallback) reached
# the 1e-8 tolerance on few of them in 200 iterations (and 1e-6 on few more), "robust" took
# as many as "balance", "speed_abs" stopped at its minimum step.
# Under the soft rows' exact penalties, mu0 is raised to the largest penalty rho (the
# multiplier an active soft row's slack takes): on QPs taken along each maneuver (every few
# MPC steps, 2026-12-08; mean iterations at mu0 = 1e5 / rho) poseidyn-lqmpc (rho = 1e8, 16
# QPs) 50.9 / 17.9, thesis-vbar (1e6, 3) 21.3 / 19.7, fastmpc-3d (5e6, 8) 11.1 / 10.0;
# spot-2d-a and rotating-target-a have rho = 1e5 (lower mu0 took more iterations there).
DEFAULT_MU0 = 1e5

# hpipm_common.h: enum hpipm_mode, enum hpipm_status
_MODES = {"speed_abs": 0, "speed": 1, "balance": 2, "robust": 3}
_STATUS = {0: "SUCCESS", 1: "MAX_ITER", 2: "MIN_STEP", 3: "NAN_SOL", 4: "INCONS_EQ"}


def _candidates() -> list[Path]:
    found = []
    if os.environ.get(HPIPM_ENV):
        found.append(Path(os.environ[HPIPM_ENV]).expanduser())
    spec = importlib.util.find_spec("acados")
    if spec is not None and spec.submodule_search_locations:
        found += [Path(p) / "install" / "lib" for p in spec.submodule_search_locations]
    return found


def _missing_cpu_flags(lib: Path, cpuinfo: Path = Path("/proc/cpuinfo")) -> list[str]:
    """The instruction sets BLASFEO's build needs (its ``blasfeo_target.h`` beside the
    library) that ``/proc/cpuinfo`` does not list, checked before any of its code runs: a
    library built with AVX2 could stop the process on an illegal instruction even in its own
    feature test. [] where either file is missing (BLASFEO's test then decides)."""
    header = lib.parent / "include" / "blasfeo" / "include" / "blasfeo_target.h"
    try:
        target = header.read_text()
        flags = set()
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("flags"):
                flags = set(line.split(":", 1)[1].split())
                break
    except OSError:
        return []
    needs = {"AVX2": "avx2", "FMA": "fma", "AVX": "avx", "SSE3": "pni"}  # cpuinfo's names
    return [
        name
        for name, flag in needs.items()
        if f"#define TARGET_NEED_FEATURE_{name} 1" in target and flags and flag not in flags
    ]


@functools.cache
def _load() -> tuple[ctypes.CDLL | None, str]:
    """(HPIPM's library, "") or (None, why not)."""
    folders = [p for p in _candidates() if (p / "libhpipm.so").is_file()]
    if not folders:
        return None, (
            f"no libhpipm.so found (set {HPIPM_ENV} to the folder holding libhpipm.so and "
            "libblasfeo.so, e.g. after `pip install --no-deps --target ~/.hpipm "
            "comma-deps-acados`: ~/.hpipm/acados/install/lib)"
        )
    lib = folders[0]
    missing = _missing_cpu_flags(lib)
    if missing:
        return None, f"this CPU lacks {', '.join(missing)}, which {lib / 'libblasfeo.so'} needs"
    try:
        blasfeo = ctypes.CDLL(str(lib / "libblasfeo.so"), mode=ctypes.RTLD_GLOBAL)
        features = ctypes.c_int(0)
        if blasfeo.blasfeo_processor_cpu_features(ctypes.byref(features)) != 1:
            need = ctypes.create_string_buffer(256)
            blasfeo.blasfeo_processor_library_string(need)
            return None, (
                f"this CPU lacks what {lib / 'libblasfeo.so'} was built for "
                f"({need.value.decode(errors='replace').strip()})"
            )
        hpipm = ctypes.CDLL(str(lib / "libhpipm.so"), mode=ctypes.RTLD_GLOBAL)
        for part in ("dim", "", "sol", "ipm_arg", "ipm_ws"):  # the sizes are size_t, not int
            for size in ("strsize", "memsize"):
                name = "_".join(w for w in ("d_ocp_qp", part, size) if w)
                getattr(hpipm, name).restype = ctypes.c_size_t
        return hpipm, ""
    except OSError as err:
        return None, f"cannot load HPIPM from {lib}: {err}"


def hpipm_library() -> ctypes.CDLL | None:
    """HPIPM's shared library, loaded once, or None where it is not usable here."""
    return _load()[0]


def hpipm_unavailable() -> str:
    """Why HPIPM cannot run here ("" where it can)."""
    return _load()[1]


class Stages(NamedTuple):
    """An OCP QP in HPIPM's stages k = 0 .. N (lists of N + 1 arrays, column-major when
    passed; absent blocks have a zero dimension)."""

    nx: list[int]
    nu: list[int]
    A: list[np.ndarray]  # (nx[k+1], nx[k]), k < N
    B: list[np.ndarray]  # (nx[k+1], nu[k]), k < N
    b: list[np.ndarray]  # (nx[k+1],), k < N
    Q: list[np.ndarray]
    S: list[np.ndarray]  # (nu[k], nx[k])
    R: list[np.ndarray]
    q: list[np.ndarray]
    r: list[np.ndarray]
    C: list[np.ndarray]  # (ng[k], nx[k])
    D: list[np.ndarray]  # (ng[k], nu[k])
    ug: list[np.ndarray]
    soft: list[np.ndarray]  # indices (into the stage's rows) of the softened rows
    z: list[np.ndarray]  # their linear penalty, one per softened row
    u_cols: list[np.ndarray]  # the standard form's columns of u_k, k < N
    x_cols: list[np.ndarray]  # ... of x_k, k >= 1
    s_cols: list[np.ndarray]  # ... of the softened rows' slacks


def ocp_stages(qp: QP) -> Stages:
    """HPIPM's stages of a standard-form QP built by :func:`rvdjax.qp.to_qp` (its
    stage-interleaved plan, its dynamics rows, its one-sided rows and their slacks).

    Raises ValueError where ``qp`` does not have that structure (a coupling between stages in
    P, a row over two stages, a slack in more than one row)."""
    nu, nx = qp.nu, qp.nx
    if nu <= 0 or nx <= 0 or qp.n_plan % (nu + nx):
        raise ValueError("the QP must come from rvdjax.qp.to_qp (its nu and nx recorded)")
    N = qp.n_plan // (nu + nx)
    ns = nu + nx
    nz = qp.P.shape[0]

    def su(k):  # the columns of u_k, k < N
        return slice(k * ns, k * ns + nu)

    def sx(k):  # ... of x_k, k >= 1
        return slice((k - 1) * ns + nu, k * ns)

    P = qp.P.toarray()
    Aeq = qp.A_eq.toarray()
    col = np.arange(qp.n_plan)
    stage_of = np.full(nz, -1)  # the HPIPM stage of each column (slacks: -1)
    stage_of[: qp.n_plan] = col // ns + (col % ns >= nu)
    Pc = sp.coo_matrix(qp.P)
    Pc = Pc.row[Pc.data != 0], Pc.col[Pc.data != 0]
    if np.any(stage_of[Pc[0]] != stage_of[Pc[1]]) or np.any(stage_of[Pc[0]] < 0):
        raise ValueError("P couples two stages or weighs a slack: not an OCP QP of to_qp")

    empty = np.zeros(0)
    nxs = [0] + [nx] * N
    nus = [nu] * N + [0]
    dyn = [slice(k * nx, (k + 1) * nx) for k in range(N)]  # the rows of x_{k+1}'s dynamics
    if not np.allclose(np.stack([Aeq[dyn[k], sx(k + 1)] for k in range(N)]), np.eye(nx)):
        raise ValueError("a dynamics row is not x_{t+1} - A x_t - B u_t = b")
    Bb = [-Aeq[dyn[k], su(k)] for k in range(N)]
    Ab = [np.zeros((nx, 0))] + [-Aeq[dyn[k], sx(k)] for k in range(1, N)]
    bb = [np.asarray(qp.b_eq[dyn[k]], float) for k in range(N)]
    Qs = [np.zeros((0, 0))] + [P[sx(k), sx(k)] for k in range(1, N + 1)]
    Rs = [P[su(k), su(k)] for k in range(N)] + [np.zeros((0, 0))]
    Ss = [np.zeros((nu, 0))] + [P[su(k), sx(k)] for k in range(1, N)] + [np.zeros((0, nx))]
    qv = np.asarray(qp.q, float)
    qs = [empty] + [qv[sx(k)] for k in range(1, N + 1)]
    rs = [qv[su(k)] for k in range(N)] + [empty]

    Gsp = sp.coo_matrix(qp.G)
    G = Gsp.toarray()
    h = np.asarray(qp.h, float)
    Gp, Gs = G[:, : qp.n_plan], G[:, qp.n_plan :]
    on_slack = Gs != 0
    n_slack = on_slack.sum(axis=1)
    # each row's first and last stage, over its nonzero plan entries
    nzr = (Gsp.data != 0) & (Gsp.col < qp.n_plan)
    r_of, s_of = Gsp.row[nzr], stage_of[Gsp.col[nzr]]
    first = np.full(G.shape[0], N + 1)
    last = np.full(G.shape[0], -1)
    np.minimum.at(first, r_of, s_of)
    np.maximum.at(last, r_of, s_of)
    plan_row = last >= 0
    # a row without plan columns must be -s <= 0: HPIPM's own bound on its slacks
    bound = ~plan_row & ((n_slack != 1) | (h != 0) | (Gs.sum(axis=1) >= 0))
    if bound.any():
        i = np.argmax(bound)
        raise ValueError(f"row {i} of G is neither a stage's row nor a slack's bound")
    spans = plan_row & ((first != last) | (n_slack > 1))
    if spans.any():
        raise ValueError(f"row {np.argmax(spans)} of G spans two stages or two slacks")
    softened = plan_row & (n_slack == 1)
    # the slack of a softened row (the hard form has no slack columns)
    s_of_row = np.argmax(on_slack, axis=1) if Gs.shape[1] else np.zeros(G.shape[0], int)
    taken = s_of_row[softened]
    bad = (Gs[softened, taken] != -1.0) | (np.bincount(taken, minlength=Gs.shape[1])[taken] > 1)
    if bad.any():
        raise ValueError(f"slack column {qp.n_plan + taken[np.argmax(bad)]} is not one row's -s")

    C, D, ug, soft, zs, s_cols = [], [], [], [], [], []
    in_plan = np.flatnonzero(plan_row)
    by_stage = in_plan[np.argsort(first[in_plan], kind="stable")]  # G's order within a stage
    counts = np.bincount(first[in_plan], minlength=N + 1)
    ends = np.cumsum(counts)
    starts = ends - counts
    for k in range(N + 1):
        rows = by_stage[starts[k] : ends[k]]
        C.append(Gp[rows, sx(k)] if k else np.zeros((rows.size, 0)))
        D.append(Gp[rows, su(k)] if k < N else np.zeros((rows.size, 0)))
        ug.append(h[rows])
        soft.append(np.flatnonzero(softened[rows]).astype(np.int32))
        cols = qp.n_plan + s_of_row[rows[softened[rows]]]
        s_cols.append(cols)
        zs.append(qv[cols])
    cols = np.arange(nz)
    u_cols = [cols[su(k)] for k in range(N)] + [np.zeros(0, int)]
    x_cols = [np.zeros(0, int)] + [cols[sx(k)] for k in range(1, N + 1)]
    return Stages(
        nxs, nus, Ab, Bb, bb, Qs, Ss, Rs, qs, rs, C, D, ug, soft, zs, u_cols, x_cols, s_cols,
    )  # fmt: skip


def _buffer(size: int):
    return ctypes.create_string_buffer(int(size) + 64)  # HPIPM aligns its memory itself


def _f(a) -> np.ndarray:
    """A float64 column-major copy of ``a``, the layout HPIPM's setters read."""
    return np.asfortranarray(a, dtype=np.float64)


# The address as c_void_p: ctypes' cast in ``ndarray.ctypes.data_as`` cost more than HPIPM's
# solve when a QP's ~600 arrays were passed that way (an MPC step in the loop). ``keep`` holds
# the array until HPIPM has read it.
def _ints(values, keep: list) -> ctypes.c_void_p:
    a = np.ascontiguousarray(values, dtype=np.int32)
    keep.append(a)
    return ctypes.c_void_p(a.ctypes.data)


def _doubles(values, keep: list) -> ctypes.c_void_p:
    a = _f(values)
    keep.append(a)
    return ctypes.c_void_p(a.ctypes.data)


def _workspace(lib, nx, nu, ng, ns, mode, tol, max_iter, mu0, warm):
    """HPIPM's dimensions, QP, solution, IPM arguments and workspace for one OCP shape and one
    setting (``warm``: start from the primal variables in the solution), with the QP's values
    that :func:`solve_hpipm` leaves alone: the lower bounds ``lg`` masked (one-sided rows),
    they and the slacks' quadratic weights at the zeros ``d_ocp_qp_create`` writes. Returns
    the five structs and, to keep alive with them, the memory they point into. Created for
    each solve: kept across the solves of one shape, as an MPC loop built on HPIPM keeps
    them, they saved 0.2 of 4.4 ms a fastmpc-3d step, and the solution had to be zeroed
    between solves (a previous solve's slacks moved the next one's bits)."""
    N = len(nx) - 1
    keep = []

    def ints(values):
        return _ints(values, keep)

    zeros = [0] * (N + 1)
    dim = _buffer(lib.d_ocp_qp_dim_strsize())
    dim_mem = _buffer(lib.d_ocp_qp_dim_memsize(N))
    lib.d_ocp_qp_dim_create(N, dim, dim_mem)
    lib.d_ocp_qp_dim_set_all(
        ints(nx), ints(nu), ints(zeros), ints(zeros), ints(ng), ints(zeros), ints(zeros),
        ints(ns), dim,
    )  # fmt: skip
    qp_h = _buffer(lib.d_ocp_qp_strsize())
    qp_mem = _buffer(lib.d_ocp_qp_memsize(dim))
    lib.d_ocp_qp_create(dim, qp_h, qp_mem)
    for k in range(N + 1):
        if ng[k]:
            lib.d_ocp_qp_set_lg_mask(k, _doubles(np.zeros(ng[k]), keep), qp_h)

    sol = _buffer(lib.d_ocp_qp_sol_strsize())
    sol_mem = _buffer(lib.d_ocp_qp_sol_memsize(dim))
    lib.d_ocp_qp_sol_create(dim, sol, sol_mem)

    arg = _buffer(lib.d_ocp_qp_ipm_arg_strsize())
    arg_mem = _buffer(lib.d_ocp_qp_ipm_arg_memsize(dim))
    lib.d_ocp_qp_ipm_arg_create(dim, arg, arg_mem)
    lib.d_ocp_qp_ipm_arg_set_default(_MODES[mode], arg)
    lib.d_ocp_qp_ipm_arg_set_iter_max(ctypes.byref(ctypes.c_int(max_iter)), arg)
    for field in ("stat", "eq", "ineq", "comp"):
        getattr(lib, f"d_ocp_qp_ipm_arg_set_tol_{field}")(ctypes.byref(ctypes.c_double(tol)), arg)
    if mu0 is not None:
        lib.d_ocp_qp_ipm_arg_set_mu0(ctypes.byref(ctypes.c_double(mu0)), arg)
    if warm:  # HPIPM starts from the primal variables in ``sol``
        lib.d_ocp_qp_ipm_arg_set_warm_start(ctypes.byref(ctypes.c_int(1)), arg)

    ws = _buffer(lib.d_ocp_qp_ipm_ws_strsize())
    ws_mem = _buffer(lib.d_ocp_qp_ipm_ws_memsize(dim, arg))
    lib.d_ocp_qp_ipm_ws_create(dim, arg, ws, ws_mem)
    return dim, qp_h, sol, arg, ws, (dim_mem, qp_mem, sol_mem, arg_mem, ws_mem)


def solve_hpipm(
    qp: QP,
    tol: float = 1e-8,
    max_iter: int = 200,
    mode: str = "balance",
    mu0: float | str | None = "auto",
    start: str = "drift",
    resolve: bool = True,
) -> PeerResult:
    """Solve with HPIPM's OCP QP interior-point method (``d_ocp_qp_ipm_solve``) from its own
    cold start.

    Args:
        qp: a standard-form QP of :func:`rvdjax.qp.to_qp` (hard or soft form).
        tol: HPIPM's stationarity, equality, inequality and complementarity tolerances.
        max_iter: iteration cap.
        mode: HPIPM's ``speed_abs``, ``speed``, ``balance`` or ``robust`` default settings.
        mu0: HPIPM's initial barrier parameter ("auto": the largest of 1e5 and the soft
            rows' penalties; None: the mode's default).
        start: "drift" (HPIPM's primal warm start at zero inputs and the states they give,
            the start rvdjax's solver takes cold) or "cold" (HPIPM's own: zero inputs and
            states, which leave the dynamics unmet).
        resolve: solve twice in the same memory and time the second solve (``solve_ms``), as
            an MPC loop that keeps HPIPM's workspace re-solves; False: one solve, timed (the
            closed-loop backend, which builds the workspace anew every step).

    Raises:
        RuntimeError: HPIPM is not usable here (:func:`hpipm_unavailable` says why).
        ValueError: a bad ``mode``, or a QP without the OCP structure (:func:`ocp_stages`).
    """
    if start not in ("drift", "cold"):
        raise ValueError(f"start must be 'drift' or 'cold', got {start!r}")
    if mode not in _MODES:
        raise ValueError(f"mode must be one of {', '.join(_MODES)}, got {mode!r}")
    if isinstance(mu0, str) and mu0 != "auto":
        raise ValueError(f"mu0 must be a number, 'auto' or None, got {mu0!r}")
    lib = hpipm_library()
    if lib is None:
        raise RuntimeError(f"HPIPM is not available: {hpipm_unavailable()}")
    t0 = time.perf_counter()
    st = ocp_stages(qp)
    N = len(st.nx) - 1
    keep = []  # every array HPIPM reads, alive until the solve returns

    def ints(values):
        return _ints(values, keep)

    def ptr(values):
        return _doubles(values, keep)

    ng = [len(u) for u in st.ug]
    ns = [len(s) for s in st.soft]
    if mu0 == "auto":
        mu0 = max([DEFAULT_MU0] + [float(np.max(z)) for z in st.z if z.size])
    dim, qp_h, sol, arg, ws, _memory = _workspace(
        lib, tuple(st.nx), tuple(st.nu), tuple(ng), tuple(ns), mode, tol, max_iter, mu0,
        start == "drift",
    )  # fmt: skip
    for k in range(N + 1):
        if k < N:
            lib.d_ocp_qp_set_A(k, ptr(st.A[k]), qp_h)
            lib.d_ocp_qp_set_B(k, ptr(st.B[k]), qp_h)
            lib.d_ocp_qp_set_b(k, ptr(st.b[k]), qp_h)
        lib.d_ocp_qp_set_Q(k, ptr(st.Q[k]), qp_h)
        lib.d_ocp_qp_set_S(k, ptr(st.S[k]), qp_h)
        lib.d_ocp_qp_set_R(k, ptr(st.R[k]), qp_h)
        lib.d_ocp_qp_set_q(k, ptr(st.q[k]), qp_h)
        lib.d_ocp_qp_set_r(k, ptr(st.r[k]), qp_h)
        if ng[k]:
            lib.d_ocp_qp_set_C(k, ptr(st.C[k]), qp_h)
            lib.d_ocp_qp_set_D(k, ptr(st.D[k]), qp_h)
            lib.d_ocp_qp_set_ug(k, ptr(st.ug[k]), qp_h)
        if ns[k]:
            lib.d_ocp_qp_set_idxs(k, ints(st.soft[k]), qp_h)
            lib.d_ocp_qp_set_zl(k, ptr(st.z[k]), qp_h)
            lib.d_ocp_qp_set_zu(k, ptr(st.z[k]), qp_h)

    def from_drift():
        x = np.zeros(0)
        for k in range(N):
            x = st.A[k] @ x + st.b[k]  # zero inputs
            lib.d_ocp_qp_sol_set_u(k, ptr(np.zeros(st.nu[k])), sol)
            lib.d_ocp_qp_sol_set_x(k + 1, ptr(x), sol)

    if start == "drift":
        from_drift()

    if resolve:
        lib.d_ocp_qp_ipm_solve(qp_h, sol, arg, ws)  # HPIPM's fresh memory touched
        if start == "drift":
            from_drift()
    setup_ms = _ms(t0)
    t0 = time.perf_counter()
    lib.d_ocp_qp_ipm_solve(qp_h, sol, arg, ws)  # the same solve, as an MPC loop runs it
    solve_ms = _ms(t0)

    status, iters = ctypes.c_int(-1), ctypes.c_int(0)
    lib.d_ocp_qp_ipm_get_status(ws, ctypes.byref(status))
    lib.d_ocp_qp_ipm_get_iter(ws, ctypes.byref(iters))
    z = np.zeros(qp.P.shape[0])
    for k in range(N + 1):
        if st.nu[k]:
            u = np.zeros(st.nu[k])
            lib.d_ocp_qp_sol_get_u(k, sol, ctypes.c_void_p(u.ctypes.data))
            z[st.u_cols[k]] = u
        if st.nx[k]:
            x = np.zeros(st.nx[k])
            lib.d_ocp_qp_sol_get_x(k, sol, ctypes.c_void_p(x.ctypes.data))
            z[st.x_cols[k]] = x
        if ns[k]:
            su = np.zeros(ns[k])
            lib.d_ocp_qp_sol_get_su(k, sol, ctypes.c_void_p(su.ctypes.data))
            z[st.s_cols[k]] = su
    name = _STATUS.get(status.value, f"STATUS_{status.value}")
    return PeerResult(z, qp_objective(qp, z), int(iters.value), name, solve_ms, setup_ms)
