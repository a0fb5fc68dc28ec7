"""Paper 002 (Nonlinear MPC for spacecraft rendezvous and docking with a rotating target):
cases A-C of Table 1, results of Table 2. rvdjax solves the linearised (LQ) problem."""

from __future__ import annotations

from rvdjax.actuators import sets
from rvdjax.scenarios import Scenario, paper_kappa

# case: (target rate [deg/s], published effort [N s], published time to dock [s])
CASES = {"a": (0.5, 5.98, 152.0), "b": (1.0, 7.04, 155.0), "c": (2.0, 9.40, 165.0)}

ASSUMPTIONS = (
    "chaser mass 10 kg (POSEIDYN, 'approximately 10 kg'), inertia 0.15 kg m^2 (a 0.3 m cube), "
    "torque limit 0.015 N m (0.15 N at 0.1 m)",
    "target port axis at 0 deg at t = 0; chaser starts at rest with attitude 0 deg",
    "holding position 0.05 m outside the dynamic circle; phase switch and shrink when the "
    "position error < 0.1 m and attitude error < 10 deg (thresholds c_alpha1, c_alpha2 are not "
    "given); docked when r_hold = r_t and the chaser is within 0.05 m of its holding position",
    "the entry cone (20 deg) is enforced over the whole horizon once the final phase starts; "
    "its 0.5 m corridor length is not modelled; in the final phase the keep-out and holding "
    "circles are linearised about the port axis (tangent lines across the cone; paper 002's "
    "NMPC keeps them exact), in free flight about the previous plan",
    "keep-out and cone rows are soft (exact penalty rho = 1e5 per metre)",
    "effort: with ideal forces, sum_k (|Fx| + |Fy|) Ts (attitude not counted); with the "
    "thrusters (rvdjax run --thrusters) paper 002 Eq. 11, the impulse of all 8 thrusters, "
    "attitude firings included (u_i in {0, 1} times the thrust: the paper reports N s)",
    "rvdjax solves the linearised (LQ) problem; paper 002 solves the nonlinear one (IPOPT)",
)


def _rotating(case: str) -> Scenario:
    rate, effort, time = CASES[case]
    return Scenario(
        name=f"rotating-target-{case}",
        family="planar-docking",
        source="paper 002 Tables 1-2",
        description=f"planar two-phase docking to a target rotating at {rate} deg/s",
        physical=dict(
            mass=10.0,
            inertia=0.15,
            ts=2.0,
            Q=(10.0, 10.0, 10.0, 300.0, 300.0, 500.0),
            R=(10.0, 10.0, 10.0),
            u_max=(0.15, 0.15, 0.015),
            target=(2.0, 2.0, 0.0),
            target_rate_deg_s=rate,
            r_t=0.65,
            r_hold0=1.15,
            gap=0.05,
            gamma=0.98,
            c_pos=0.1,
            c_att_deg=10.0,
            half_angle_deg=20.0,
        ),
        x0=(3.5, 3.5, 0.0, 0.0, 0.0, 0.0),
        config=dict(N=40, logic="two-phase"),
        n_steps=150,
        published={
            "effort_l1_N_s": {"NMPC (IPOPT)": effort},
            "time_to_dock_s": {"NMPC (IPOPT)": time},
        },
        assumptions=ASSUMPTIONS,
        paper_kappa=paper_kappa(q_position=10.0, dock_tol_m=0.05),
        thrusters=sets.POSEIDYN_PWM,
        thruster_metrics={"effort_l1_N_s": "thruster_impulse_N_s"},
    )


SCENARIOS = tuple(_rotating(c) for c in CASES)
