"""Paper 000 (Fast MPC for spacecraft rendezvous and docking with moving obstacles):
the 3-D CW rendezvous of Sec. IV.A (Table 1) and the 2-D SPOT cases of Sec. IV.B (Table 2)."""

from __future__ import annotations

import numpy as np

from rvdjax.actuators import sets
from rvdjax.scenarios import Scenario, paper_kappa

# Table 1 (three-dimensional simulations).
FASTMPC3D = dict(
    altitude_m=705e3,
    mass=6500.0,
    ts=15.0,
    Q=(1.0, 1.0, 1.0, 100.0, 100.0, 100.0),
    R=(100.0, 100.0, 100.0),
    u_max=20.0,
    stop_radius=2.3,
    obstacles=(
        (-30.0, -800.0, 10.0, -0.075, -0.005, 0.015),
        (-100.0, 0.0, -40.0, 0.07, -0.16, 0.01),
    ),
    radii=(20.0, 50.0),
    # exact penalty 1e8 per unit of relative penetration |x - o| / r - 1 (the row scaling of
    # paper 000 Eq. 8): 1e8 / r per metre
    rho=(1e8 / 20.0, 1e8 / 50.0),
    # disturbed runs only: paper 003 Ch. 5's noise and thrust error on paper 000's chaser
    disturbances=dict(sigma_pos=0.05, sigma_vel=1e-3, thrust_max=20.0),
)
FASTMPC3D_X0 = (50.0, -1000.0, 10.0, 0.0, 0.0, 0.0)

_FASTMPC_ASSUMPTIONS = (
    "obstacles move on straight lines at their Table 1 velocities (paper: 'constant "
    "translational velocity')",
    "keep-out rows re-linearised each step about the previous plan (first step: unforced drift)",
    "keep-out rows are soft with exact L1 penalty rho = 1e8 per unit of relative penetration "
    "(|r - o| / r_j - 1; 5e6 and 2e6 per metre), ~100x the largest keep-out multiplier",
    "'total impulse' compared as sum_k ||u_k||_1 Ts (per-axis thrusters); the L2 sum is also "
    "reported",
    "Earth mu = 3.986004418e14 m^3/s^2, radius 6378.137 km; the truth is the CW model itself "
    "unless --truth two-body / two-body-j2 (equatorial circular target orbit at 705 km)",
)

_FASTMPC_PUBLISHED = {
    # paper 000 Sec. IV.A "total impulse" [N s]; matches sum_k ||u_k||_1 Ts
    "effort_l1_N_s": {
        "Fast MPC": 33.98e3,
        "ISNM": 33.80e3,
        "IPOPT NMPC": 32.93e3,
        "fmincon": 34.33e3,
    },
}

# Table 2: 2-D SPOT simulations (RED chaser, rotating and translating target, two moving
# obstacles). The paper shows trajectories only; no figure of merit is tabulated.
_SPOT_CASES = {
    "a": dict(
        x0=(3.0, 1.3, 180.0),
        target=(1.1, 1.3, 270.0, 0.015, -0.008, 4.0),
        obstacles=((1.0, 2.0, 0.0, -0.005), (1.0, 0.5, 0.01, 0.0)),
    ),
    "b": dict(
        x0=(3.2, 2.2, 90.0),
        target=(0.2, 0.2, 0.0, 0.02, 0.01, -2.5),
        obstacles=((1.3, 1.0, 0.01, -0.01), (2.1, 1.0, 0.012, 0.01)),
    ),
}
_SPOT_ASSUMPTIONS = (
    "chaser = SPOT RED: 16.9478 kg, 0.2709 kg m^2 (the SPOT initialiser); torque limit "
    "0.025 N m (two 0.15 N thrusters at 83 mm)",
    "target docking port on the target body x-axis, 0.15 m from its centre (0.3 m platforms); "
    "docked when r_hold reaches r_hold,min = 0.3 m (centre to centre) with the chaser within "
    "0.05 m of the holding point and the attitude error < 10 deg",
    "holding point on the holding circle (no gap), straight in front of the port; the chaser "
    "must also stay 0.3 m from the target centre",
    "obstacles move on straight lines at their Table 2 velocities; keep-out, holding and cone "
    "rows are soft (rho = 1e5 per metre)",
    "paper 000 tabulates no figure of merit for these cases (trajectory figures only)",
)


def _spot(case: str, obstacles: bool) -> Scenario:
    c = _SPOT_CASES[case]
    tg = c["target"]
    name = f"spot-2d-{case}" + ("" if obstacles else "-free")
    return Scenario(
        name=name,
        family="planar-docking",
        source="paper 000 Sec. IV.B, Table 2" + ("" if obstacles else " (obstacles absent)"),
        description=f"SPOT 2-D docking, case {case.upper()}: rotating and translating target"
        + (", two moving obstacles" if obstacles else ", no obstacles"),
        physical=dict(
            mass=16.9478,
            inertia=0.2709,
            ts=2.0,
            Q=(10.0, 10.0, 10.0, 300.0, 300.0, 500.0),
            R=(10.0, 10.0, 10.0),
            u_max=(0.15, 0.15, 0.025),
            target=(tg[0], tg[1], float(np.deg2rad(tg[2]))),
            target_vel=(tg[3], tg[4]),
            target_rate_deg_s=tg[5],
            r_t=0.3,
            r_min=0.3,
            r_port=0.15,
            r_hold0=1.15,
            gap=0.0,
            gamma=0.95,
            c_pos=float(np.sqrt(0.5)),
            c_att_deg=10.0,
            half_angle_deg=20.0,
            cone_radius=0.75,
            obstacles=c["obstacles"],
            obstacle_radii=(0.47, 0.47),
            obstacles_on=obstacles,
        ),
        x0=(*c["x0"][:2], float(np.deg2rad(c["x0"][2])), 0.0, 0.0, 0.0),
        config=dict(N=15, logic="holding-radius"),
        n_steps=150,
        published={},
        assumptions=_SPOT_ASSUMPTIONS,
        thrusters=sets.SPOT,
        paper_kappa=paper_kappa(q_position=10.0, dock_tol_m=0.05),
    )


SCENARIOS = (
    Scenario(
        name="fastmpc-3d",
        family="rendezvous",
        source="paper 000 Sec. IV.A, Table 1",
        description="3-D CW rendezvous at 705 km to 2.3 m, two moving spherical keep-out zones",
        physical=FASTMPC3D,
        x0=FASTMPC3D_X0,
        config=dict(N=30),
        n_steps=240,
        published=_FASTMPC_PUBLISHED,
        assumptions=_FASTMPC_ASSUMPTIONS,
        thrusters=sets.FASTMPC_3D,
    ),
    Scenario(
        name="fastmpc-3d-free",
        family="rendezvous",
        source="paper 000 Sec. IV.A, Table 1 (obstacles absent)",
        description="3-D CW rendezvous at 705 km to 2.3 m, no obstacles",
        physical={**FASTMPC3D, "obstacles_on": False},
        x0=FASTMPC3D_X0,
        config=dict(N=30),
        n_steps=240,
        published={},  # paper 000 plots this case (Fig. 3, left) but gives no impulse
        assumptions=_FASTMPC_ASSUMPTIONS[3:],
        thrusters=sets.FASTMPC_3D,
    ),
    _spot("a", True),
    _spot("a", False),
    _spot("b", True),
    _spot("b", False),
)
