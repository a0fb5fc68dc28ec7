"""The papers' vehicles as thruster sets (DESIGN §5, §7a). Every value a paper does not give
is an assumption, listed in the set's ``assumptions`` and printed with every run that flies
it.

* Paper 000, 3-D (``fastmpc-3d``): the paper applies ideal per-axis forces of up to 20 N;
  rvdjax's set is six 20 N thrusters along the body axes through the centre of mass.
* SPOT (paper 000's 2-D cases): eight 0.15 N thrusters, two on each face of the 0.3 m
  platform at 83 mm from the face centre (the scenarios' torque limit assumes them).
* POSEIDYN's free-flying simulator (papers 001 and 002): "eight cold-gas thrusters" (paper 001);
  paper 001's force limits (a quarter and a half of "the actual achievable level") give
  0.3 N per axis: eight 0.15 N thrusters, two on each face, 0.1 m from the face centre (the
  scenarios' 0.015 N m torque limit assumes one thruster at 0.1 m).
* Paper 003's 6U CubeSat: "500 mN thrusters configured to provide thrust in all axes" and six
  thrusters (Sec. 2.3): six 0.5 N thrusters along the body axes; pulses under the minimum
  impulse bit are discarded (Eq. 2.6).
"""

from __future__ import annotations

from rvdjax.actuators.thrusters import axis_set, planar_eight

__all__ = ["FASTMPC_3D", "SPOT", "POSEIDYN_PWM", "POSEIDYN_DELTA_SIGMA", "CUBESAT_6U"]

_CENTRED = (
    "PWM pulses centred in each period (the zero-order-hold model's impulse centroid: for the "
    "double integrator the state at the period's end is the model's whatever the width); "
)

_LAB = (
    "valve resolution 0.01 s (paper 002: 'a resolution of 0.01 s for each thruster'); "
    "minimum on-time 0.01 s (one valve tick; not given); Isp 60 s (compressed-air cold gas; "
    "not given)"
)

FASTMPC_3D = axis_set(
    "paper 000 chaser (ideal axes)",
    thrust_N=20.0,
    valve_s=0.01,
    min_on_s=0.0,
    isp_s=220.0,
    modulator="pwm",
    align="centre",
    assumptions=(
        "thrusters: six 20 N thrusters along the body axes through the centre of mass, body "
        "axes on LVLH (paper 000 applies ideal per-axis forces |u_i| <= 20 N); PWM centred in "
        "each 15 s period (the zero-order-hold model's impulse centroid), valve resolution "
        "0.01 s, no minimum on-time, Isp 220 s (hydrazine; not given)",
    ),
)

SPOT = planar_eight(
    "SPOT RED",
    thrust_N=0.15,
    half_width_m=0.15,
    offset_m=0.083,
    valve_s=0.01,
    min_on_s=0.01,
    isp_s=60.0,
    modulator="pwm",
    align="centre",
    assumptions=(
        "thrusters: eight 0.15 N thrusters, two on each face of the 0.3 m platform at 83 mm "
        "either side of the face centre, firing along the face normal; " + _CENTRED + _LAB,
    ),
)

POSEIDYN_PWM = planar_eight(
    "POSEIDYN free-flying simulator",
    thrust_N=0.15,
    half_width_m=0.15,
    offset_m=0.1,
    valve_s=0.01,
    min_on_s=0.01,
    isp_s=60.0,
    modulator="pwm",
    align="centre",
    assumptions=(
        "thrusters: eight 0.15 N thrusters (0.3 N per axis: paper 001's 0.15 N limit is 'a "
        "half of the actual achievable level'), two on each face of a 0.3 m body, 0.1 m either "
        "side of the face centre; attitude torque through the same thrusters, counted in "
        "paper 002 Eq. 11's effort; " + _CENTRED + _LAB,
    ),
)

POSEIDYN_DELTA_SIGMA = POSEIDYN_PWM.replace(
    modulator="delta-sigma",
    ticks=50,
    rows=(0, 1, 5),
    frame="fixed",
    assumptions=(
        "thrusters: eight 0.15 N thrusters (0.3 N per axis: paper 001's 0.15 N limit is 'a "
        "half of the actual achievable level'), two on each face of a 0.3 m body, 0.1 m either "
        "side of the face centre; " + _LAB,
        "delta-sigma modulator (paper 001, its ref. [4]; its rate is not given): 50 ticks of "
        "0.1 s per 5 s period, the valve open for whole ticks",
        "attitude held by paper 001's slew and PD loop outside the MPC with the body axes on "
        "the table axes; its firings are not modelled or counted (paper 001: 'only the "
        "translation forces are considered'); the allocation demands zero torque",
    ),
)

CUBESAT_6U = axis_set(
    "paper 003 6U CubeSat",
    thrust_N=0.5,
    arm_m=0.15,
    valve_s=0.01,
    min_on_s=0.02,
    isp_s=220.0,
    modulator="pwm",
    carry=False,
    assumptions=(
        "thrusters: six 0.5 N thrusters along the body axes through the centre of mass (Sec. "
        "2.3: 'configured to provide thrust in all axes'), body axes on LVLH; each delta-v "
        "becomes a pulse of m |dv| / 0.5 N from the start of the period (Eq. 2.5), quantised "
        "to 0.01 s; pulses under the minimum on-time 0.02 s (minimum impulse bit 10 mN s; "
        "not given) are discarded (Eq. 2.6); Isp 220 s (the thesis' AF-M315E example)",
        "thrusters: the guidance's model has the finite burns (a delta-v dv is a burn of "
        "m |dv| / 0.5 N from the period's start, up to 5 s: the impulse of Eq. 3.1 acts at the "
        "burn's centre, linearised about the previous plan's delta-v); the thesis' impulsive "
        "model with the burns (Config finite_burn=False) lags its plans by up to 0.45 m a step",
    ),
)
