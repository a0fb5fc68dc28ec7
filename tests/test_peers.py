"""Peer QP solvers (rvdjax.peers) against Clarabel, and Clarabel against a direct KKT solve."""

from __future__ import annotations

import numpy as np
import pytest

from rvdjax import peers
from rvdjax.ocp import make_ocp
from rvdjax.qp import QP, qp_objective, to_qp

NX, NU, N = 4, 2, 8
DT = 0.5


def _ocp(x0, rho=1e6, constrained=True):
    """Planar double integrator steered to the origin, |u| <= 1, two state rows."""
    A = np.eye(NX)
    A[0, 2] = A[1, 3] = DT
    B = np.zeros((NX, NU))
    B[:2] = 0.5 * DT**2 * np.eye(NU)
    B[2:] = DT * np.eye(NU)
    kw = {}
    if constrained:
        # x_pos <= 0.2 (the target is at 0) and y_vel >= -0.3: active along the optimal path.
        kw = dict(
            u_max=1.0,
            Fx=np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, -1.0]]),
            fx=np.array([0.2, 0.3]),
            rho=rho,
        )
    return make_ocp(
        A,
        B,
        np.asarray(x0, float),
        np.diag([1.0, 1.0, 0.1, 0.1]),
        0.5 * np.eye(NU),
        N=N,
        Q_f=10.0 * np.eye(NX),
        **kw,
    )


X0 = np.array([-3.0, 2.0, 1.5, -0.2])


@pytest.fixture(scope="module")
def problems() -> dict[str, QP]:
    return {
        "hard": to_qp(_ocp(X0), soft=False),
        "soft": to_qp(_ocp(X0), soft=True),  # rho = 1e6: same optimum as "hard"
        "soft_violated": to_qp(_ocp(X0, rho=0.5), soft=True),  # cheap penalty: slacks > 0
    }


@pytest.fixture(scope="module")
def reference(problems) -> dict[str, peers.PeerResult]:
    return {name: peers.solve_clarabel(qp, mode="reference") for name, qp in problems.items()}


def test_registry():
    assert set(peers.PEERS) == {
        "clarabel", "piqp", "daqp", "daqp-condensed", "osqp", "hpipm", "qpax"
    }  # fmt: skip
    avail = peers.available_peers()
    assert "clarabel" in avail
    assert set(avail) <= set(peers.PEERS)


def test_problems_exercise_constraints(problems, reference):
    # Some inequality rows are active at the optimum, and the cheap-penalty form uses slacks.
    for name in ("hard", "soft"):
        qp, z = problems[name], reference[name].z
        assert np.sum(np.abs(qp.G @ z - qp.h) < 1e-6) >= 2
    qp, z = problems["soft_violated"], reference["soft_violated"].z
    assert np.max(z[qp.n_plan :]) > 1e-3
    # exact penalty: soft optimum = hard optimum for large rho
    assert reference["soft"].objective == pytest.approx(reference["hard"].objective, rel=1e-8)


@pytest.mark.parametrize("name", ["hard", "soft", "soft_violated"])
def test_clarabel_reference_feasible(problems, reference, name):
    qp, res = problems[name], reference[name]
    assert res.status == "Solved"
    assert np.max(np.abs(qp.A_eq @ res.z - qp.b_eq)) < 1e-8
    assert np.max(qp.G @ res.z - qp.h) < 1e-8
    assert res.objective == pytest.approx(qp_objective(qp, res.z))
    assert res.iterations > 0 and res.solve_ms > 0 and res.setup_ms > 0
    bench = peers.solve_clarabel(qp, mode="benchmark")
    assert bench.status == "Solved"
    assert bench.objective == pytest.approx(res.objective, rel=1e-6, abs=1e-8)


def test_clarabel_equality_only_matches_kkt():
    # No input or state rows: G is empty; solve [[P, A'], [A, 0]] [z; y] = [-q; b] directly.
    x_ref = np.tile([0.5, -0.2, 0.0, 0.0], (N, 1))
    ocp = _ocp(X0, constrained=False)._replace(x_ref=x_ref)
    qp = to_qp(ocp)
    assert qp.G.shape[0] == 0
    P, A = qp.P.toarray(), qp.A_eq.toarray()
    nz, m = P.shape[0], A.shape[0]
    K = np.block([[P, A.T], [A, np.zeros((m, m))]])
    z_kkt = np.linalg.solve(K, np.concatenate([-qp.q, qp.b_eq]))[:nz]
    res = peers.solve_clarabel(qp)
    assert res.status == "Solved"
    np.testing.assert_allclose(res.z, z_kkt, atol=1e-8, rtol=0)
    assert res.objective == pytest.approx(qp_objective(qp, z_kkt), rel=1e-10, abs=1e-8)


def test_clarabel_bad_mode(problems):
    with pytest.raises(ValueError, match="mode"):
        peers.solve_clarabel(problems["hard"], mode="fast")


# (peer, expected status, relative objective tolerance vs Clarabel reference)
PEER_CASES = [
    ("piqp", "PIQP_SOLVED", 1e-7),
    ("daqp", "EXIT_OPTIMAL", 1e-7),
    ("daqp-condensed", "EXIT_OPTIMAL", 1e-7),
    ("osqp", "solved", 1e-3),
    ("hpipm", "SUCCESS", 1e-7),
    ("qpax", "converged", 1e-5),
]


def _skip_unless_usable(peer: str):
    if peer == "hpipm":
        if not peers.hpipm_library():
            pytest.skip(f"HPIPM: {peers.hpipm_unavailable()}")
    else:
        pytest.importorskip(peers._MODULE.get(peer, peer))


@pytest.mark.parametrize("name", ["hard", "soft", "soft_violated"])
@pytest.mark.parametrize(("peer", "status", "rtol"), PEER_CASES)
def test_peer_agrees_with_clarabel(problems, reference, peer, status, rtol, name):
    _skip_unless_usable(peer)
    qp, ref = problems[name], reference[name]
    res = peers.PEERS[peer](qp)
    assert res.status == status
    assert res.z.shape == ref.z.shape
    assert res.objective == pytest.approx(ref.objective, rel=rtol, abs=1e-8)
    assert res.objective == pytest.approx(qp_objective(qp, res.z))
    assert np.max(np.abs(qp.A_eq @ res.z - qp.b_eq)) < 1e3 * rtol
    assert np.max(qp.G @ res.z - qp.h) < 1e3 * rtol
    assert res.iterations >= 0 and res.solve_ms > 0


def test_qpax_scaling_needed(problems):
    pytest.importorskip("qpax")
    qp = problems["soft"]
    assert peers.solve_qpax(qp, scale=True).status == "converged"
    assert peers.solve_qpax(qp, scale=False).status == "not_converged"


def test_qpax_batch(problems):
    pytest.importorskip("qpax")
    import jax

    rng = np.random.default_rng(0)
    x0s = X0 + 0.3 * rng.standard_normal((3, NX))
    qps = [to_qp(_ocp(x0), soft=True) for x0 in x0s]
    batch = peers.qpax_batch_solver(qps)
    assert batch.batch_size == 3
    z, converged, iters = jax.block_until_ready(batch())
    assert z.shape == (3, qps[0].P.shape[0])
    assert np.all(np.asarray(converged) == 1)
    for qp, zi in zip(qps, np.asarray(z), strict=True):
        ref = peers.solve_clarabel(qp)
        assert qp_objective(qp, zi) == pytest.approx(ref.objective, rel=1e-5)
    with pytest.raises(ValueError, match="same shapes"):
        peers.qpax_batch_solver([problems["hard"], problems["soft"]])


@pytest.mark.parametrize("backend", ["clarabel", "piqp", "daqp", "daqp-condensed", "hpipm"])
def test_peer_backend_reports_a_solved_qp_as_converged(backend):
    """SolverSettings(backend=...) solves the OCP with a host peer inside the jitted solve; a
    QP the peer solved is reported as converged, at rvdjax's optimum (PIQP's "PIQP_SOLVED"
    was reported as max_iter until 2026-12-06)."""
    _skip_unless_usable(backend)
    from rvdjax.problems import fastmpc3d_first_step
    from rvdjax.solver import SolverSettings, Status, solve

    ocp = fastmpc3d_first_step()
    sol = solve(ocp, SolverSettings(backend=backend))
    ref = solve(ocp)
    assert int(sol.status) == Status.CONVERGED, Status.name(int(sol.status))
    assert int(sol.iterations) > 0
    assert float(sol.objective) == pytest.approx(float(ref.objective), rel=1e-6)


@pytest.mark.parametrize("name", ["hard", "soft", "soft_violated"])
def test_hpipm_stages_rebuild_the_standard_form(problems, name):
    """HPIPM's stages of a standard-form QP (peers_hpipm.ocp_stages, no library needed): the
    sparse QP assembled again from them, as HPIPM's OCP QP reads them (stage 0 without a
    state, stage N without an input, the state rows' slacks as softened rows), is the QP."""
    from rvdjax.peers_hpipm import ocp_stages

    qp = problems[name]
    st = ocp_stages(qp)
    N = len(st.nx) - 1
    assert st.nx == [0] + [NX] * N and st.nu == [NU] * N + [0]
    nz = qp.P.shape[0]
    P = np.zeros((nz, nz))
    q = np.zeros(nz)
    A_eq = np.zeros((N * NX, nz))
    G_rows, h = [], []
    for k in range(N + 1):
        u, x = st.u_cols[k], st.x_cols[k]
        P[np.ix_(u, u)] = st.R[k]
        P[np.ix_(x, x)] = st.Q[k]
        P[np.ix_(u, x)] = st.S[k]
        P[np.ix_(x, u)] = st.S[k].T
        q[u], q[x] = st.r[k], st.q[k]
        q[st.s_cols[k]] = st.z[k]
        if k < N:
            rows = np.arange(k * NX, (k + 1) * NX)
            A_eq[np.ix_(rows, st.x_cols[k + 1])] = np.eye(NX)
            A_eq[np.ix_(rows, u)] = -st.B[k]
            A_eq[np.ix_(rows, x)] = -st.A[k]
            np.testing.assert_array_equal(st.b[k], qp.b_eq[rows])
        for j in range(len(st.ug[k])):
            row = np.zeros(nz)
            row[x], row[u] = st.C[k][j], st.D[k][j]
            if j in st.soft[k]:
                row[st.s_cols[k][list(st.soft[k]).index(j)]] = -1.0
            G_rows.append(row)
            h.append(st.ug[k][j])
    np.testing.assert_array_equal(P, qp.P.toarray())
    np.testing.assert_array_equal(q, qp.q)
    np.testing.assert_array_equal(A_eq, qp.A_eq.toarray())
    # the standard form's rows: every stage row, then each slack's -s <= 0 (HPIPM's own bound)
    G = qp.G.toarray()
    plan_rows = np.any(G[:, : qp.n_plan] != 0, axis=1)
    np.testing.assert_array_equal(np.array(G_rows).reshape(-1, nz), G[plan_rows])
    np.testing.assert_array_equal(np.array(h), qp.h[plan_rows])
    n_slack = nz - qp.n_plan
    assert sum(len(s) for s in st.soft) == n_slack == int(np.sum(~plan_rows))
    assert (n_slack > 0) == (name != "hard")


def test_hpipm_refuses_what_it_cannot_read(problems, monkeypatch, tmp_path):
    """A QP whose cost couples two stages is not an OCP QP; HPIPM's library missing, the
    peer is unavailable with the reason and ``solve_hpipm`` says so."""
    import scipy.sparse as sp

    from rvdjax import peers_hpipm
    from rvdjax.peers_hpipm import ocp_stages

    qp = problems["hard"]
    P = qp.P.tolil()
    P[0, qp.n_plan - 1] = P[qp.n_plan - 1, 0] = 0.1  # u_0 with x_N
    with pytest.raises(ValueError, match="couples two stages"):
        ocp_stages(qp._replace(P=sp.csc_matrix(P)))
    with pytest.raises(ValueError, match="to_qp"):
        ocp_stages(qp._replace(nu=0))
    G = qp.G.tolil()
    G[0, qp.n_plan - 1] = 1.0  # a stage-0 row reaching x_N
    with pytest.raises(ValueError, match="row 0 of G spans two stages"):
        ocp_stages(qp._replace(G=sp.csc_matrix(G)))
    soft = problems["soft"]
    G = soft.G.toarray()
    s0 = soft.n_plan  # the first slack column, in one row: put it in a second row too
    other = next(i for i in range(G.shape[0]) if G[i, s0] == 0 and G[i, : soft.n_plan].any())
    G[other, s0] = -1.0
    with pytest.raises(ValueError, match=f"slack column {s0} is not one row's -s"):
        ocp_stages(soft._replace(G=sp.csc_matrix(G)))
    monkeypatch.setenv(peers_hpipm.HPIPM_ENV, str(tmp_path))
    monkeypatch.setattr(peers_hpipm, "_candidates", lambda: [tmp_path])
    peers_hpipm._load.cache_clear()
    try:
        assert peers_hpipm.hpipm_library() is None
        assert "no libhpipm.so found" in peers_hpipm.hpipm_unavailable()
        assert "hpipm" not in peers.available_peers()
        with pytest.raises(RuntimeError, match="HPIPM is not available"):
            peers.solve_hpipm(qp)
    finally:
        monkeypatch.undo()
        peers_hpipm._load.cache_clear()


def test_hpipm_starts(problems, reference):
    """HPIPM from its own cold start and from the drift of x0 (the default) lands on
    Clarabel's optimum; a bad start or mode is refused."""
    _skip_unless_usable("hpipm")
    for name in ("hard", "soft_violated"):
        for start in ("cold", "drift"):
            res = peers.solve_hpipm(problems[name], start=start)
            assert res.status == "SUCCESS" and res.iterations > 0
            assert res.objective == pytest.approx(reference[name].objective, rel=1e-7)
    with pytest.raises(ValueError, match="start"):
        peers.solve_hpipm(problems["hard"], start="warm")
    with pytest.raises(ValueError, match="mode"):
        peers.solve_hpipm(problems["hard"], mode="fast")
    # mu0 "auto" (the default): the largest of 1e5 and the soft rows' penalty (rho = 1e6 here)
    auto, at_rho = (peers.solve_hpipm(problems["soft"], mu0=m) for m in ("auto", 1e6))
    np.testing.assert_array_equal(auto.z, at_rho.z)
    assert auto.iterations == at_rho.iterations
    low = peers.solve_hpipm(problems["soft"], mu0=1e5)
    assert low.iterations != auto.iterations or not np.array_equal(low.z, auto.z)
    with pytest.raises(ValueError, match="mu0"):
        peers.solve_hpipm(problems["hard"], mu0="large")


def test_hpipm_needs_what_its_blasfeo_was_built_for(tmp_path):
    """The instruction sets BLASFEO's build asks for (its target header) are checked against
    the CPU's flags before any of its code runs."""
    from rvdjax.peers_hpipm import _missing_cpu_flags

    lib = tmp_path / "install" / "lib"
    header = tmp_path / "install" / "include" / "blasfeo" / "include" / "blasfeo_target.h"
    header.parent.mkdir(parents=True)
    lib.mkdir(parents=True)
    header.write_text(
        "#define TARGET_X64_INTEL_HASWELL\n#define TARGET_NEED_FEATURE_AVX2 1\n"
        "#define TARGET_NEED_FEATURE_FMA 1\n/* #undef TARGET_NEED_FEATURE_AVX */\n"
    )
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text("processor : 0\nflags : fpu sse2 avx fma\n")
    assert _missing_cpu_flags(lib, cpuinfo) == ["AVX2"]
    cpuinfo.write_text("processor : 0\nflags : fpu sse2 avx avx2 fma\n")
    assert _missing_cpu_flags(lib, cpuinfo) == []
    assert _missing_cpu_flags(tmp_path / "elsewhere", cpuinfo) == []  # no header: BLASFEO's test
