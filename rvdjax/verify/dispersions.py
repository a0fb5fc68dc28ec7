"""Dispersions as one standardised vector xi ~ N(0, I).

A dispersion (``--dispersion``) is a ``+``-separated list of components; each takes its own
coordinates of xi (the count in brackets) and maps them, differentiably, to the run's
inputs:

* ``paper003`` (5 coordinates): paper 003 Sec. 4 initial state (3-D CW): range
  r_min + (r_max - r_min) Phi(xi_0) (0.15-2.5 km), bearing 2 pi Phi(xi_1) in the orbital
  plane, velocity (0, -2 n x, 0) + 0.5 m/s xi_2..4 (the same law as the studies'
  ``--initial paper003``);
* ``x0:SP,SV[,SA]`` (nx): x0 + N(0, SP) m on positions, N(0, SV) m/s on velocities,
  N(0, SA) rad on attitudes;
* ``mass:S`` (1): the truth's mass m exp(S xi) (the guidance keeps m): the applied force acts
  on the true mass;
* ``inertia:S`` (1): the same for the torques (planar 3-DOF);
* ``thrust:S`` (force axes / T): thrust magnitude (1 + S xi) per force axis, or per thruster
  with ``--thrusters``;
* ``misalignment:DEG`` (3 T): thruster direction rotation vectors DEG xi [deg]
  (``--thrusters``);
* ``nav`` (S nx): the navigation-noise sequence (``--disturbed``): step k's standard-normal
  draws;
* ``thrust-error`` (A + 2 S A): the Gauss-Markov thrust error: w(0) and its driving noise per
  step (``--disturbed``).

(S: MPC steps of the loop, A: thrust-error axes, T: thrusters.) A run's inputs are a pure
function of xi, so a gradient with respect to xi shapes an initial state, a vehicle and a
noise realisation alike. Uniform quantities are mapped through the normal CDF Phi, so the
whole vector is standard normal (the space of FORM and subset simulation).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.stats import norm

from rvdjax.disturbances import Draws
from rvdjax.loop.plant import with_plant

__all__ = ["Component", "Dispersion", "parse_dispersion", "COMPONENTS"]

COMPONENTS = {
    "paper003": "paper 003 Sec. 4 initial states (5 coordinates; 3-D CW families)",
    "x0": "x0:SP,SV[,SA]: normal offsets of the initial state [m, m/s, rad]",
    "mass": "mass:S: the truth's mass m exp(S xi), the guidance keeps m",
    "inertia": "inertia:S: the truth's inertia exp(S xi) (families with torques)",
    "thrust": "thrust:S: thrust magnitude 1 + S xi per force axis (per thruster with thrusters)",
    "misalignment": "misalignment:DEG: thruster direction errors [deg] (with thrusters)",
    "nav": "the navigation-noise sequence (disturbed loops)",
    "thrust-error": "the Gauss-Markov thrust-error sequence and w(0) (disturbed loops)",
}

P003_R = (150.0, 2500.0)  # paper 003 Sec. 4 range [m]
P003_SIGMA_V = 0.5  # [m/s]


@dataclasses.dataclass(frozen=True)
class Component:
    """One component: ``kind``, its numeric arguments and its number of coordinates."""

    kind: str
    args: tuple[float, ...]
    dim: int

    def label(self) -> str:
        if not self.args:
            return self.kind
        return f"{self.kind}:{','.join(f'{a:g}' for a in self.args)}"


@dataclasses.dataclass(frozen=True)
class Dispersion:
    """A parsed dispersion bound to a loop (its shapes): ``apply(xi, x0, params)``."""

    components: tuple[Component, ...]
    mean_motion: float | None = None

    @property
    def dim(self) -> int:
        return sum(c.dim for c in self.components)

    def label(self) -> str:
        return "+".join(c.label() for c in self.components)

    def names(self) -> list[str]:
        """A short name per coordinate (tables, figures)."""
        out = []
        for c in self.components:
            if c.kind == "paper003":
                out += ["p003_range", "p003_bearing", "p003_vx", "p003_vy", "p003_vz"]
            else:
                out += [f"{c.kind}[{i}]" for i in range(c.dim)] if c.dim > 1 else [c.kind]
        return out

    def touches_params(self) -> bool:
        return any(c.kind not in ("paper003", "x0") for c in self.components)

    def apply(self, xi, x0, params, layout):
        """(x0, params) of one run at ``xi`` (dim,) from the nominal ``x0`` and ``params``
        (pure, differentiable in xi)."""
        xi = jnp.asarray(xi)
        x0 = jnp.asarray(x0, xi.dtype)
        draws = {}
        scale = None
        thr = params.plant.thrusters
        i = 0
        for c in self.components:
            z = xi[i : i + c.dim]
            i += c.dim
            if c.kind == "paper003":
                r = P003_R[0] + (P003_R[1] - P003_R[0]) * norm.cdf(z[0])
                ang = 2.0 * jnp.pi * norm.cdf(z[1])
                x, y = r * jnp.cos(ang), r * jnp.sin(ang)
                v = jnp.stack([0.0, -2.0 * self.mean_motion * x, 0.0]) + P003_SIGMA_V * z[2:5]
                x0 = jnp.concatenate([jnp.stack([x, y, jnp.zeros_like(x)]), v])
            elif c.kind == "x0":
                sd = np.zeros(layout.nx)
                sd[list(layout.pos)] = c.args[0]
                sd[list(layout.vel)] = c.args[1]
                if layout.att:
                    sd[list(layout.att)] = c.args[2] if len(c.args) > 2 else 0.0
                x0 = x0 + jnp.asarray(sd) * z
            elif c.kind in ("mass", "inertia"):
                axes = layout.force if c.kind == "mass" else _torque_axes(layout)
                s = (
                    jnp.ones(layout.nu, xi.dtype)
                    .at[jnp.asarray(axes, int)]
                    .set(jnp.exp(-c.args[0] * z[0]))
                )
                scale = s if scale is None else scale * s
            elif c.kind == "thrust":
                if thr is not None:
                    thr = thr._replace(magnitude_error=c.args[0] * z)
                else:
                    s = (
                        jnp.ones(layout.nu, xi.dtype)
                        .at[jnp.asarray(layout.force, int)]
                        .set(1.0 + c.args[0] * z)
                    )
                    scale = s if scale is None else scale * s
            elif c.kind == "misalignment":
                thr = thr._replace(misalignment=jnp.deg2rad(c.args[0]) * z.reshape(-1, 3))
            elif c.kind == "nav":
                draws["nav"] = z.reshape(-1, layout.nx)
            elif c.kind == "thrust-error":
                a = _gm_axes(c)
                draws["gm0"] = z[:a]
                draws["gm"] = z[a:].reshape(-1, a, 2)
        if scale is not None:
            draws["input_scale"] = scale
        if draws:
            d = params.plant.disturbances._replace(draws=Draws(**draws))
            params = with_plant(params, disturbances=d)
        if thr is not None and thr is not params.plant.thrusters:
            params = with_plant(params, thrusters=thr)
        return x0, params

    def batch_apply(self, xis, x0, params, layout):
        """``apply`` over a leading batch axis of ``xis``: (x0s (B, nx), per-run params)."""
        return jax.vmap(lambda z: self.apply(z, x0, params, layout))(xis)


def _torque_axes(layout) -> tuple[int, ...]:
    return tuple(i for i in range(layout.nu) if i not in layout.force)


def _gm_axes(c: Component) -> int:
    return int(c.args[0])


def _args(item: str, kind: str, n_min: int, n_max: int) -> tuple[float, ...]:
    body = item.split(":", 1)[1] if ":" in item else ""
    try:
        args = tuple(float(a) for a in body.split(",") if a.strip())
    except ValueError:
        raise ValueError(f"--dispersion {item}: arguments must be numbers") from None
    if not n_min <= len(args) <= n_max:
        want = n_min if n_min == n_max else f"{n_min} to {n_max}"
        raise ValueError(f"--dispersion {item}: {kind} takes {want} number(s): {COMPONENTS[kind]}")
    if any(not (np.isfinite(a) and a >= 0) for a in args):
        raise ValueError(f"--dispersion {item}: the spreads must be finite and >= 0")
    return args


def parse_dispersion(text: str, scenario, loop, thrusters: bool) -> Dispersion:
    """Parse ``--dispersion`` against a scenario and its loop (shapes, what it flies); a
    ValueError names the component and the allowed values. Nothing is compiled."""
    from rvdjax.dynamics import mean_motion

    lay = scenario.guidance_family.layout
    S = loop.config.n_steps
    comps = []
    n_motion = None
    for raw in str(text).split("+"):
        item = raw.strip()
        kind = item.split(":", 1)[0]
        if kind not in COMPONENTS:
            raise ValueError(
                f"--dispersion: unknown component {kind!r}; allowed: "
                + "; ".join(f"{k} ({v})" for k, v in COMPONENTS.items())
            )
        if any(c.kind == kind for c in comps):
            raise ValueError(f"--dispersion: component {kind!r} given twice")
        if kind == "paper003":
            _args(item, kind, 0, 0)
            if lay.nx != 6 or "altitude_m" not in scenario.physical:
                raise ValueError(
                    f"--dispersion paper003: 3-D CW families only (scenario {scenario.name!r} "
                    f"is {scenario.family!r})"
                )
            n_motion = float(mean_motion(altitude_m=float(scenario.physical["altitude_m"])))
            comps.append(Component(kind, (), 5))
        elif kind == "x0":
            args = _args(item, kind, 2, 3)
            comps.append(Component(kind, args, lay.nx))
        elif kind in ("mass", "inertia"):
            args = _args(item, kind, 1, 1)
            if thrusters:
                raise ValueError(
                    f"--dispersion {kind}: not with --thrusters (use thrust:S, misalignment:DEG)"
                )
            if kind == "inertia" and not _torque_axes(lay):
                raise ValueError(
                    f"--dispersion inertia: family {scenario.family!r} commands no torque"
                )
            comps.append(Component(kind, args, 1))
        elif kind == "thrust":
            args = _args(item, kind, 1, 1)
            n = scenario.thrusters.n if thrusters else len(lay.force)
            comps.append(Component(kind, args, n))
        elif kind == "misalignment":
            args = _args(item, kind, 1, 1)
            if not thrusters:
                raise ValueError("--dispersion misalignment: needs --thrusters")
            comps.append(Component(kind, args, 3 * scenario.thrusters.n))
        elif kind in ("nav", "thrust-error"):
            _args(item, kind, 0, 0)
            if not loop.config.disturbed:
                raise ValueError(f"--dispersion {kind}: needs --disturbed (a noisy loop)")
            if kind == "nav":
                comps.append(Component(kind, (), S * lay.nx))
            else:
                a = scenario.thrusters.n if thrusters else lay.nu
                comps.append(Component(kind, (float(a),), a + 2 * S * a))
    if sum(c.kind in ("paper003", "x0") for c in comps) > 1:
        raise ValueError("--dispersion: paper003 and x0 both set the initial state; pick one")
    return Dispersion(tuple(comps), n_motion)
