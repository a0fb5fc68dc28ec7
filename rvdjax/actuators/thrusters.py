"""Thruster sets as data (DESIGN §7a): what each vehicle of the papers fires.

A :class:`ThrusterSet` is a plain record (body-frame positions and unit directions, maximum
thrust, valve resolution, minimum on-time, specific impulse, the modulator and its values,
the assumptions behind every value a paper does not give). :meth:`ThrusterSet.build` checks
it once and returns the traced :class:`Thrusters` (arrays: they can be batched, dispersed and
differentiated) and :meth:`ThrusterSet.actuation` the static :class:`Actuation` (the
modulator kind and the shapes: a change recompiles).

Frames. The body frame of the planar vehicles (x, y in the table plane, z up) rotates with
the state's attitude angle (``Actuation.frame = "attitude"``); the 3-D vehicles keep their body
axes on the local (LVLH) frame (``"fixed"``: none of the papers flies an attitude for them).
A thruster of thrust f along unit direction d at position r gives the body force f d and the
torque f (r x d) about the centre of mass.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from rvdjax import checks
from rvdjax.actuators.modulation import ALIGNMENTS

__all__ = [
    "G0",
    "Thrusters",
    "Actuation",
    "ThrusterSet",
    "MODULATORS",
    "ALLOCATIONS",
    "FAULTS",
    "effectiveness",
    "rotation_z",
    "misaligned_directions",
    "axis_set",
    "planar_eight",
]

G0 = 9.80665  # standard gravity [m/s^2] (propellant mass from specific impulse)
MODULATORS = ("pwm", "schmitt", "delta-sigma")
ALLOCATIONS = ("least-thrust", "separate")
FAULTS = ("healthy", "stuck-off", "stuck-on")


class Thrusters(NamedTuple):
    """Traced thruster data (SI units).

    Attributes:
        position: (T, 3) body-frame position of each thruster from the centre of mass [m].
        direction: (T, 3) body-frame unit thrust direction (the force on the vehicle).
        thrust: (T,) nominal thrust when open [N].
        valve_s: () valve resolution: on-times are multiples of it [s].
        min_on_s: () minimum on-time (the minimum impulse bit is thrust * min_on_s) [s].
        isp_s: () specific impulse [s] (propellant mass = impulse / (isp g0)).
        schmitt_on, schmitt_off: () Schmitt trigger levels, fractions of the minimum on-time.
        magnitude_error: (T,) actual thrust = (1 + magnitude_error) * thrust (dispersion).
        misalignment: (T, 3) small rotation vector of each direction [rad] (dispersion).
        fault: (T,) 0 healthy, 1 stuck off, 2 stuck on (:data:`FAULTS`); applied only by a
            loop whose :attr:`Actuation.faults` is True.
        fault_time_s: (T,) the fault acts from the first step starting at or after it [s].
    """

    position: jnp.ndarray
    direction: jnp.ndarray
    thrust: jnp.ndarray
    valve_s: jnp.ndarray
    min_on_s: jnp.ndarray
    isp_s: jnp.ndarray
    schmitt_on: jnp.ndarray
    schmitt_off: jnp.ndarray
    magnitude_error: jnp.ndarray
    misalignment: jnp.ndarray
    fault: jnp.ndarray
    fault_time_s: jnp.ndarray


@dataclasses.dataclass(frozen=True)
class Actuation:
    """Static actuator configuration of a loop (a change recompiles).

    Attributes:
        n: number of thrusters T.
        modulator: "pwm" (one pulse per control period from its start, on-time quantised to
            the valve resolution; pulses under the minimum on-time dropped, or carried with
            ``carry``), "schmitt" (PWM whose pulses under the minimum on-time fire at the
            minimum on-time or not at all, by a Schmitt trigger on their length: Basilisk's
            thrFiringSchmitt) or "delta-sigma" (paper 001's modulator: the valve opens for
            whole ticks of Ts / ``ticks``, driven by the integral of command minus fired).
        carry: PWM: the impulse lost to quantisation and to dropped pulses is added to the
            next command of the same thruster (error feedback); False drops it (paper 003).
        align: PWM and Schmitt: "start" (the pulse opens with the period: an impulsive
            model's delta-v acts as early as it can) or "centre" (centred in the period: a
            zero-order-hold model's impulse centroid, exact for a double integrator at the
            period's end), :data:`rvdjax.actuators.modulation.ALIGNMENTS`.
        ticks: delta-sigma ticks per control period.
        rows: the wrench rows (0-2 force x, y, z; 3-5 torque x, y, z, body frame) the
            allocation must meet; the family's force inputs map to rows 0, 1(, 2) in order,
            its torque input to row 5, every other listed row to zero.
        frame: "attitude" (body frame rotated about z by the state's attitude angle) or
            "fixed" (body axes on the model frame).
        pair_groups: the thrusters along each body axis direction, ordered +x, -x, +y,
            -y(, +z, -z), each group's thrusters alike and placed so that thrust shared
            equally among them gives no torque. The allocation of a force demand is then the
            closed form of opposing pairs (each group one thruster of the group's total
            thrust, shared equally), exact whenever no torque is demanded: single-thruster
            groups (thrusters through the centre of mass) always, larger groups when the
            family has no torque input and no fault can split a group. Empty: the LP.
        allocation: "least-thrust" (the least total thrust that meets force and torque
            together: a torque may come for free from firing a pair unevenly) or "separate"
            (a simple vehicle's split: the force by ``pair_groups``, each group's thrusters
            sharing it equally so that it gives no torque, plus the torque by the least-thrust
            pure couple; the sum is scaled down as a whole where a thruster saturates). Needs
            ``pair_groups``, a torque row and no faults.
        fdir: the allocation knows a failed thruster from its onset (it allocates around a
            stuck-off thruster and subtracts a stuck-on one from the demand); False: the
            fault goes unnoticed.
        faults: the loop applies ``Thrusters.fault``; False compiles the fault logic out (the
            allocation then sees one thrust vector for a whole batch, which is cheaper).
    """

    n: int
    modulator: str = "pwm"
    carry: bool = False
    align: str = "start"
    ticks: int = 50
    rows: tuple[int, ...] = (0, 1, 2)
    frame: str = "fixed"
    pair_groups: tuple[tuple[int, ...], ...] = ()
    allocation: str = "least-thrust"
    fdir: bool = True
    faults: bool = False

    def __post_init__(self):
        checks.integer("n (number of thrusters)", self.n)
        checks.choice("modulator", self.modulator, MODULATORS)
        checks.choice("align (pulse position in the period)", self.align, ALIGNMENTS)
        checks.integer("ticks (delta-sigma ticks per control period)", self.ticks)
        checks.choice("frame", self.frame, ("attitude", "fixed"))
        if not self.rows or any(r not in range(6) for r in self.rows):
            raise ValueError(f"rows must be wrench rows in 0..5, got {self.rows!r}")
        checks.choice("allocation", self.allocation, ALLOCATIONS)
        if self.allocation == "separate":
            n_axes = len(self.pair_groups) // 2
            if not self.pair_groups or len(self.rows) <= n_axes or self.faults:
                raise ValueError(
                    "allocation='separate' needs pair_groups, a torque row after the force "
                    "rows and no faults"
                )


@dataclasses.dataclass(frozen=True)
class ThrusterSet:
    """A vehicle's thrusters as plain data (checked by :meth:`build`).

    Attributes:
        name: a label.
        position_m: T body-frame positions [m] (planar sets: z = 0).
        direction: T body-frame thrust directions (normalised by :meth:`build`).
        thrust_N: thrust of each thruster when open [N] (one value or T).
        valve_s: valve resolution [s] (> 0).
        min_on_s: minimum on-time [s] (>= 0).
        isp_s: specific impulse [s] (> 0).
        modulator, carry, align, ticks, rows, frame, pair_groups, allocation, fdir:
            :class:`Actuation`.
        schmitt_levels: (on, off) levels of the Schmitt trigger, fractions of min_on_s.
        assumptions: what rvdjax chose where the papers are silent (printed with a run).
    """

    name: str
    position_m: tuple
    direction: tuple
    thrust_N: float | tuple = 1.0
    valve_s: float = 0.01
    min_on_s: float = 0.0
    isp_s: float = 70.0
    modulator: str = "pwm"
    carry: bool = False
    align: str = "start"
    ticks: int = 50
    rows: tuple[int, ...] = (0, 1, 2)
    frame: str = "fixed"
    pair_groups: tuple[tuple[int, ...], ...] = ()
    allocation: str = "least-thrust"
    fdir: bool = True
    schmitt_levels: tuple[float, float] = (0.75, 0.25)
    assumptions: tuple[str, ...] = ()

    @property
    def n(self) -> int:
        return len(self.position_m)

    def actuation(self, **changes) -> Actuation:
        """The static :class:`Actuation` of this set (``changes`` override its fields)."""
        fields = {f.name for f in dataclasses.fields(Actuation)} - {"n", "faults"}
        base = {k: getattr(self, k) for k in fields}
        return Actuation(n=self.n, **{**base, **changes})

    def replace(self, **changes) -> ThrusterSet:
        return dataclasses.replace(self, **changes)

    def build(
        self,
        magnitude_error=None,
        misalignment=None,
        fault=None,
        fault_time_s=None,
    ) -> Thrusters:
        """Check the values (ValueError naming the field and its allowed range) and return the
        traced :class:`Thrusters`; the dispersions default to none."""
        T = self.n
        pos = checks.shape("position_m", self.position_m, (T, 3))
        checks.finite("position_m", pos, "m")
        d = checks.shape("direction", self.direction, (T, 3))
        norms = np.linalg.norm(d, axis=1)
        if not np.all(np.isfinite(norms)) or np.any(norms < 1e-12):
            raise ValueError("direction: every thruster needs a finite, non-zero direction")
        thrust = np.broadcast_to(np.asarray(self.thrust_N, float), (T,)).copy()
        checks.positive("thrust_N", thrust, "N")
        checks.positive("valve_s", self.valve_s, "s")
        checks.nonnegative("min_on_s", self.min_on_s, "s")
        checks.positive("isp_s", self.isp_s, "s")
        on, off = self.schmitt_levels
        checks.in_range("schmitt_levels (on)", on, 0.0, 1.0, False, False)
        checks.in_range("schmitt_levels (off)", off, 0.0, on, False, False)
        mag = np.zeros(T) if magnitude_error is None else np.broadcast_to(magnitude_error, (T,))
        checks.in_range("magnitude_error", mag, -1.0, None, lo_open=False)
        mis = np.zeros((T, 3)) if misalignment is None else np.broadcast_to(misalignment, (T, 3))
        checks.finite("misalignment", mis, "rad")
        fault = np.zeros(T, int) if fault is None else np.broadcast_to(fault, (T,))
        if not np.all(np.isin(fault, (0, 1, 2))):
            raise ValueError(f"fault must be 0 (healthy), 1 (stuck off) or 2 (stuck on): {fault}")
        ft = np.zeros(T) if fault_time_s is None else np.broadcast_to(fault_time_s, (T,))
        checks.nonnegative("fault_time_s", ft, "s")
        f = jnp.asarray
        return Thrusters(
            position=f(pos),
            direction=f(d / norms[:, None]),
            thrust=f(thrust),
            valve_s=f(float(self.valve_s)),
            min_on_s=f(float(self.min_on_s)),
            isp_s=f(float(self.isp_s)),
            schmitt_on=f(float(on)),
            schmitt_off=f(float(off)),
            magnitude_error=f(np.asarray(mag, float)),
            misalignment=f(np.asarray(mis, float)),
            fault=f(np.asarray(fault, np.int32)),
            fault_time_s=f(np.asarray(ft, float)),
        )

    def describe(self) -> str:
        """One line: count, thrust, modulator and its values."""
        thrust = np.unique(np.broadcast_to(np.asarray(self.thrust_N, float), (self.n,)))
        mod = self.modulator + (
            f" ({self.ticks} ticks a period)" if self.modulator == "delta-sigma" else ""
        )
        if self.modulator in ("pwm", "schmitt"):
            mod += ", pulses centred in the period" if self.align == "centre" else ""
        if self.modulator == "pwm":
            mod += ", short pulses carried" if self.carry else ", short pulses dropped"
        if self.allocation == "separate":
            mod += ", force and couple allocated separately"
        return (
            f"{self.name}: {self.n} thrusters of {'/'.join(f'{t:g}' for t in thrust)} N, "
            f"{mod}, valve resolution {self.valve_s:g} s, minimum on-time {self.min_on_s:g} s, "
            f"Isp {self.isp_s:g} s"
        )


# --------------------------------------------------------------------------------------------


def rotation_z(theta):
    """(3, 3) rotation about z by ``theta`` [rad] (body to model frame)."""
    c, s = jnp.cos(theta), jnp.sin(theta)
    z, o = jnp.zeros_like(c), jnp.ones_like(c)
    return jnp.stack([jnp.stack([c, -s, z]), jnp.stack([s, c, z]), jnp.stack([z, z, o])])


def _rodrigues(w):
    """(3, 3) rotation by the rotation vector ``w`` [rad]; smooth at w = 0."""
    th2 = jnp.sum(w * w)
    small = th2 < 1e-16
    th = jnp.sqrt(jnp.where(small, 1.0, th2))
    a = jnp.where(small, 1.0 - th2 / 6.0, jnp.sin(th) / th)
    b = jnp.where(small, 0.5 - th2 / 24.0, (1.0 - jnp.cos(th)) / jnp.where(small, 1.0, th2))
    K = jnp.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    return jnp.eye(3) + a * K + b * (K @ K)


def misaligned_directions(thr: Thrusters):
    """(T, 3) actual body-frame directions: each nominal one rotated by its misalignment."""
    import jax

    R = jax.vmap(_rodrigues)(thr.misalignment)
    return jnp.einsum("tij,tj->ti", R, thr.direction)


def effectiveness(position, direction):
    """(6, T) wrench per newton of each thruster: rows force x, y, z and torque x, y, z."""
    torque = jnp.cross(position, direction)
    return jnp.concatenate([direction.T, torque.T], axis=0)


# --------------------------------------------------------------------------------------------
# Builders


def axis_set(name: str, thrust_N: float, arm_m: float = 0.0, **options) -> ThrusterSet:
    """Six thrusters in opposing pairs along the body axes through the centre of mass, ordered
    +x, -x, +y, -y, +z, -z (a "direction" is the force on the vehicle). ``arm_m`` places them
    on the faces of a cube (the position does not matter: they pass through the centre)."""
    dirs = []
    for axis in range(3):
        for sign in (1.0, -1.0):
            d = [0.0, 0.0, 0.0]
            d[axis] = sign
            dirs.append(tuple(d))
    pos = tuple(tuple(-arm_m * c for c in d) for d in dirs)
    return ThrusterSet(
        name=name,
        position_m=pos,
        direction=tuple(dirs),
        thrust_N=thrust_N,
        pair_groups=tuple((i,) for i in range(6)),
        rows=(0, 1, 2),
        frame="fixed",
        **options,
    )


def planar_eight(name: str, thrust_N: float, half_width_m: float, offset_m: float, **options):
    """Eight thrusters of a square air-bearing vehicle, two on each face, firing inward along
    the face normal (the force on the vehicle points away from the face), ``offset_m`` either
    side of the face centre: each pair gives a pure force, one thruster of a pair a force and
    a torque of thrust * offset. Thrusters 0-1 are on the +x face (force -x), 2-3 on -x, 4-5
    on +y, 6-7 on -y."""
    w, o = half_width_m, offset_m
    pos, dirs = [], []
    for nx_, ny_ in ((1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0)):
        tx, ty = -ny_, nx_  # along the face
        for side in (1.0, -1.0):
            pos.append((w * nx_ + side * o * tx, w * ny_ + side * o * ty, 0.0))
            dirs.append((-nx_, -ny_, 0.0))
    return ThrusterSet(
        name=name,
        position_m=tuple(pos),
        direction=tuple(dirs),
        thrust_N=thrust_N,
        rows=(0, 1, 5),
        frame="attitude",
        pair_groups=((2, 3), (0, 1), (6, 7), (4, 5)),  # +x, -x, +y, -y
        **options,
    )
