"""The three-phase family's layout, traced parameters, static configuration, guidance state
and physical inputs (:data:`SCHEMA`, :func:`make_params`): the inputs side of
:mod:`rvdjax.families.phases`."""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from rvdjax import checks
from rvdjax.disturbances import THESIS_DISTURBANCES
from rvdjax.disturbances import disturbances as make_disturbances
from rvdjax.families.common import (
    make_plant,
)
from rvdjax.loop.family import Layout
from rvdjax.loop.plant import Plant
from rvdjax.propagate import Drag, circular_orbit
from rvdjax.schema import (
    Input,
    Schema,
    disturbance_table,
    finite,
    make_params_of,
    positive,
    value,
    within,
)

__all__ = [
    "LAYOUT",
    "Params",
    "Config",
    "Guidance",
    "SCHEMA",
    "make_params",
    "check",
    "LP_EPS",
    "LP_REG",
]

POS = (0, 1, 2)
VEL = (3, 4, 5)
N_PHASES = 3
LAYOUT = Layout(
    nx=6,
    nu=3,
    pos=POS,
    vel=VEL,
    force=POS,
    input="delta-v",
    names=("x", "y", "z", "vx", "vy", "vz"),
)

# LP rendezvous (Config.rendezvous_cost = "lp"): the solver needs u = 0 strictly feasible and R
# positive definite. The split's lower bounds v >= 0 are written -v <= LP_EPS u_max (a slack of
# 1.8e-8 m/s per axis and step, taken off the upper bounds; with 1e-9 four of the 81
# warm-started rendezvous solves of the V-bar case ended NONFINITE), and the rendezvous weight
# is R' = LP_REG max(w) I: the LP becomes a QP whose quadratic term is below LP_REG of the L1
# term for |v| <= u_max (LP_REG max(w) v^2 <= LP_REG w_max u_max v). Neither moves the delta-v
# by more than 1e-5 m/s (V-bar: eps 1e-9 .. 1e-6, reg 1e-9 .. 1e-4 checked); the plans match
# Clarabel's LP optimum.
LP_EPS = 1e-7
LP_REG = 1e-9


class Params(NamedTuple):
    """Traced parameters (SI units, angles in rad). Leading axis 3 = phase (0 rendezvous,
    1 approach, 2 docking).

    Attributes:
        A, B: (3, 6, 6), (3, 6, 3) impulsive CW model per phase (input: delta-v [m/s]).
        Q, R, Q_f: (3, 6, 6), (3, 3, 3), (3, 6, 6) weights (Q_f: DARE solution per phase).
        ts: (3,) sample time per phase [s].
        u_max: (3,) per-axis delta-v bound per step [m/s].
        lam: (3,) cone-penalty weight lambda (phases 0 and 1).
        half_angle: (3,) LoS cone half angle [rad] (phases 0, 1: approach cone at the centre
            of mass; phase 2: docking cone at the port).
        n: () mean motion [rad/s] (cap on the keep-out plane rotation rate).
        r1, r2, r3: () keep-out radius / approach-to-docking switch / docked distance [m].
        v_max: () soft-docking velocity bound [m/s].
        port_body: (3,) docking port in the target body frame [m].
        axis_body: (3,) unit approach axis in the body frame (the port's outward direction).
        target_angle0: () body angle about the LVLH z-axis at t = 0 [rad].
        target_rate: () body rate about z [rad/s].
        rho: () exact penalty of the thesis' hard constraints [per metre or per m/s].
        switch_tol: () relative tolerance on r1 and r2 for the phase switches.
        setpoint: () rendezvous reference: 1.0 the set point at r1 on the approach-cone axis
            (Eq. 3.2), 0.0 the target's centre of mass (Table 3.6 "QP without set point").
        plant: the vehicle and its surroundings (:class:`~rvdjax.loop.plant.Plant`: mass [kg],
            orbit, drag, disturbances, continuous model, thrusters).
    """

    A: jnp.ndarray
    B: jnp.ndarray
    Q: jnp.ndarray
    R: jnp.ndarray
    Q_f: jnp.ndarray
    ts: jnp.ndarray
    u_max: jnp.ndarray
    lam: jnp.ndarray
    half_angle: jnp.ndarray
    n: jnp.ndarray
    r1: jnp.ndarray
    r2: jnp.ndarray
    r3: jnp.ndarray
    v_max: jnp.ndarray
    port_body: jnp.ndarray
    axis_body: jnp.ndarray
    target_angle0: jnp.ndarray
    target_rate: jnp.ndarray
    rho: jnp.ndarray
    switch_tol: jnp.ndarray
    setpoint: jnp.ndarray
    plant: Plant  # the vehicle and its surroundings (rvdjax.loop.plant)


@dataclasses.dataclass(frozen=True)
class Config:
    """Static configuration.

    Attributes:
        N: horizon per phase (paper 003 Table 3.1: 30 / 15 / 12).
        n_faces: faces of the polyhedral cones (paper 003: 4).
        rendezvous_cost: "qp" (Eq. 3.2, the thesis' default) or "lp": the rendezvous phase
            minimises the 1-norm cost of Eq. 2.10 (Sec. 3.6.4, Table 3.6), see :func:`ocp`.
            "lp" splits the input of every phase (one shape for all).
        between_samples: the rendezvous keep-out planes also hold at the instants the truth
            is judged between samples (j Ts / 8, the state there a coast back from x_{t+1}:
            :func:`rvdjax.constraints.between_samples`). The thesis constrains the samples
            only; a chord between two samples outside the 100 m sphere can cut into it
            (by centimetres where the plan rides the sphere). rvdjax's choice, on by
            default: the keep-out sphere is judged between samples.
        finite_burn: with the thrusters flying (``params.plant.thrusters``), the model has their
            finite burns (:func:`finite_burn`); False keeps the thesis' impulsive model
            (Eq. 3.1) while the thrusters burn for up to 5 s from each period's start, as the
            thesis' own formulation does: its truth then lags the plans by up to
            m u_max^2 / (2 F) = 0.45 m per step and crosses the overshoot plane.
        latch_turn: once the keep-out planes must turn the way the chaser's bearing turns
            (the rotation does not fit in the horizon, Sec. 3.1.3), keep that sense of
            rotation until it fits. Off (the default, today's published figures): the sense is
            read afresh each step from the tangential velocity, which near the bearing
            opposite the approach axis can flip from one step to the next; the planes swing
            from one side to the other and the chaser comes straight in: thesis-vbar's
            keep-out breaches deeper than 10 m under paper 003's initial states are such runs
            (docs/verification.md, "Where the deep breaches come from").
    """

    N: tuple[int, int, int] = (30, 15, 12)
    n_faces: int = 4
    rendezvous_cost: str = "qp"
    between_samples: bool = True
    finite_burn: bool = True
    # added 2026-11-27: left out of stored definitions while off (runs as before it existed)
    latch_turn: bool = dataclasses.field(default=False, metadata={"stored_unless": False})

    def __post_init__(self):
        if len(self.N) != N_PHASES or any(not isinstance(k, int) or k < 1 for k in self.N):
            raise ValueError(f"N must be three ints >= 1 (one per phase), got {self.N!r}")
        if not isinstance(self.n_faces, int) or self.n_faces < 3:
            raise ValueError(f"n_faces must be an int >= 3, got {self.n_faces!r}")
        checks.choice("rendezvous_cost", self.rendezvous_cost, ("qp", "lp"))
        for name in ("between_samples", "finite_burn", "latch_turn"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be True or False, got {getattr(self, name)!r}")

    def notes(self) -> tuple[str, ...]:
        """Assumptions this configuration adds to its scenario's (printed with a run)."""
        if self.latch_turn:
            return (
                "keep-out planes: once the turn does not fit in the horizon, the sense chosen "
                "first is kept until it fits (latch_turn; the thesis' 'natural relative orbit "
                "motion' read per step flips near the bearing opposite the approach axis)",
            )
        return ()


class Guidance(NamedTuple):
    """The current phase (0 rendezvous, 1 approach, 2 docking) and whether the chaser has
    been inside the docking cone at a sample of the docking phase (from then on the truth
    must stay in it: the docking cone is judged; before, the chaser is still entering).
    ``turn`` (with ``Config.latch_turn``): the unit axis (3,) about which the keep-out
    planes turned at the last step whose turn did not fit in the horizon; zero while the turn
    fits (or before the first step, or after the rendezvous phase); None without."""

    phase: jnp.ndarray
    entered: jnp.ndarray | bool = True
    turn: jnp.ndarray | None = None


SCHEMA = Schema(
    (
        positive("mass", "kg", "chaser mass"),
        positive("altitude_m", "m", "circular target orbit altitude (CW mean motion)"),
        positive("ts", "s", "sample time", shape="per-phase", alias="Ts"),
        value(
            "Q",
            "",
            "state weight per phase: (6,) diagonals or (6, 6) PSD matrices",
            shape="(3, 6, 6)",
        ),
        value(
            "R",
            "",
            "input weight per phase: (3,) diagonals or (3, 3) PD matrices",
            shape="(3, 3, 3)",
        ),
        positive("u_max", "m/s", "per-axis delta-v bound per step", shape="per-phase"),
        positive("lam", "", "cone-penalty weight lambda", shape="per-phase"),
        within(
            "los_deg",
            "deg",
            0.0,
            90.0,
            "line-of-sight cone half angles",
            shape="per-phase",
            label="los_deg (cone half angles)",
        ),
        positive("r1", "m", "keep-out radius (rendezvous -> approach switch)"),
        positive("r2", "m", "approach -> docking switch radius (< r1)"),
        positive("r3", "m", "docked distance (< r2)"),
        positive("v_max", "m/s", "soft-docking velocity bound"),
        value("port_body", "m", "docking port in the target body frame (non-zero)", shape="(3,)"),
        finite("target_angle0_deg", "deg", "target body angle about z at t = 0", default=0.0),
        finite("target_rate_deg_s", "deg/s", "target body rate about z", default=0.0),
        positive("rho", "", "exact penalty of the hard constraints", default=1e6),
        Input(
            "switch_tol",
            "relative tolerance of the phase switches",
            check="range",
            lo=0.0,
            hi=1.0,
            lo_open=False,
            default=0.05,
        ),
        value(
            "setpoint",
            "",
            "rendezvous reference: the set point at r1 (false: the target)",
            kind="bool",
            default=True,
        ),
        value(
            "x0",
            "m, m/s",
            "initial state: finite, outside r1",
            shape="(6,)",
            kind="state",
            default=None,
        ),
        within(
            "inclination_deg",
            "deg",
            0.0,
            180.0,
            "target orbit inclination",
            closed=True,
            default=51.6,
        ),
        positive("drag_area_m2", "m^2", "chaser drag area", default=0.0366),
        positive("cd_chaser", "", "chaser drag coefficient", default=1.4),
        positive("cd_target", "", "target drag coefficient", default=2.0),
        positive("target_mass", "kg", "target mass (none: mass)", default=None),
        positive("target_area_m2", "m^2", "target drag area (none: drag_area_m2)", default=None),
        disturbance_table("disturbance keyword values over paper 003 Ch. 5's"),
    ),
    n_phases=N_PHASES,
)


def _build(v) -> Params:
    """Check physical values and build :class:`Params` (once, before any jit).

    Keywords: :data:`SCHEMA`. ``ts``, ``u_max``, ``lam``, ``los_deg`` take three values (one
    per phase), ``Q`` and ``R`` three matrices (or diagonals). ``inclination_deg``,
    ``drag_area_m2``, ``cd_chaser``, ``cd_target``, ``target_mass`` (default: ``mass``) and
    ``target_area_m2`` (default: ``drag_area_m2``) set up the nonlinear truths: the target's
    circular orbit (ascending node at t = 0) and both bodies' ballistic coefficients
    C_D A / m (paper 003 Sec. 5.4). ``disturbances``: keyword values over paper 003 Ch. 5's
    defaults (:data:`rvdjax.disturbances.THESIS_DISTURBANCES`).

    Raises ValueError naming the parameter: each input's own check (:data:`SCHEMA`), then
    r3 < r2 < r1; R positive definite and Q positive semidefinite per phase; port_body
    non-zero; x0 finite and outside r1.
    """
    from rvdjax.dynamics import cw_continuous, dare, discretize_impulsive, mean_motion

    x0 = v.x0
    ts, u_max, lam, los = (np.asarray(a, dtype=float) for a in (v.ts, v.u_max, v.lam, v.los_deg))
    if not v.r3 < v.r2 < v.r1:
        raise ValueError(f"radii must satisfy r3 < r2 < r1, got r1={v.r1}, r2={v.r2}, r3={v.r3} m")
    Qs = [np.diag(np.asarray(q, float)) if np.ndim(q) == 1 else np.asarray(q, float) for q in v.Q]
    Rs = [np.diag(np.asarray(r, float)) if np.ndim(r) == 1 else np.asarray(r, float) for r in v.R]
    if len(Qs) != N_PHASES or len(Rs) != N_PHASES:
        raise ValueError("Q and R must give one matrix per phase (3 each)")
    for k in range(N_PHASES):
        checks.shape(f"Q[{k}]", Qs[k], (6, 6))
        checks.shape(f"R[{k}]", Rs[k], (3, 3))
        checks.pos_semidef(f"Q[{k}] (phase {k})", Qs[k])
        checks.pos_def(f"R[{k}] (phase {k})", Rs[k])
    port = checks.shape("port_body", v.port_body, (3,))
    if np.linalg.norm(port) == 0:
        raise ValueError("port_body must be a non-zero (3,) vector [m]")
    if x0 is not None:
        x0 = checks.shape("x0", x0, (6,))
        checks.outside("the keep-out sphere r1", x0[:3], np.zeros(3), v.r1)
    target_mass = v.mass if v.target_mass is None else v.target_mass
    target_area_m2 = v.drag_area_m2 if v.target_area_m2 is None else v.target_area_m2
    n = mean_motion(altitude_m=v.altitude_m)
    Ac, _ = cw_continuous(n, v.mass)
    A, B, P = [], [], []
    for k in range(N_PHASES):
        Ak, Bk = discretize_impulsive(Ac, float(ts[k]))
        A.append(Ak)
        B.append(Bk)
        P.append(dare(Ak, Bk, jnp.asarray(Qs[k]), jnp.asarray(Rs[k])))
    f = jnp.asarray
    return Params(
        A=jnp.stack(A),
        B=jnp.stack(B),
        Q=f(np.stack(Qs)),
        R=f(np.stack(Rs)),
        Q_f=jnp.stack(P),
        ts=f(ts),
        u_max=f(u_max),
        lam=f(lam),
        half_angle=f(np.deg2rad(los)),
        n=f(n),
        r1=f(float(v.r1)),
        r2=f(float(v.r2)),
        r3=f(float(v.r3)),
        v_max=f(float(v.v_max)),
        port_body=f(port),
        axis_body=f(port / np.linalg.norm(port)),
        target_angle0=f(np.deg2rad(v.target_angle0_deg)),
        target_rate=f(np.deg2rad(v.target_rate_deg_s)),
        rho=f(float(v.rho)),
        switch_tol=f(float(v.switch_tol)),
        setpoint=f(1.0 if v.setpoint else 0.0),
        plant=make_plant(
            float(v.mass),
            *cw_continuous(n, v.mass),
            orbit=circular_orbit(v.altitude_m, inclination_rad=np.deg2rad(v.inclination_deg)),
            drag=Drag(
                b_chaser=f(v.cd_chaser * v.drag_area_m2 / v.mass),
                b_target=f(v.cd_target * target_area_m2 / target_mass),
            ),
            disturbances=make_disturbances(**{**THESIS_DISTURBANCES, **(v.disturbances or {})}),
        ),
    )


make_params = make_params_of(SCHEMA, _build)


def check(params: Params, x0, config) -> None:
    """The LP rendezvous cost needs a diagonal rendezvous R (||R u||_1 = sum R_ii |u_i|)."""
    if config.family_config.rendezvous_cost == "lp":
        R0 = np.asarray(params.R[0], dtype=float)
        if not np.array_equal(R0, np.diag(np.diag(R0))) or np.any(np.diag(R0) <= 0):
            raise ValueError(
                "R[0] must be diagonal with a positive diagonal for the LP rendezvous cost "
                "(||R u||_1 is modelled as sum_i R_ii |u_i|)"
            )
