"""The truth: one step of the plant for a family's layout (DESIGN §4).

* ``linear``: the discrete model of the current phase itself, exact (matrix exponential; ZOH
  for force inputs, impulsive for delta-v inputs).
* ``two-body``, ``two-body-j2``, ``two-body-j2-drag``: both spacecraft integrated in the
  inertial frame (RK4, :mod:`rvdjax.propagate`) — model mismatch. A force is held constant in
  the LVLH frame over the step; a delta-v is applied at the start of the step, then both bodies
  coast for Ts.

The actuator (:mod:`rvdjax.disturbances`) sits in front: minimum impulse bit on the force
axes, then the Gauss-Markov thrust-amplitude error on every axis.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import jax.numpy as jnp
from jax import lax

from rvdjax.actuators.response import pulse_response, pulse_segments
from rvdjax.propagate import propagate_step

if TYPE_CHECKING:
    from rvdjax.actuators.thrusters import Thrusters
    from rvdjax.disturbances import Disturbances
    from rvdjax.propagate import Drag, Orbit

__all__ = [
    "Plant",
    "checked_plant",
    "with_plant",
    "TRUTHS",
    "truth_step",
    "truth_step_pulses",
    "impulse_per_unit",
]


class Plant(NamedTuple):
    """The vehicle and its surroundings as the truth flies them: one field of every guidance
    family's traced parameters (``params.plant``), the only part of them the loop kernel reads.

    Attributes:
        mass: the chaser's mass [kg] (impulse <-> delta-v, the nonlinear truths' accelerations).
        orbit: the target's inertial orbit (:class:`~rvdjax.propagate.Orbit`, the nonlinear
            truths' initial condition); None for a family flown on its linear model only.
        drag: differential drag (:class:`~rvdjax.propagate.Drag`, truth
            ``two-body-j2-drag``); None without.
        disturbances: navigation noise, thrust error and minimum impulse bit
            (:class:`~rvdjax.disturbances.Disturbances`, disturbed runs); None without.
        Ac, Bc: the continuous model and its force input [N, N m] -> state rate: the linear
            truth's response to thruster pulses (:mod:`rvdjax.actuators.response`).
        thrusters: the vehicle's thrusters (:class:`~rvdjax.actuators.thrusters.Thrusters`,
            runs with thrusters); None: ideal forces.
    """

    mass: jnp.ndarray
    orbit: Orbit | None = None
    drag: Drag | None = None
    disturbances: Disturbances | None = None
    Ac: jnp.ndarray | None = None
    Bc: jnp.ndarray | None = None
    thrusters: Thrusters | None = None

    # provenance (rvdjax.provenance.canonical) stores these fields as the parameters' own, as
    # they were before the record, so that stored definitions of runs keep their meaning
    STORED_FLAT = True


def checked_plant(params, family: str, actuation, disturbed: bool, truth: str) -> Plant:
    """``params.plant``, checked against the loop's configuration while its program is traced
    (the contract of :mod:`rvdjax.loop.family`): a :class:`Plant`, with the thrusters a loop
    with ``actuation`` flies, the disturbances of a ``disturbed`` run and the orbit of a
    nonlinear ``truth``."""
    plant = getattr(params, "plant", None)
    if not isinstance(plant, Plant):
        raise TypeError(
            f"the {family} family's parameters need a field plant: rvdjax.loop.plant.Plant"
            f" (got {type(plant).__name__})"
        )
    if actuation is not None:
        thr = plant.thrusters
        if thr is None or thr.thrust.shape != (actuation.n,):
            raise ValueError(
                f"a loop with thrusters needs params.plant.thrusters of {actuation.n} "
                "thrusters (Scenario.build(thrusters=True))"
            )
    if disturbed and plant.disturbances is None:
        raise ValueError("a disturbed run needs params.plant.disturbances")
    if truth != "linear" and plant.orbit is None:
        raise ValueError(f"truth={truth!r} needs params.plant.orbit (the target's orbit)")
    return plant


def with_plant(params, **fields):
    """``params`` with the named :class:`Plant` fields replaced (``thrusters=...``)."""
    return params._replace(plant=params.plant._replace(**fields))


TRUTHS = ("linear", "two-body", "two-body-j2", "two-body-j2-drag")


def impulse_per_unit(layout, mass, dt):
    """Impulse [N s] per unit of a force-axis command: dt for a force, m for a delta-v."""
    return dt if layout.input == "force" else mass


def truth_step(layout, truth: str, substeps: int, A, B, plant, orbit, x, u, dt):
    """(x_next, orbit_next) of the truth after applying ``u`` for one step of ``dt`` [s].

    Args:
        layout: the family's :class:`~rvdjax.loop.family.Layout`.
        truth: one of :data:`TRUTHS` (static).
        substeps: RK4 steps per sample for the nonlinear truths (static).
        A, B: the discrete model of the step (linear truth).
        plant: the :class:`Plant` (``mass``, ``drag``).
        orbit: the target's inertial state (nonlinear truths) or None.
    """
    if truth == "linear":
        return A @ x + B @ u, orbit
    j2 = truth != "two-body"
    drag = plant.drag if truth == "two-body-j2-drag" else None
    if layout.input == "force":
        orbit_next, x_next = propagate_step(orbit, x, u, plant.mass, dt, substeps, j2, drag)
    else:  # impulse at the step start (paper 003 Eq. 3.1), then both bodies coast for Ts
        vel = jnp.asarray(layout.vel)
        orbit_next, x_next = propagate_step(
            orbit, x.at[vel].add(u), jnp.zeros_like(u), plant.mass, dt, substeps, j2, drag
        )
    return x_next, orbit_next


def truth_step_pulses(
    truth: str,
    substeps: int,
    A,
    plant,
    orbit,
    x,
    pulses,
    g,
    dt,
    grid: bool = False,
    from_start: bool = True,
):
    """(x_next, orbit_next) of the truth under valve pulses (:mod:`rvdjax.actuators`).

    Linear truth: A x plus the exact forced response of the pulses
    (:func:`rvdjax.actuators.response.pulse_response`, continuous model ``plant.Ac``,
    ``plant.Bc``). Nonlinear truths: RK4 over the constant-thrust segments between valve
    closings (``substeps`` RK4 steps each), the force held in the LVLH frame.

    Args:
        pulses: (T, P) starts and widths [s]; g: (T, nu) generalised force of each thruster
            while open, model frame [N, N m].
        grid: static; whole ticks of one shared grid (delta-sigma, linear truth only).
        from_start: static; every pulse starts with the period (PWM aligned to its start):
            the nonlinear truths then cut it at the valve closings only.
    """
    if truth == "linear":
        return A @ x + pulse_response(plant.Ac, plant.Bc, dt, pulses, g, grid), orbit
    j2 = truth != "two-body"
    drag = plant.drag if truth == "two-body-j2-drag" else None
    durations, forces = pulse_segments(pulses, g, dt, from_start)

    def seg(carry, piece):
        o, xc = carry
        h, f = piece
        o2, x2 = propagate_step(o, xc, f, plant.mass, h, substeps, j2, drag)
        return (o2, x2), None

    (orbit_next, x_next), _ = lax.scan(seg, (orbit, x), (durations, forces))
    return x_next, orbit_next
