"""Tests of rvdjax.solver: the barrier / Newton solver against Clarabel, batching, statuses.

Costs: JAX compiles once per (shape, settings, dtype); every random shape class is solved as
one vmapped batch under one jit, so the file compiles about a dozen programs in total.

Plan tolerance (accurate mode). With x eliminated through the dynamics the objective J(u) is
strongly convex in u with modulus 2 lambda_min(R) (Q and the L1 penalty are only convex), and
the optimum u* satisfies the first-order condition on the convex feasible set, so for every
feasible u:  J(u) - J* >= lambda_min(R) ||u - u*||^2. The solver stops at a relative gap
~1e-9, so its plan can only be pinned to ~sqrt(1e-9) ~ 3e-5 relative, never to the 1e-9 of the
objective. The tests assert that bound (with an allowance for Clarabel's own inexactness) and
report the plan difference relative to u_max (measured <= ~2e-4; asserted <= 1e-3).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from ocp_factory import SHAPE_CLASSES, random_ocp

from rvdjax.ocp import OCP, make_ocp
from rvdjax.problems import (
    FASTMPC3D,
    fastmpc3d_first_step,
    fastmpc3d_step,
    stack_ocps,
)
from rvdjax.qp import split_solution, to_qp
from rvdjax.solver import (
    Solution,
    SolverParams,
    SolverSettings,
    Status,
    max_violation,
    shift_solution,
    solve,
    solve_batch,
)

ACCURATE = SolverSettings()
PAPER = SolverSettings.paper()
BARRIER = SolverSettings(mode="barrier")

# Problems per shape class (>= 200 in total) and their seeds. Each class is solved in two
# equal chunks of new data through the same jitted function (see test_jit_traces_once).
N_PROBLEMS = {"small": 100, "medium": 60, "large": 30, "long": 20}

OBJ_RTOL = 1e-6  # |J - J_clarabel| / (1 + |J_clarabel|)
VIOL_TOL = 1e-7  # max row-normalised violation + max dynamics residual
U_REL_TOL = 1e-3  # max |u - u_clarabel| / u_max
CLARABEL_ALLOWANCE = 1e-10  # relative objective inexactness allowed for Clarabel's optimum
RHO_RTOL = 1e-7  # soft vs hard Clarabel objectives (rho exceeds the multipliers)
SLACK_TOL = 1e-7  # Clarabel's soft slacks at the optimum

# Trace counts of the batched solve, keyed by (class name, settings): Python side effect.
TRACES: dict[tuple, int] = {}


def _batched(key, settings):
    """A jitted, vmapped solve that counts its traces in TRACES[key]."""

    def run(ocps):
        TRACES[key] = TRACES.get(key, 0) + 1
        return jax.vmap(lambda o: solve(o, settings))(ocps)

    return jax.jit(run)


def _index(batch, i):
    return jax.tree.map(lambda a: np.asarray(a[i]), batch)


def _u_max(ocp) -> np.ndarray:
    """The box bound of each input: the first 2 nu input rows are +-u_i <= u_max_i."""
    return np.asarray(ocp.fu)[0, : ocp.nu]


def _dynamics_residual(ocp, u, x) -> float:
    """max |x_{t+1} - A_t x_t - B_t u_t - c_t| (NumPy, independent of the solver's code)."""
    A, B, c = (np.asarray(a) for a in (ocp.A, ocp.B, ocp.c))
    x_prev = np.concatenate([np.asarray(ocp.x0)[None], x[:-1]])
    r = x - np.einsum("tij,tj->ti", A, x_prev) - np.einsum("tij,tj->ti", B, u) - c
    return float(np.max(np.abs(r)))


def _reference(ocp, clarabel_solve):
    """Clarabel's hard optimum (u, x, J) plus the soft-problem checks of rho."""
    hard = to_qp(ocp, soft=False)
    z, J, status = clarabel_solve(hard)
    soft = to_qp(ocp, soft=True)
    zs, Js, status_s = clarabel_solve(soft)
    u, x = split_solution(z, ocp.N, ocp.nx, ocp.nu)
    return {
        "u": u,
        "x": x,
        "J": J,
        "status": status,
        "status_soft": status_s,
        "soft_gap": abs(Js - J) / (1.0 + abs(J)),
        "max_slack": float(np.max(zs[soft.n_plan :], initial=0.0)),
    }


def _check(ocp, sol, ref, label) -> tuple[dict, list[str]]:
    """Compare one accurate-mode solution with Clarabel; return (metrics, failures)."""
    u, x = np.asarray(sol.u), np.asarray(sol.x)
    J = float(sol.objective)
    gap = (J - ref["J"]) / (1.0 + abs(ref["J"]))
    viol = float(max_violation(ocp, u, x)) + _dynamics_residual(ocp, u, x)
    du_rel = float(np.max(np.abs(u - ref["u"]) / _u_max(ocp)))
    lam = float(np.min(np.linalg.eigvalsh(np.asarray(ocp.R))))
    eps = CLARABEL_ALLOWANCE * (1.0 + abs(ref["J"]))
    bound = np.sqrt((max(J - ref["J"], 0.0) + eps) / lam) + np.sqrt(eps / lam)
    du_norm = float(np.linalg.norm(u - ref["u"]))
    m = {
        "status": int(sol.status),
        "iterations": int(sol.iterations),
        "gap": gap,
        "viol": viol,
        "du_rel": du_rel,
        "du_bound_ratio": du_norm / bound,
    }
    fails = []
    if ref["status"] != "Solved" or ref["status_soft"] != "Solved":
        fails.append(f"clarabel status {ref['status']}/{ref['status_soft']}")
    if not (ref["soft_gap"] <= RHO_RTOL and ref["max_slack"] <= SLACK_TOL):
        fails.append(f"rho too small: soft gap {ref['soft_gap']:.2e} slack {ref['max_slack']:.2e}")
    if m["status"] != Status.CONVERGED:
        fails.append(f"status {Status.name(m['status'])}")
    if not abs(gap) <= OBJ_RTOL:
        fails.append(f"objective gap {gap:.3e}")
    if not viol <= VIOL_TOL:
        fails.append(f"violation {viol:.3e}")
    if not du_rel <= U_REL_TOL:
        fails.append(f"|du|/u_max {du_rel:.3e}")
    if not du_norm <= bound:
        fails.append(f"|du| {du_norm:.3e} > strong-convexity bound {bound:.3e}")
    if fails:
        fails = [f"{label}: iterations {m['iterations']}, gap {gap:.3e}: " + "; ".join(fails)]
    return m, fails


# --------------------------------------------------------------------------------------------
# 1. Random feasible OCPs vs Clarabel


@pytest.fixture(scope="module")
def class_runs():
    """Lazily solved shape classes: name -> (list of OCPs, stacked accurate-mode Solution)."""
    cache = {}

    def get(name):
        if name not in cache:
            shape = SHAPE_CLASSES[name]
            ocps = [random_ocp(seed, shape) for seed in range(N_PROBLEMS[name])]
            run = _batched((name, ACCURATE), ACCURATE)
            half = len(ocps) // 2
            parts = [run(stack_ocps(ocps[:half])), run(stack_ocps(ocps[half:]))]
            sols = jax.tree.map(lambda *a: np.concatenate([np.asarray(b) for b in a]), *parts)
            cache[name] = (ocps, Solution(*sols))
        return cache[name]

    return get


@pytest.mark.parametrize("name", list(SHAPE_CLASSES))
def test_random_ocps_match_clarabel(name, class_runs, clarabel_solve):
    """Accurate mode on random feasible OCPs: objective, feasibility, status and plan."""
    ocps, sols = class_runs(name)
    shape = SHAPE_CLASSES[name]
    metrics, failures = [], []
    for seed, ocp in enumerate(ocps):
        ref = _reference(ocp, clarabel_solve)
        m, f = _check(ocp, _index(sols, seed), ref, f"{name} {tuple(shape[:3])} seed {seed}")
        metrics.append(m)
        failures += f
    it = np.array([m["iterations"] for m in metrics])
    print(
        f"\n[{name} nx={shape.nx} nu={shape.nu} N={shape.N}] {len(ocps)} problems: "
        f"iterations median {np.median(it):.0f} max {it.max()}; "
        f"max |gap| {max(abs(m['gap']) for m in metrics):.2e}; "
        f"max viol {max(m['viol'] for m in metrics):.2e}; "
        f"max |du|/u_max {max(m['du_rel'] for m in metrics):.2e}; "
        f"max |du|/bound {max(m['du_bound_ratio'] for m in metrics):.2f}"
    )
    for line in failures:
        print("  FAIL", line)
    assert not failures, "\n".join(failures)


def test_random_ocps_cover_the_brief():
    """The generator covers masked rows, time-varying data and active state rows."""
    tv, masked_u, masked_x = 0, 0, 0
    for name, shape in SHAPE_CLASSES.items():
        for seed in range(N_PROBLEMS[name]):
            o = random_ocp(seed, shape)
            tv += bool(np.any(np.asarray(o.A) != np.asarray(o.A)[0]))
            masked_u += bool(np.any(np.asarray(o.u_mask) == 0))
            masked_x += bool(np.any(np.asarray(o.x_mask) == 0))
            assert np.all(np.asarray(o.fu) > 0)
    total = sum(N_PROBLEMS.values())
    assert total >= 200
    assert tv > total // 4 and masked_u > total // 2 and masked_x > total // 2


def test_jit_traces_once(class_runs):
    """Repeated calls with new data of the same shape trace a jitted solve once.

    The batched solve of the small class was called on two different chunks of 40 problems;
    a jitted single solve is called on three different problems.
    """
    class_runs("small")
    assert TRACES[("small", ACCURATE)] == 1
    counter = {"n": 0}

    @jax.jit
    def single(o):
        counter["n"] += 1
        return solve(o, ACCURATE)

    objectives = [
        float(single(random_ocp(s, SHAPE_CLASSES["small"])).objective) for s in (200, 201, 202)
    ]
    assert counter["n"] == 1
    assert len(set(objectives)) == 3  # new data really reached the compiled program


# --------------------------------------------------------------------------------------------
# 2. fastmpc-3d first step


@pytest.fixture(scope="module")
def fastmpc_pair():
    """The first step with obstacles and without (same shapes: keep-out rows masked off, the
    QP of ``fastmpc3d_first_step(obstacles=False)``), stacked as a batch of two."""
    with_obs = fastmpc3d_first_step(obstacles=True)
    without = with_obs._replace(x_mask=jnp.zeros_like(with_obs.x_mask))
    plain = to_qp(fastmpc3d_first_step(obstacles=False), soft=False)
    masked = to_qp(without, soft=False)
    assert (abs(plain.G - masked.G).max(), np.abs(plain.h - masked.h).max()) == (0.0, 0.0)
    return [with_obs, without], stack_ocps([with_obs, without])


@pytest.fixture(scope="module")
def fastmpc_accurate(fastmpc_pair):
    """(jitted batched accurate solve, its solutions of the fastmpc pair)."""
    run = jax.jit(jax.vmap(lambda o: solve(o, ACCURATE)))
    return run, run(fastmpc_pair[1])


def test_fastmpc3d_accurate_matches_clarabel(fastmpc_pair, fastmpc_accurate, clarabel_solve):
    ocps, _ = fastmpc_pair
    _, sols = fastmpc_accurate
    failures = []
    for i, (ocp, label) in enumerate(zip(ocps, ("obstacles", "no obstacles"), strict=True)):
        ref = _reference(ocp, clarabel_solve)
        m, f = _check(ocp, _index(sols, i), ref, f"fastmpc-3d {label}")
        print(f"\n[fastmpc-3d {label}] accurate: {m}")
        failures += f
    assert not failures, "\n".join(failures)


def test_fastmpc3d_barrier_matches_clarabel(fastmpc_pair, clarabel_solve):
    """The primal barrier continuation (mode="barrier") reaches the same optimum."""
    ocps, batch = fastmpc_pair
    sols = jax.jit(jax.vmap(lambda o: solve(o, BARRIER)))(batch)
    failures = []
    for i, (ocp, label) in enumerate(zip(ocps, ("obstacles", "no obstacles"), strict=True)):
        ref = _reference(ocp, clarabel_solve)
        m, f = _check(ocp, _index(sols, i), ref, f"fastmpc-3d {label} barrier")
        print(f"\n[fastmpc-3d {label}] barrier: {m}")
        failures += f
    assert not failures, "\n".join(failures)


def test_fastmpc3d_paper_mode_gap(fastmpc_pair, clarabel_solve):
    """Paper mode (kappa = 0.05, 10 iterations) returns a feasible barrier iterate.

    Measured relative objective gap (J_paper - J*) / |J*| to Clarabel's optimum:
    0.151 with obstacles, 0.348 without (status max_iter after 10 iterations in both).
    """
    ocps, batch = fastmpc_pair
    sols = jax.jit(jax.vmap(lambda o: solve(o, PAPER)))(batch)
    for i, (ocp, label) in enumerate(zip(ocps, ("obstacles", "no obstacles"), strict=True)):
        ref = _reference(ocp, clarabel_solve)
        sol = _index(sols, i)
        gap = (float(sol.objective) - ref["J"]) / abs(ref["J"])
        viol = float(max_violation(ocp, sol.u, sol.x))
        print(
            f"\n[fastmpc-3d {label}] paper mode: gap {gap:.4f}, status "
            f"{Status.name(sol.status)}, iterations {int(sol.iterations)}, violation {viol:.1e}"
        )
        assert np.isfinite(gap)
        assert gap >= -1e-9
        assert viol <= VIOL_TOL
        assert np.all(np.isfinite(sol.u)) and np.all(np.isfinite(sol.x))


@pytest.mark.parametrize(
    "settings", [ACCURATE, PAPER, BARRIER], ids=["accurate", "paper", "barrier"]
)
def test_dense_isnm_matches_riccati(settings):
    """The dense KKT solve gives the same iterates as the Riccati recursion."""
    ocp = random_ocp(1, SHAPE_CLASSES["small"], time_varying=True)
    dense = dataclasses.replace(settings, method="dense")
    a, b = solve(ocp, settings), solve(ocp, dense)
    assert int(a.iterations) == int(b.iterations)
    assert int(a.status) == int(b.status)
    for field in ("u", "x", "nu", "objective"):
        fa, fb = np.asarray(getattr(a, field)), np.asarray(getattr(b, field))
        np.testing.assert_allclose(fb, fa, rtol=0, atol=1e-8 * max(1.0, np.max(np.abs(fa))))


# --------------------------------------------------------------------------------------------
# 3. vmap, tracing, dtype


def test_vmap_equals_loop(class_runs):
    ocps, sols = class_runs("small")
    for i in range(6):
        single = solve(ocps[i], ACCURATE)
        batched = _index(sols, i)
        assert int(single.iterations) == int(batched.iterations)
        assert int(single.status) == int(batched.status)
        for field in ("u", "x", "nu", "objective"):
            fa, fb = np.asarray(getattr(single, field)), np.asarray(getattr(batched, field))
            np.testing.assert_allclose(fb, fa, rtol=0, atol=1e-10 * max(1.0, np.max(np.abs(fa))))


def test_solve_batch_equals_vmap(class_runs):
    """Chunked lax.map of vmap (solve_batch) returns what one vmap returns."""
    ocps, sols = class_runs("small")
    half = len(ocps) // 2
    chunked = jax.jit(solve_batch, static_argnames=("settings", "chunk"))(
        stack_ocps(ocps[:half]), ACCURATE, chunk=16
    )
    for field in ("u", "x", "objective", "status", "iterations"):
        a = np.asarray(getattr(sols, field))[:half]
        np.testing.assert_allclose(
            np.asarray(getattr(chunked, field)),
            a,
            rtol=0,
            atol=1e-10 * max(1.0, float(np.max(np.abs(a)))),
        )


_FLOAT32_CHILD = """
import sys
import jax, jax.numpy as jnp, numpy as np
import rvdjax
sys.path.insert(0, {tests!r})
from ocp_factory import SHAPE_CLASSES, random_ocp
from rvdjax.problems import stack_ocps
from rvdjax.solver import SolverSettings, solve
ocps = [random_ocp(seed, SHAPE_CLASSES["small"]) for seed in range({n})]
b32 = jax.tree.map(lambda a: a.astype(jnp.float32), stack_ocps(ocps))
s = jax.jit(jax.vmap(lambda o: solve(o, SolverSettings(mode="accurate"))))(b32)
dtypes = {{str(s.u.dtype), str(s.x.dtype), str(s.objective.dtype)}}
finite = all(bool(np.all(np.isfinite(np.asarray(a)))) for a in (s.u, s.x, s.nu, s.objective))
print(",".join(sorted(dtypes)), finite)
print(" ".join(str(int(v)) for v in np.asarray(s.status)))
print(" ".join(repr(float(v)) for v in np.asarray(s.objective)))
"""


def test_float32_inputs(class_runs):
    """float32 OCPs are solved in float32: the outputs stay float32 (no silent upcast).

    The accurate mode's tol = 1e-9 is below float32 resolution (eps 1.2e-7), so such solves
    rarely converge: they end as max_iter or nonfinite with the last finite iterate, which can
    be far from the optimum. Required: finite outputs, honest status codes, and a converged
    float32 solve is as good as float32 allows (objective within 1e-4 of float64).

    The float32 solve runs in a fresh interpreter at XLA's default optimisation level, the
    level a user's program compiles at: float32 rounding depends on the generated code (the
    suite compiles at level 0, tests/conftest.py, where the same solves land at 1.0e-4 instead
    of 5e-5).
    """
    import os
    import subprocess
    import sys

    assert ACCURATE == SolverSettings(mode="accurate")
    small, ref = class_runs("small")
    n = 40
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    code = _FLOAT32_CHILD.format(tests=os.path.dirname(os.path.abspath(__file__)), n=n)
    child = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600
    )
    assert child.returncode == 0, child.stderr[-2000:]
    head, statuses, objectives = child.stdout.strip().split("\n")[-3:]
    assert head == "float32 True"  # every output float32 and finite
    status = np.array([int(v) for v in statuses.split()])
    assert set(status.tolist()) <= {0, 1, 2, 3}
    J64 = np.asarray(ref.objective)[:n]
    J32 = np.array([float(v) for v in objectives.split()])
    rel = np.abs(J32 - J64) / (1 + np.abs(J64))
    print(
        f"\n[float32] statuses {np.bincount(status, minlength=4).tolist()} "
        f"(converged, max_iter, infeasible, nonfinite); max rel objective error "
        f"{np.max(rel):.2e}, when converged {np.max(rel[status == 0], initial=0):.2e}"
    )
    assert np.all(rel[status == Status.CONVERGED] <= 1e-4)


# --------------------------------------------------------------------------------------------
# 4. Status codes, never NaN


def _small_like(**kw) -> OCP:
    """A problem of the small class's shapes (N=5, nx=2, nu=1, mu=3, mx=2): reuses its jit."""
    return random_ocp(7, SHAPE_CLASSES["small"])._replace(**kw)


def _assert_finite(sol):
    for field in ("u", "x", "nu", "objective"):
        assert np.all(np.isfinite(np.asarray(getattr(sol, field)))), field


def test_infeasible_state_rows_status():
    """A keep-out row reached next step that a tiny thrust cannot avoid: INFEASIBLE, finite."""
    A = np.array([[1.0, 1.0], [0.0, 1.0]])
    B = np.array([[0.5], [1.0]])
    ocp = make_ocp(
        A, B, [0.0, 1.0], np.eye(2), np.eye(1), N=5, u_max=1e-3,
        Fu=np.zeros((1, 1)), fu=[1.0], u_mask=[1.0, 1.0, 0.0],
        Fx=np.array([[1.0, 0.0], [1.0, 0.0]]), fx=[0.5, 0.5], rho=1e4, x_mask=[1.0, 0.0],
    )  # fmt: skip
    sol = solve(ocp, ACCURATE)
    assert int(sol.status) == Status.INFEASIBLE
    _assert_finite(sol)
    assert float(max_violation(ocp, sol.u, sol.x)) > 0.4


@pytest.mark.parametrize("fu0", [0.0, -0.1])
def test_no_strictly_feasible_input_status(fu0):
    """OCP(...) without validation, an input row with fu <= 0: INFEASIBLE, finite output."""
    base = _small_like()
    ocp = base._replace(fu=base.fu.at[:, 0].set(fu0))
    sol = solve(ocp, ACCURATE)
    assert int(sol.status) == Status.INFEASIBLE
    _assert_finite(sol)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_nonfinite_x0_status(bad):
    """NaN / inf in x0 (OCP(...) without validation): status nonfinite, no NaN anywhere.

    The plan is zero and the objective +inf (documented in ``solve``).
    """
    base = _small_like()
    ocp = base._replace(x0=base.x0.at[0].set(bad))
    for settings in (ACCURATE, PAPER):
        sol = solve(ocp, settings)
        assert int(sol.status) == Status.NONFINITE
        for field in ("u", "x", "nu", "kappa", "residual"):
            assert not np.any(np.isnan(np.asarray(getattr(sol, field)))), field
        assert np.all(np.isfinite(np.asarray(sol.u))) and np.all(np.isfinite(np.asarray(sol.x)))
        assert float(sol.objective) == np.inf


# --------------------------------------------------------------------------------------------
# 5. Input validation


def _good_args():
    A = np.array([[1.0, 1.0], [0.0, 1.0]])
    B = np.array([[0.5], [1.0]])
    return dict(A=A, B=B, x0=np.array([1.0, 0.0]), Q=np.eye(2), R=np.eye(1), N=4, u_max=1.0)


@pytest.mark.parametrize(
    "change, word",
    [
        (dict(x0=np.array([np.nan, 0.0])), "x0"),
        (dict(x0=np.zeros(3)), "x0"),
        (dict(R=np.array([[0.0]])), "R"),
        (dict(R=-np.eye(1)), "R"),
        (dict(Q=np.diag([1.0, -1.0])), "Q"),
        (dict(Q=np.array([[1.0, 2.0], [0.0, 1.0]])), "Q"),
        (dict(Fx=np.array([[1.0, 0.0]]), fx=[1.0], rho=0.0), "rho"),
        (dict(Fx=np.array([[1.0, 0.0]]), fx=[1.0], rho=-5.0), "rho"),
        (dict(A=np.eye(3)), "A"),
        (dict(B=np.ones(2)), "B"),
        (dict(N=0), "N"),
        (dict(N=2.5), "N"),
        (dict(Fu=np.array([[1.0]]), fu=[0.0]), "fu"),
        (dict(Fu=np.array([[1.0]]), fu=[-1.0]), "fu"),
        (dict(u_max=0.0), "u_max"),
        (dict(Q_f=np.full((2, 2), np.inf)), "Q"),
    ],
)
def test_make_ocp_rejects_bad_inputs(change, word):
    args = {**_good_args(), **change}
    with pytest.raises(ValueError, match=word):
        make_ocp(**args)


@pytest.mark.parametrize(
    "kw, word",
    [
        (dict(mode="x"), "mode"),
        (dict(method="lu"), "method"),
        (dict(max_iter=0), "max_iter"),
        (dict(line_search_batch=0), "line_search_batch"),
        (dict(paper_start="cold"), "paper_start"),
        (dict(backend="osqp"), "backend"),
        (dict(step_fraction="full"), "step_fraction"),
    ],
)
def test_settings_reject_bad_values(kw, word):
    with pytest.raises(ValueError, match=word):
        SolverSettings(**kw)


@pytest.mark.parametrize(
    "kw, word",
    [
        (dict(beta=1.5), "beta"),
        (dict(alpha=0.7), "alpha"),
        (dict(kappa=0.0), "kappa"),
        (dict(tol=-1.0), "tol"),
        (dict(kappa_factor=1.0), "kappa_factor"),
        (dict(kappa=float("nan")), "kappa"),
    ],
)
def test_solver_params_reject_bad_values(kw, word):
    with pytest.raises(ValueError, match=word):
        SolverParams.paper(**kw)


# --------------------------------------------------------------------------------------------
# 6. Warm start


def test_warm_start_next_step(fastmpc_pair, fastmpc_accurate, clarabel_solve):
    """fastmpc-3d step 2 from shift_solution(step 1): converges to the cold / Clarabel optimum.

    Step 2: x0 = the planned x_1 of step 1, obstacles moved on by one sampling time, keep-out
    rows re-linearised about the new drift path.
    """
    p = FASTMPC3D
    run, sols = fastmpc_accurate
    fastmpc_pair[0][0]
    sol1 = Solution(*_index(sols, 0))
    assert int(sol1.status) == Status.CONVERGED
    x1 = np.asarray(sol1.x[0])  # the state after applying u_0
    nxt = fastmpc3d_step(x1, p["ts"])
    warm = solve(nxt, ACCURATE, init=shift_solution(sol1))
    cold = _index(run(stack_ocps([nxt, fastmpc_pair[0][1]])), 0)  # no new compile
    ref = _reference(nxt, clarabel_solve)
    m, failures = _check(nxt, warm, ref, "fastmpc-3d step 2 warm")
    print(f"\n[warm start] iterations warm {int(warm.iterations)} cold {int(cold.iterations)}; {m}")
    assert not failures, "\n".join(failures)
    assert abs(float(warm.objective) - float(cold.objective)) <= 1e-8 * abs(float(cold.objective))


@pytest.mark.users_compiler  # two programs to 1e-12: XLA's default emitters (conftest.py)
def test_the_adaptive_step_length_and_the_differentiated_solve(clarabel_solve):
    """The corrector's step length (docs/solver.md). fastmpc-3d's first 20 MPC steps, each
    warm-started from the previous plan shifted (the state moves along the plan): steps 13-20,
    where the warm start is close, take fewer iterations stepping 1 - sigma of the way to the
    boundary than 0.99 of the way ("fixed"), and both end at Clarabel's optimum (their states
    drift apart by the plans' 1e-6 differences). A solve
    under differentiation steps 0.99 of the way whatever the settings say: value_and_grad's
    plan is the fixed solve's (to rounding), not the adaptive one's (2e-6 apart here)."""
    fixed = SolverSettings(step_fraction="fixed")
    iterations, last = {}, {}
    for settings in (ACCURATE, fixed):
        sol = solve(fastmpc3d_first_step(), settings)
        its = []
        for k in range(1, 21):
            ocp = fastmpc3d_step(np.asarray(sol.x[0]), k * FASTMPC3D["ts"])
            sol = solve(ocp, settings, init=shift_solution(sol))
            its.append(int(sol.iterations))
        iterations[settings.step_fraction], last[settings.step_fraction] = its, (ocp, sol)
    assert sum(iterations["adaptive"][12:]) < sum(iterations["fixed"][12:]), iterations
    for name, (ocp, sol) in last.items():  # states 2e-4 apart by now: each its own reference
        _, failures = _check(ocp, sol, _reference(ocp, clarabel_solve), f"step 20, {name}")
        assert not failures, "\n".join(failures)

    prev = solve(fastmpc3d_first_step(), ACCURATE)
    ocp = fastmpc3d_step(np.asarray(prev.x[0]), FASTMPC3D["ts"])
    init = shift_solution(prev)

    def plan(x0, settings=ACCURATE):
        u = solve(ocp._replace(x0=x0), settings, init=init).u
        return jnp.sum(u), u

    (_, u_grad), g = jax.value_and_grad(plan, has_aux=True)(ocp.x0)
    assert np.all(np.isfinite(np.asarray(g)))
    u_fixed = np.asarray(plan(ocp.x0, fixed)[1])
    u_adaptive = np.asarray(plan(ocp.x0)[1])
    scale = np.max(np.abs(u_fixed))
    assert np.max(np.abs(np.asarray(u_grad) - u_fixed)) <= 1e-12 * scale
    assert np.max(np.abs(np.asarray(u_grad) - u_adaptive)) > 1e-9 * scale


def test_paper_start_feasible_keeps_the_dynamics(fastmpc_pair, fastmpc_accurate):
    """Paper mode from a warm start whose states do not match the new x0 (the shifted plan of
    step 1 against a perturbed measurement), cut after 2 Newton steps: the default feasible
    start returns a plan that obeys the dynamics to rounding; Algorithm 1's literal infeasible
    start ("warm") still carries part of the initial dynamics residual (it shrinks by the
    factor (1 - t) of each step), so its u_0 belongs to no flyable plan."""
    from rvdjax.solver.barrier import dyn_residual

    _, sols = fastmpc_accurate
    first = fastmpc_pair[0][0]
    sol1 = Solution(*_index(sols, 0))
    x1 = np.asarray(sol1.x[0]) + np.array([5.0, -5.0, 2.0, 0.01, 0.0, -0.01])
    nxt = first._replace(x0=jnp.asarray(x1))
    init = shift_solution(sol1)
    scale = float(np.max(np.abs(x1)))
    res = {}
    for start in ("feasible", "warm"):
        settings = SolverSettings.paper(max_iter=2, paper_start=start)
        sol = solve(nxt, settings, init=init)
        assert int(sol.status) in (Status.CONVERGED, Status.MAX_ITER)
        res[start] = float(jnp.max(jnp.abs(dyn_residual(nxt, sol.u, sol.x)))) / scale
    assert res["feasible"] < 1e-12
    assert res["warm"] > 1e-6


def test_track_start_is_the_lqr_tracking_optimum(fastmpc_pair, fastmpc_accurate):
    """paper_start="track": the start inputs minimise sum (x - x_prev)'Q(x - x_prev) +
    (u - u_prev)'R(u - u_prev) under the dynamics from the new x0 — checked against the dense
    equality-constrained least-squares solution (NumPy KKT solve), and its states are closer
    to the previous plan (in that weighted measure) than the drift of the shifted inputs."""
    from rvdjax.solver.start import drift, track_plan

    _, sols = fastmpc_accurate
    first = fastmpc_pair[0][0]
    sol1 = Solution(*_index(sols, 0))
    init = shift_solution(sol1)
    x1 = np.asarray(sol1.x[0]) + np.array([5.0, -5.0, 2.0, 0.01, 0.0, -0.01])
    ocp = first._replace(x0=jnp.asarray(x1))
    u = np.asarray(track_plan(ocp, init.u, init.x, "riccati"))
    # dense reference: z = (u_0, x_1, ..., u_{N-1}, x_N)
    N, nx, nu = ocp.N, ocp.nx, ocp.nu
    A, B = np.asarray(ocp.A), np.asarray(ocp.B)
    n = N * (nx + nu)
    H, g = np.zeros((n, n)), np.zeros(n)
    C, b = np.zeros((N * nx, n)), np.zeros(N * nx)
    for t in range(N):
        iu, ix = t * (nx + nu), t * (nx + nu) + nu
        H[iu : iu + nu, iu : iu + nu] = 2 * np.asarray(ocp.R[t])
        H[ix : ix + nx, ix : ix + nx] = 2 * np.asarray(ocp.Q[t])
        g[iu : iu + nu] = -2 * np.asarray(ocp.R[t]) @ np.asarray(init.u[t])
        g[ix : ix + nx] = -2 * np.asarray(ocp.Q[t]) @ np.asarray(init.x[t])
        C[t * nx : (t + 1) * nx, ix : ix + nx] = np.eye(nx)
        C[t * nx : (t + 1) * nx, iu : iu + nu] = -B[t]
        if t == 0:
            b[:nx] = A[0] @ x1
        else:
            C[t * nx : (t + 1) * nx, ix - nx - nu : ix - nu] = -A[t]
    K = np.block([[H, C.T], [C, np.zeros((N * nx, N * nx))]])
    z = np.linalg.solve(K, np.concatenate([-g, b]))[:n]
    u_ref = np.stack([z[t * (nx + nu) : t * (nx + nu) + nu] for t in range(N)])
    np.testing.assert_allclose(u, u_ref, rtol=0, atol=1e-8 * FASTMPC3D["u_max"])

    def tracking(uu):
        e = np.asarray(drift(ocp, jnp.asarray(uu))) - np.asarray(init.x)
        du = np.asarray(uu) - np.asarray(init.u)
        return np.einsum("ti,tij,tj->", e, np.asarray(ocp.Q), e) + np.einsum(
            "ti,tij,tj->", du, np.asarray(ocp.R), du
        )

    assert tracking(u) < 0.5 * tracking(init.u)


@pytest.mark.parametrize("settings", [ACCURATE, PAPER, BARRIER], ids=lambda s: s.mode)
def test_iterate_leaves_a_finished_or_frozen_solve_unchanged(settings):
    """A solve that met its stopping test, and one frozen before it did (the batch engine's
    free slots), come back from one more iteration with every field's values as they were;
    the same iteration moves a solve that is neither (so the check could fail). In accurate
    mode a stopped solve takes a step of length zero; the others keep the old state. A batched
    solve relies on it: its loop runs every problem's iteration until the last one finishes
    (driver._until_finished)."""
    from rvdjax.solver import finished, freeze, iterate, start

    ocp, params = random_ocp(3, SHAPE_CLASSES["small"]), SolverParams.for_settings(settings)
    ocp, st = start(ocp, settings, params)
    step = jax.jit(lambda s: iterate(ocp, settings, params, s))
    moved = step(st)
    assert not np.array_equal(np.asarray(moved.core.u), np.asarray(st.core.u))
    # the barrier terms, counted once at the start for every iteration: one per input row,
    # two per soft state row (s >= 0, s >= g)
    wu, wx = np.asarray(ocp.u_mask, float), np.asarray(ocp.x_mask, float)
    assert float(moved.n_barrier) == float(st.n_barrier) == wu.sum() + 2.0 * wx.sum() > 0
    for state in (freeze(st), jax.lax.while_loop(lambda s: ~finished(settings, s), step, st)):
        again = step(state)
        assert bool(finished(settings, state))
        for a, b in zip(jax.tree.leaves(state), jax.tree.leaves(again), strict=True):
            np.testing.assert_array_equal(np.asarray(b), np.asarray(a))


def _split_input_lp(eps: float = 1e-7) -> OCP:
    """fastmpc-3d's first step with paper 003's fuel-optimal input form: each input split into
    two parts v1, v2 >= 0 (B' = [B, -B]) with a linear cost on both (1e3 per m/s), the lower
    bounds relaxed to -eps u_max so that u = 0 is strictly feasible, as the LP family writes
    them (rvdjax.families.phases_inputs.LP_EPS), and R' = 1e-9 I."""
    o = fastmpc3d_first_step()
    N, _, nu = o.B.shape
    u_max = float(np.max(np.asarray(o.fu)))
    e = jnp.eye(2 * nu)
    hi, lo = jnp.full(2 * nu, (1 - eps) * u_max), jnp.full(2 * nu, eps * u_max)
    return o._replace(
        B=jnp.concatenate([o.B, -o.B], axis=-1),
        R=jnp.broadcast_to(1e-9 * e, (N, 2 * nu, 2 * nu)),
        r=jnp.full((N, 2 * nu), 1e3),
        Fu=jnp.broadcast_to(jnp.concatenate([e, -e]), (N, 4 * nu, 2 * nu)),
        fu=jnp.broadcast_to(jnp.concatenate([hi, lo]), (N, 4 * nu)),
        u_mask=jnp.ones((N, 4 * nu)),
    )


def test_a_start_a_hair_from_its_input_rows_is_lifted(clarabel_solve):
    """Split inputs bounded 1e-7 u_max below zero: from the cold start u = 0 the central
    multipliers are 1e7x the others and the solve crept to its iteration cap (measured with
    the lift taken out: 100 iterations, MAX_ITER, an objective 14 % high); lifted towards the
    input rows' anchor (start.lift_inside) it converges in 18 (asked: under 30), at Clarabel's
    optimum. A start with no row that close (fastmpc-3d's symmetric thrust box, a warm start
    pulled to 1 % of a limit) is left as it is, to the bit."""
    from rvdjax.solver.barrier import rows_of, u_slack
    from rvdjax.solver.start import input_anchor, lift_inside

    lp = _split_input_lp()
    sol = solve(lp)
    ref = _reference(lp, clarabel_solve)
    gap = (float(sol.objective) - ref["J"]) / (1.0 + abs(ref["J"]))
    assert int(sol.status) == Status.CONVERGED and int(sol.iterations) < 30, int(sol.iterations)
    assert abs(gap) <= OBJ_RTOL, gap
    assert float(max_violation(lp, sol.u, sol.x)) <= VIOL_TOL

    rows = rows_of(lp)
    u0 = jnp.zeros((lp.N, lp.nu))
    lifted = lift_inside(rows, u0)
    anchor, s_a = input_anchor(rows)
    np.testing.assert_allclose(np.asarray(s_a), np.asarray(u_slack(rows, anchor)), atol=1e-15)
    assert np.all(np.asarray(s_a) > 0)  # the anchor is inside every row
    assert np.all(np.asarray(u_slack(rows, lifted)) >= 0.1 * np.asarray(s_a) * (1 - 1e-12))

    box = rows_of(fastmpc3d_first_step())
    u = 0.99 * jnp.broadcast_to(box.fu[:, :3], (lp.N, 3))  # at 1 % of the upper limits
    for start in (jnp.zeros_like(u), u):
        assert np.array_equal(np.asarray(lift_inside(box, start)), np.asarray(start))
