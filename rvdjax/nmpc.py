"""Nonlinear MPC reference (CasADi + IPOPT) for the rendezvous closed loop (paper 000 Sec. IV).

The OCP of the rendezvous family (:mod:`rvdjax.families.rendezvous`) with the ellipsoidal
keep-out constraints kept nonlinear,
1 <= (r - o)^T S (r - o) (paper 000 Eq. 6), instead of linearised: the "IPOPT NMPC" of paper
000's comparison. Same CW model, weights, thrust box, horizon and truth as the LQ-MPC loop;
each step is warm-started from the previous solution shifted by one stage. Optional:
``pip install 'rvdjax[nmpc]'`` (CasADi).
"""

from __future__ import annotations

import numpy as np

from rvdjax.families.rendezvous import Params
from rvdjax.loop.kernel import Loop
from rvdjax.loop.metrics import HIST_BINS, Metrics, RunStatus

__all__ = ["run_nmpc_loop"]


def run_nmpc_loop(p: Params, x0, loop: Loop, ipopt_tol=1e-8):
    """Fly the rendezvous loop (``loop``: its horizon and step count) with nonlinear MPC solved
    by IPOPT.

    Returns:
        (dict of per-step NumPy arrays x, u, status, iterations, active, keepout_margin;
        :class:`~rvdjax.loop.Metrics` of NumPy values; seconds spent in IPOPT).
    """
    import time

    import casadi as ca

    if loop.config.truth != "linear":
        raise ValueError("run_nmpc_loop supports the linear truth only")
    N, n_steps = loop.N, loop.config.n_steps
    A, B = np.asarray(p.A), np.asarray(p.B)
    nx, nu = B.shape
    Q, R, Q_f = np.asarray(p.Q), np.asarray(p.R), np.asarray(p.Q_f)
    x_ref = np.asarray(p.x_ref)
    obstacles, radii = np.asarray(p.obstacles), np.asarray(p.radii)
    active_obs = np.flatnonzero(np.asarray(p.obstacle_mask) > 0)
    d = obstacles.shape[1] // 2
    ts, u_max = float(p.ts), np.asarray(p.u_max)

    opti = ca.Opti()
    X = opti.variable(nx, N)
    U = opti.variable(nu, N)
    X0 = opti.parameter(nx)
    C = {j: opti.parameter(d, N) for j in active_obs}  # obstacle centres per stage
    cost = 0
    for t in range(N):
        prev = X0 if t == 0 else X[:, t - 1]
        opti.subject_to(X[:, t] == ca.DM(A) @ prev + ca.DM(B) @ U[:, t])
        opti.subject_to(opti.bounded(-ca.DM(u_max), U[:, t], ca.DM(u_max)))
        e = X[:, t] - ca.DM(x_ref)
        W = Q_f if t == N - 1 else Q
        cost += ca.mtimes([e.T, ca.DM(W), e]) + ca.mtimes([U[:, t].T, ca.DM(R), U[:, t]])
        for j in active_obs:
            dr = X[:d, t] - C[j][:, t]
            opti.subject_to(ca.dot(dr, dr) / radii[j] ** 2 >= 1.0)  # paper 000 Eq. 6
    opti.minimize(cost)
    opti.solver("ipopt", {"print_time": False}, {"print_level": 0, "sb": "yes", "tol": ipopt_tol})

    x = np.asarray(x0, dtype=float)
    guess_x = np.zeros((nx, N))
    xd = x.copy()
    for t in range(N):
        xd = A @ xd
        guess_x[:, t] = xd
    guess_u = np.zeros((nu, N))
    t_now, active, solve_s = 0.0, np.linalg.norm(x[:d]) > float(p.stop_radius), 0.0
    fields = ("x", "u", "status", "iterations", "objective", "active", "keepout_margin")
    rec = {k: [] for k in fields}
    for _ in range(n_steps):
        centres_now = obstacles[:, :d] + t_now * obstacles[:, d:]
        margin = np.linalg.norm(x[:d][None] - centres_now, axis=-1) - radii
        margin = np.where(np.asarray(p.obstacle_mask) > 0, margin, np.inf)
        status, its, obj, u = -1, 0, np.nan, np.zeros(nu)
        if active:
            opti.set_value(X0, x)
            times = t_now + ts * np.arange(1, N + 1)
            for j in active_obs:
                opti.set_value(
                    C[j], (obstacles[j, :d][None] + times[:, None] * obstacles[j, d:][None]).T
                )
            opti.set_initial(X, guess_x)
            opti.set_initial(U, guess_u)
            t0 = time.perf_counter()
            try:
                sol = opti.solve()
                status = 0
                get = sol.value
            except RuntimeError:  # IPOPT failed: use its last iterate, report the status
                status = 1
                get = opti.debug.value
            solve_s += time.perf_counter() - t0
            Xs, Us = np.asarray(get(X)).reshape(nx, N), np.asarray(get(U)).reshape(nu, N)
            its = int(opti.stats().get("iter_count", 0))
            obj = float(get(cost))
            u = Us[:, 0]
            guess_x = np.concatenate([Xs[:, 1:], Xs[:, -1:]], axis=1)
            guess_u = np.concatenate([Us[:, 1:], Us[:, -1:]], axis=1)
        for k, v in zip(fields, (x, u, status, its, obj, active, margin), strict=True):
            rec[k].append(np.asarray(v))
        if active:
            x = A @ x + B @ u
            t_now += ts
            active = np.linalg.norm(x[:d]) > float(p.stop_radius)
    infos = {k: np.stack(rec[k]) for k in fields}
    act = infos["active"].astype(bool)
    n = int(act.sum())
    docked = not active
    u_all = infos["u"][act]
    impulse = float(np.sum(np.linalg.norm(u_all, axis=1))) * ts
    margins = np.where(act[:, None], infos["keepout_margin"], np.inf)
    counts = np.bincount(np.asarray(infos["status"])[act].astype(int), minlength=4)[:4]
    hist = np.zeros(HIST_BINS, int)
    metrics = Metrics(
        status=np.int32(RunStatus.DOCKED if docked else RunStatus.TIMEOUT),
        docked=np.bool_(docked),
        steps=np.int32(n),
        time_to_dock_s=np.float64(n * ts if docked else np.inf),
        total_impulse_N_s=np.float64(impulse),
        effort_l1_N_s=np.float64(np.sum(np.abs(u_all)) * ts),
        delta_v_m_s=np.float64(impulse / float(p.plant.mass)),
        delta_v_l1_m_s=np.float64(np.sum(np.abs(u_all)) * ts / float(p.plant.mass)),
        torque_l1_N_m_s=np.float64(0.0),
        phase_delta_v_m_s=np.array([impulse / float(p.plant.mass)]),
        phase_time_s=np.array([n * ts]),
        phase_effort_l1_N_s=np.array([np.sum(np.abs(u_all)) * ts]),
        phase_thruster_impulse_N_s=np.array([0.0]),
        max_violation_m=np.float64(max(0.0, -float(np.min(margins, initial=np.inf)))),
        margins_m={"keep_out": np.float64(np.min(margins, initial=np.inf))},
        status_counts=counts,
        mean_iterations=np.float64(np.asarray(infos["iterations"])[act].mean() if n else 0.0),
        iteration_histogram=hist,
        thruster_impulse_N_s=np.float64(0.0),  # ideal forces: no thrusters flown
        propellant_kg=np.float64(0.0),
        valve_openings=np.int32(0),
        pulses_dropped=np.int32(0),
        contact_speed_m_s=np.float64(np.linalg.norm(x[nx // 2 :]) if docked else np.inf),
    )
    return infos, metrics, solve_s
