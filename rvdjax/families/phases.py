"""Three-phase rendezvous and docking of a small satellite (paper 003 Ch. 3, Algorithm 1).

The guidance uses the Clohessy-Wiltshire model with impulsive inputs (u_k = delta-v, paper 003
Eq. 3.1: B = A [0; I]). Every MPC step solves the QP of the current phase (paper 003):

0. rendezvous (Eq. 3.7): quadratic cost to a set point on the approach-cone axis at the
   keep-out radius r1, rotating-plane keep-out rows n_i^T r_i >= r1 (Eqs. 3.5-3.6, normal
   rotating from the chaser's bearing towards the cone axis at most the orbit rate), terminal
   approach-cone penalty lambda 1^T (H r_N)_+ (Eq. 3.3, apex at the target's centre of mass);
1. approach (Eq. 3.10): set point on the axis at r2, cone penalty on every stage (Eq. 3.8),
   overshoot row a_i^T r_i >= r2 (Eq. 3.9);
2. docking (Eq. 3.14): quadratic cost to the docking-port state, docking cone with its apex at
   the port (Eq. 3.12) and the soft-docking velocity bound |v|_inf <= v_max (Eq. 3.13).

Phase switches (Algorithm 1): 0 -> 1 when the chaser is inside the approach cone and within
r1 (1 + switch_tol) of the target; 1 -> 2 when within r2 (1 + switch_tol); docked when within
r3 of the docking port. A rotating target (Sec. 3.4, Eq. 3.15) turns the port, the cone axes
and the set points about the LVLH z-axis at ``target_rate``.

Rendezvous cost variants of Sec. 3.6.4 (Table 3.6): ``setpoint = 0`` makes the rendezvous
reference the target's centre of mass ("QP without set point"); ``Config(rendezvous_cost=
"lp")`` replaces the rendezvous QP by the 1-norm cost of Eq. 2.10 (an LP), modelled exactly
with cost rows (state terms) and a split input (delta-v term), see :func:`ocp`.

One array shape for all phases (DESIGN §4 "Phases"): every phase is padded to the largest
horizon with identity dynamics (A = I, B = 0) and zero state cost; the phase's terminal weight
sits on the last padded stage (the padded stages hold x_N, so this equals the cost on the
phase's own terminal stage), and the state rows of the padded stages are masked off. "Hard"
constraints of the thesis (keep-out planes, overshoot, docking cone, velocity bound) are soft
rows with a large exact penalty ``rho``; the thesis' external penalties are "penalty" blocks
with rho = lambda.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from rvdjax.constraints import (
    approach_cone,
    approach_cone_penalty,
    between_samples,
    block_margin,
    cost_rows,
    exclusive,
    keep_out_plane,
    overshoot,
    sphere_keep_out,
    stack,
    thrust_box,
    velocity_bound,
)
from rvdjax.families.common import (
    field_tunable,
    smooth_excess,
    smooth_norm,
    weight_tunables,
)
from rvdjax.families.phases_burns import (  # noqa: F401  (tests read them here)
    SUBSAMPLES,
    _coast_back,
    axis_thrust,
    finite_burn,
)
from rvdjax.families.phases_geometry import (  # noqa: F401  (tests read them here)
    _in_cone,
    _plane_normals,
    _turn,
    target_state,
)
from rvdjax.families.phases_inputs import (  # noqa: F401  (the family's inputs, re-exported)
    LAYOUT,
    LP_EPS,
    LP_REG,
    N_PHASES,
    POS,
    SCHEMA,
    VEL,
    Config,
    Guidance,
    Params,
    check,
    make_params,
)
from rvdjax.loop.family import Family, Hooks, Tuning, lazy
from rvdjax.ocp import OCP
from rvdjax.solver import drift_plan
from rvdjax.solver import stagewise as sw
from rvdjax.solver.platform import cuda_or_default
from rvdjax.solver.riccati import ModelTable

__all__ = [
    "Params",
    "Config",
    "SCHEMA",
    "make_params",
    "FAMILY",
    "target_state",
    "LP_EPS",
    "LP_REG",
]


# --------------------------------------------------------------------------- the family


def init(p: Params, fc: Config, x0):
    turn = jnp.zeros(3, jnp.asarray(x0).dtype) if fc.latch_turn else None
    return Guidance(phase=jnp.asarray(0, jnp.int32), entered=jnp.asarray(False), turn=turn)


def _N(fc: Config) -> int:
    return max(fc.N)


def initial_plan(p: Params, fc: Config, g, x0):
    """The drift of the rendezvous phase's (padded) model from x0."""
    N = _N(fc)
    stage = jnp.arange(N)
    A = jnp.where((stage < fc.N[0])[:, None, None], p.A[0], jnp.eye(6, dtype=p.A.dtype))
    return drift_plan(A, x0, N, 6 if fc.rendezvous_cost == "lp" else 3)


def observe(p, fc, g, x, t, plan):
    return g


def ocp(p: Params, fc: Config, g: Guidance, x, t, plan):
    """The phase's QP, padded to the largest horizon (module docstring)."""
    phase = g.phase
    Ns = jnp.asarray(fc.N)
    N = _N(fc)
    nf = fc.n_faces
    dtype = x.dtype
    n_real = Ns[phase]
    ts = p.ts[phase]
    stage = jnp.arange(N)
    real = stage < n_real
    i_eff = jnp.minimum(stage, n_real - 1)
    times = t + (i_eff + 1) * ts  # padded stages repeat the last real stage
    port, port_vel, axis = target_state(p, times)
    _, _, axis_end = target_state(p, t + n_real * ts)
    p0, p1, p2 = (phase == 0), (phase == 1), (phase == 2)
    on = real.astype(dtype)
    last = (stage == n_real - 1).astype(dtype)

    # references (per stage, turning with the target): phase 0 set point at r1 on the cone
    # axis (or the origin when p.setpoint = 0), phase 1 at r2, phase 2 the port state;
    # velocities those of the turning points
    omega = jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0], dtype) * p.target_rate, (N, 3))
    ref0 = p.setpoint * jnp.concatenate([p.r1 * axis, jnp.cross(omega, p.r1 * axis)], -1)
    ref1 = jnp.concatenate([p.r2 * axis, jnp.cross(omega, p.r2 * axis)], -1)
    ref2 = jnp.concatenate([port, port_vel], -1)
    x_ref = jnp.stack([ref0, ref1, ref2])[phase]

    normals = _plane_normals(x[:3], axis_end, N, n_real, ts, p.n, x[3:], g.turn)
    # The phases' rows are never active together, so they share rows (constraints.exclusive):
    # 10 state rows per stage instead of 16 (the solver's row work scales with the count).
    keep_out = keep_out_plane(normals, p.r1, 6, POS, rho=p.rho, name="keep_out").masked(on * p0)
    cone_penalty = approach_cone_penalty(
        jnp.zeros((N, 3), dtype), axis, p.half_angle[phase], p.lam[phase], 6, POS, nf
    ).masked(jnp.where(p0, last, on * p1))
    per_phase = [
        [keep_out, cone_penalty]
        + (
            [between_samples(keep_out, _coast_back(p.plant.Ac, p.ts)[phase], "keep_out_between")]
            if fc.between_samples
            else []
        ),
        [cone_penalty, overshoot(axis, p.r2, 6, POS, rho=p.rho).masked(on * p1)],
        [
            approach_cone(
                port, axis, p.half_angle[2], nf, 6, POS, rho=p.rho, name="docking_cone"
            ).masked(on * p2),
            velocity_bound(p.v_max, N, 6, VEL, rho=p.rho).masked(on * p2),
        ],
    ]

    B_phase, c = p.B[phase], jnp.zeros((N, 6), dtype)
    if _finite_burns(p, fc):  # the vehicle's burns, not impulses
        B_phase, c = finite_burn(p, p.A[phase], ts, _plan_dv(fc, g, plan))
        c = jnp.where(real[:, None], c, 0.0)
    if fc.rendezvous_cost == "lp":
        # 1-norm rendezvous cost (paper 003 Eq. 2.10 about the set point, Sec. 3.6.4):
        #   sum_{i<N} ||Q (x_i - x_s)||_1 + ||R u_i||_1 + ||Q_f (x_N - x_s)||_1
        # state terms: each row of W (Q, Q_f on the terminal stage) gives a cost-row pair
        # (the inputs' split: _phase_fields)
        W = jnp.where((stage < n_real - 1)[:, None, None], p.Q[0], p.Q_f[0])
        Wr = jnp.einsum("tij,tj->ti", W, x_ref)
        per_phase[0].append(cost_rows(W, Wr, name="lp_state_cost").masked(on * p0))

    blocks = [exclusive(per_phase, phase, name="phase_rows")]
    Fx, fx, rho, x_mask = stack(blocks)
    problem = OCP(
        c=c,
        x0=x,
        x_ref=x_ref,
        Fx=Fx,
        fx=fx,
        rho=rho,
        x_mask=x_mask,
        **_phase_fields(p, fc, phase, B_phase),
    )
    return problem, blocks


def _finite_burns(p: Params, fc: Config) -> bool:
    """Whether the model has the thrusters' finite burns (static: the parameters' structure
    and the configuration), whose B and c follow each step's plan."""
    return p.plant.thrusters is not None and fc.finite_burn


def _phase_fields(p: Params, fc: Config, phase, B_phase) -> dict:
    """The OCP's fields that follow from the phase alone, padded to the largest horizon, with
    the input matrix ``B_phase`` of its real stages: A, B, Q, R (identity dynamics, no input
    and no weight on the padded stages, Q_f on the last real one), the linear costs q, r and
    the hard input rows Fu, fu, u_mask (the thrust box)."""
    N = _N(fc)
    n_real = jnp.asarray(fc.N)[phase]
    stage = jnp.arange(N)
    real = stage < n_real
    dtype = p.A.dtype
    A = jnp.where(real[:, None, None], p.A[phase], jnp.eye(6, dtype=dtype))
    B = jnp.where(real[:, None, None], B_phase, 0.0)
    Q = jnp.where((stage < n_real - 1)[:, None, None], p.Q[phase], 0.0)
    Q = Q.at[-1].set(p.Q_f[phase])
    R = jnp.broadcast_to(p.R[phase], (N, 3, 3))
    r = jnp.zeros((N, 3), dtype)
    box = thrust_box(p.u_max[phase], N, nu=3)
    Fu, fu = box.F, box.f
    if fc.rendezvous_cost == "lp":
        # input: six variables v = [v1; v2] in every phase (one shape). Rendezvous: the split
        # u = v1 - v2 with 0 <= v1, v2 <= u_max, so sum_i R_ii |u_i| = w^T (v1 + v2) at the
        # optimum (R diagonal, checked by :func:`check`): B' = [B, -B], linear cost r = w,
        # R' = LP_REG max(w) I. Approach and docking keep the QP of the thesis exactly: u = v1
        # with its box, B' = [B, 0], and v2 a dummy input with no effect and weight R (its
        # optimum is v2 = 0): R' = diag(R, R). The state's cost rows: :func:`ocp`.
        p0 = phase == 0
        B = jnp.concatenate([B, jnp.where(p0, -B, 0.0)], axis=-1)
        Q = jnp.where(p0, 0.0, Q)
        w = jnp.diagonal(p.R[0])
        R_lp = jnp.where(
            p0,
            LP_REG * jnp.max(w) * jnp.eye(6, dtype=dtype),
            jnp.kron(jnp.eye(2, dtype=dtype), p.R[phase]),
        )
        R = jnp.broadcast_to(R_lp, (N, 6, 6))
        r = jnp.where(p0, jnp.broadcast_to(jnp.concatenate([w, w]), (N, 6)), 0.0)
        # hard rows v <= hi, -v <= lo: hi = lo = u_max in approach and docking; in rendezvous
        # the bound v >= 0 is relaxed to v >= -LP_EPS u_max so that v = 0 is strictly
        # feasible (the solver's cold start needs fu > 0), and v <= (1 - LP_EPS) u_max keeps
        # the applied |v1 - v2| <= u_max exactly
        u_max = jnp.broadcast_to(p.u_max[phase], (3,))
        e6 = jnp.eye(6, dtype=dtype)
        Fu = jnp.broadcast_to(jnp.concatenate([e6, -e6]), (N, 12, 6))
        um = jnp.concatenate([u_max, u_max])
        hi = jnp.where(p0, 1.0 - LP_EPS, 1.0) * um
        lo = jnp.where(p0, LP_EPS, 1.0) * um
        fu = jnp.broadcast_to(jnp.concatenate([hi, lo]), (N, 12))
    return dict(
        A=A,
        B=B,
        Q=Q,
        R=R,
        q=jnp.zeros((N, 6), dtype),
        r=r,
        Fu=Fu,
        fu=fu,
        u_mask=jnp.ones(Fu.shape[:2], dtype),
    )


def model(p: Params, fc: Config, g: Guidance):
    """The OCP's fields that follow from ``g``'s phase (:func:`_phase_fields`, and c = 0),
    which the batch engine rebuilds instead of storing in every slot; None with finite burns
    (their B and c follow each step's plan)."""
    if _finite_burns(p, fc):
        return None
    fields = _phase_fields(p, fc, g.phase, p.B[g.phase])
    del fields["u_mask"]  # stays in the slot (rvdjax.loop.engine.slots.ROWS_REBUILT)
    x_mask, rho = row_weights(p, fc)

    def table():
        # built only where the GPU kernels read it: unused, its operations still changed
        # XLA's program for the CPU (the same results, other fusions)
        BA, Fu, Q, R = model_table(p, fc)
        return ModelTable(BA, g.phase, Fu, x_mask, rho, Q, R)

    return dict(
        fields,
        c=jnp.zeros((_N(fc), 6), p.A.dtype),
        x_mask=x_mask[g.phase],
        rho=rho[g.phase],
        table=table,
    )


def model_table(p: Params, fc: Config):
    """Each phase's stages [B, A] (3, N, 6, nu + 6), input rows Fu (3, N, mu, nu) and cost
    blocks Q (3, N, 6, 6), R (3, N, nu, nu) as :func:`model` builds them (the same operations
    with the phase a constant, so entry ``phase`` of each is :func:`model`'s, bit for bit). On
    a GPU the solver's kernels read a slot's from these tables instead of from a copy of every
    slot's (:class:`rvdjax.solver.riccati.ModelTable`; the state rows' mask and penalty come
    from :func:`row_weights`)."""
    tables = [], [], [], []
    for phase in range(3):
        f = _phase_fields(p, fc, phase, p.B[phase])
        BA = jnp.concatenate([f["B"], f["A"]], axis=-1)
        for table, a in zip(tables, (BA, f["Fu"], f["Q"], f["R"]), strict=True):
            table.append(a)
    return tuple(jnp.stack(t) for t in tables)


def row_weights(p: Params, fc: Config):
    """(3, N, m) the state rows' mask and penalty in each phase, the penalty neutralised (1)
    on masked rows as the solver's start does (``barrier.rows_of``). The rows' normals and
    offsets follow the state and the time; which rows are on, and their penalties, follow the
    phase alone, so :func:`ocp` of any state gives them. The batch engine gathers them by the
    phase instead of reading two (N, m) arrays of every slot in each pass over the rows (on a
    GPU, 6 % of a thesis-vbar tick's bytes, docs/benchmark.md)."""
    x = jnp.ones(6, p.A.dtype)  # any state
    g0 = init(p, fc, x)

    def weights(phase):
        rows, _ = ocp(p, fc, g0._replace(phase=phase), x, 0.0, None)
        return rows.x_mask, jnp.where(rows.x_mask > 0, rows.rho, 1.0)

    # the three phases' QPs traced once, as a batch over the phase (the batch engine's
    # segment calls this five times: 15 traces of the whole QP became 5)
    return jax.vmap(weights)(jnp.arange(3, dtype=jnp.int32))


def _plan_dv(fc: Config, g: Guidance, plan):
    """(N, 3) the delta-v of each stage of a plan (the LP's split inputs recombined)."""
    u = plan.u
    if fc.rendezvous_cost == "lp":
        return u[:, :3] - jnp.where(g.phase == 0, u[:, 3:], 0.0)
    return u


def control(p, fc: Config, g: Guidance, sol):
    u0 = sol.u[0]
    if fc.rendezvous_cost == "lp":  # split (rendezvous) or [u; dummy]
        u0 = u0[:3] - jnp.where(g.phase == 0, u0[3:], 0.0)
    return u0


def sample_time(p: Params, g: Guidance):
    return p.ts[g.phase]


def truth_model(p: Params, g: Guidance):
    return p.A[g.phase], p.B[g.phase]


def update(p: Params, fc: Config, g: Guidance, x, u, x_next, t, ts, samples):
    """Phase switches and docking on the state reached (Algorithm 1)."""
    t_next = t + ts
    r = x_next[:3]
    dist = jnp.linalg.norm(r)
    port_n, _, axis_next = target_state(p, t_next)
    in_cone = _in_cone(p, r, t_next, fc.n_faces) >= 0
    to1 = (g.phase == 0) & in_cone & (dist <= p.r1 * (1 + p.switch_tol))
    to2 = (g.phase == 1) & (dist <= p.r2 * (1 + p.switch_tol))
    docked = (g.phase == 2) & (jnp.linalg.norm(r - port_n) <= p.r3)
    phase = g.phase + to1.astype(g.phase.dtype) + to2.astype(g.phase.dtype)
    # the sub-samples are judged, except on a step that changes phase: its end lies inside
    # the keep-out sphere (through the cone) or past r2 by design
    judged = jnp.broadcast_to(phase == g.phase, samples[0].shape)
    cone = approach_cone(port_n[None], axis_next[None], p.half_angle[2], fc.n_faces, 6, POS)
    inside = jnp.min(block_margin(cone, x_next)) >= 0.0
    entered = jnp.asarray(g.entered) | ((phase == 2) & inside)
    turn = g.turn
    if fc.latch_turn:
        # the sense this step's planes turned in (ocp's decision, from the step's start),
        # kept while the rotation does not fit; reset once it fits or the phase ends
        n_real = jnp.asarray(fc.N)[g.phase]
        _, _, axis_end = target_state(p, t + n_real * ts)
        u0, w, _, fits = _turn(x[:3], axis_end, n_real, ts, p.n, x[3:], g.turn)
        k = jnp.cross(u0, w)
        k = k / jnp.maximum(jnp.linalg.norm(k), 1e-12)
        turn = jnp.where(fits | (phase != 0), 0.0, k)
    return Guidance(phase=phase, entered=entered, turn=turn), docked, ts, judged


def subsamples(p: Params, fc: Config, x, u, dt):
    """The truth between samples: the states at dt j / SUBSAMPLES, j = 1 .. SUBSAMPLES - 1,
    coasting on the CW model after the step's impulsive delta-v ``u`` [m/s]
    (:func:`rvdjax.dynamics.zoh_states`; exact for the linear truth; with thrusters or a
    nonlinear truth an approximation of the path between samples). taus (M,) [s], states
    (M, 6)."""
    from rvdjax.dynamics import zoh_states

    taus = dt * jnp.arange(1, SUBSAMPLES, dtype=x.dtype) / SUBSAMPLES
    x = jnp.asarray(x)
    x_plus = x.at[3:].add(u[:3])
    args = (p.plant.Ac, p.plant.Bc, x_plus, jnp.zeros(p.plant.Bc.shape[1], x.dtype), taus)
    # on a GPU the products as multiplies and sums, which XLA fuses (12 launches fewer a tick)
    gpu = functools.partial(zoh_states, mv=sw.mv)
    return taus, cuda_or_default(*args, cuda=gpu, default=zoh_states)


def truth_blocks(p: Params, fc: Config, g: Guidance, x, t):
    """Keep-out sphere (phase 0), overshoot plane (phase 1) and docking cone (phase 2, once the
    chaser has been inside it: before, it is still entering) are judged; the speed bound
    (phase 2) is reported."""
    t = jnp.asarray(t)
    port, _, axis = target_state(p, t)
    r = x[None, :3]
    return [
        sphere_keep_out(r, jnp.zeros((1, 3)), p.r1, 6, POS, name="keep_out").masked(g.phase == 0),
        overshoot(axis[None], p.r2, 6, POS).masked(g.phase == 1),
        approach_cone(
            port[None], axis[None], p.half_angle[2], fc.n_faces, 6, POS, name="docking_cone"
        ).masked((g.phase == 2) & jnp.asarray(g.entered)),
        velocity_bound(p.v_max, 1, 6, VEL).with_(kind="monitor").masked(g.phase == 2),
    ]


def dock_error(p: Params, fc: Config, g: Guidance, x, t):
    """Distance beyond r3 of the docking port [m] (docked within r3)."""
    port, _, _ = target_state(p, t)
    return smooth_excess(smooth_norm(x[:3] - port), p.r3)


def _derive(p: Params, names) -> Params:
    """The impulsive CW model per phase from the sample times, then Q_f = P_bar per phase."""
    import jax

    from rvdjax.dynamics import cw_continuous, dare, discretize_impulsive

    if "ts" in names:
        Ac, _ = cw_continuous(p.n, p.plant.mass)
        A, B = jax.vmap(lambda ts: discretize_impulsive(Ac, ts))(p.ts)
        p = p._replace(A=A, B=B)
    if not names:
        return p
    return p._replace(Q_f=jax.vmap(dare)(p.A, p.B, p.Q, p.R))


TUNING = Tuning(
    tunables={
        **weight_tunables("per phase (3 rows: rendezvous, approach, docking)"),
        "lam": field_tunable(
            "lam",
            "cone-penalty weight lambda per phase (paper 003 Eqs. 3.3, 3.8; phase 2 unused)",
        ),
        "ts": field_tunable(
            "ts",
            "sample time per phase [s] (the discrete models follow; the step budget does not)",
            derived=True,
        ),
    },
    derive=_derive,
)


FAMILY = Family(
    name="three-phase",
    description="three-phase CW rendezvous, approach and docking with impulsive delta-v "
    "(paper 003)",
    law=Hooks.of(
        globals(),
        layout=LAYOUT,
        n_phases=N_PHASES,
        config_type=Config,
        horizon=_N,
    ),
    make_params=make_params,
    truths=("linear", "two-body", "two-body-j2", "two-body-j2-drag"),
    check=check,
    plot=lazy("rvdjax.families.plots.phases:plot"),
    tuning=TUNING,
)
