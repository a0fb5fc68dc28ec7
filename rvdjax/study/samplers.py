"""Samplers of a study: initial conditions and user distributions, all driven by JAX keys.

A run is reproducible from (study seed, run index): run r of a study is the triple
(sweep point p, initial condition i, replicate j), and its random numbers come from

* initial state: ``fold_in(fold_in(key(seed), 0), i)`` (shared by every point and replicate:
  common random numbers, as paper 003 Ch. 4 flies the same 500 initial states at every sweep
  point);
* varied parameters: ``fold_in(fold_in(fold_in(key(seed), 1), i), j)``, then one stream per
  ``--vary`` entry;
* disturbances (navigation noise, thrust error): ``fold_in(fold_in(fold_in(key(seed), 2), i),
  j)``.
"""

from __future__ import annotations

import dataclasses
import re

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "Dist",
    "parse_dist",
    "draw",
    "initial_key",
    "vary_key",
    "disturbance_key",
    "paper003_initial_state",
    "INITIAL_SAMPLERS",
]

_KINDS = {
    "uniform": 2,  # (low, high)
    "normal": 2,  # (mean, standard deviation)
    "loguniform": 2,  # (low, high), both > 0
    "lognormal": 2,  # (mean, standard deviation) of the logarithm
    "choice": None,  # (v1, v2, ...) equally likely
    "const": 1,  # (value)
}


@dataclasses.dataclass(frozen=True)
class Dist:
    """A scalar distribution: ``kind`` with ``args``; ``op`` "=" replaces the nominal value,
    "+" adds the draw to it, "*" multiplies it by the draw."""

    kind: str
    args: tuple[float, ...]
    op: str = "="

    def __str__(self) -> str:
        prefix = "" if self.op == "=" else self.op
        return f"{prefix}{self.kind}({','.join(f'{a:g}' for a in self.args)})"


_DIST_RE = re.compile(r"^\s*([+*]?)\s*([a-z]+)\s*\((.*)\)\s*$")


def parse_dist(text: str) -> Dist:
    """Parse ``uniform(a,b)``, ``normal(mu,sigma)``, ``loguniform(a,b)``,
    ``lognormal(mu,sigma)``, ``choice(v1,v2,...)``, ``const(v)`` or a bare number; a leading
    ``+`` or ``*`` applies the draw to the nominal value (``+normal(0,10)``, ``*normal(1,0.02)``).
    """
    text = text.strip()
    try:
        return Dist("const", (float(text),))
    except ValueError:
        pass
    m = _DIST_RE.match(text)
    if not m:
        raise ValueError(
            f"cannot read distribution {text!r}; use e.g. uniform(0.1,0.2), normal(14,0.5), "
            "+normal(0,10), *normal(1,0.02), loguniform(1,100), choice(20,30,40) or a number"
        )
    op, kind, body = m.group(1) or "=", m.group(2), m.group(3)
    if kind not in _KINDS:
        raise ValueError(f"unknown distribution {kind!r}; known: {', '.join(_KINDS)}")
    try:
        args = tuple(float(a) for a in body.split(",") if a.strip())
    except ValueError:
        raise ValueError(f"distribution {text!r}: arguments must be numbers") from None
    need = _KINDS[kind]
    if need is not None and len(args) != need:
        raise ValueError(f"{kind} takes {need} argument(s), got {len(args)} in {text!r}")
    if kind == "choice" and not args:
        raise ValueError(f"choice needs at least one value: {text!r}")
    if kind in ("uniform", "loguniform") and not args[0] < args[1]:
        raise ValueError(f"{kind}(low, high) needs low < high, got {text!r}")
    if kind == "loguniform" and args[0] <= 0:
        raise ValueError(f"loguniform needs low > 0, got {text!r}")
    if kind in ("normal", "lognormal") and args[1] < 0:
        raise ValueError(f"{kind}(mean, sigma) needs sigma >= 0, got {text!r}")
    return Dist(kind, args, op)


def draw(dist: Dist, key, nominal):
    """A draw of ``dist`` applied to ``nominal``: one independent draw per element of
    ``nominal`` (a scalar or an array)."""
    a = dist.args
    nominal = jnp.asarray(nominal, dtype=float)
    shape = nominal.shape
    if dist.kind == "uniform":
        v = jax.random.uniform(key, shape, minval=a[0], maxval=a[1])
    elif dist.kind == "normal":
        v = a[0] + a[1] * jax.random.normal(key, shape)
    elif dist.kind == "loguniform":
        v = jnp.exp(jax.random.uniform(key, shape, minval=np.log(a[0]), maxval=np.log(a[1])))
    elif dist.kind == "lognormal":
        v = jnp.exp(a[0] + a[1] * jax.random.normal(key, shape))
    elif dist.kind == "choice":
        v = jnp.asarray(a)[jax.random.randint(key, shape, 0, len(a))]
    else:
        v = jnp.asarray(a[0])
    if dist.op == "+":
        return nominal + v
    if dist.op == "*":
        return nominal * v
    return v * jnp.ones_like(nominal)


def _stream(seed: int, stream: int):
    return jax.random.fold_in(jax.random.key(seed), stream)


def initial_key(seed: int, ic):
    """Key of initial condition ``ic`` (traced or not)."""
    return jax.random.fold_in(_stream(seed, 0), ic)


def vary_key(seed: int, ic, replicate):
    return jax.random.fold_in(jax.random.fold_in(_stream(seed, 1), ic), replicate)


def disturbance_key(seed: int, ic, replicate):
    """The run's PRNG key of the closed loop (navigation noise, thrust error)."""
    return jax.random.fold_in(jax.random.fold_in(_stream(seed, 2), ic), replicate)


def paper003_initial_state(
    key, n_rad_s, r_min_m: float = 150.0, r_max_m: float = 2500.0, sigma_v_m_s: float = 0.5
):
    """Paper 003 Sec. 4 initial condition (CW LVLH: x radial, y along-track, z cross-track).

    Range uniform in [r_min, r_max] (0.15-2.5 km); velocity = the natural no-drift relative
    velocity plus N(0, sigma_v) per axis (0.5 m/s). The thesis is silent on the direction:
    rvdjax draws the bearing uniformly in the orbital plane (its Fig. 4.1 shows the points in
    the x-y plane, by quadrant) with z = 0, and takes the no-drift velocity of CW as
    (0, -2 n x, 0) (the secular along-track drift vanishes when dy/dt = -2 n x; the nominal
    thesis state (140, -1580, 60) m, (-0.90, -0.32, 0) m/s satisfies it).
    """
    k_r, k_a, k_v = jax.random.split(key, 3)
    r = jax.random.uniform(k_r, (), minval=r_min_m, maxval=r_max_m)
    ang = jax.random.uniform(k_a, (), minval=0.0, maxval=2.0 * jnp.pi)
    x, y = r * jnp.cos(ang), r * jnp.sin(ang)
    v = jnp.stack([0.0, -2.0 * n_rad_s * x, 0.0]) + sigma_v_m_s * jax.random.normal(k_v, (3,))
    return jnp.concatenate([jnp.stack([x, y, 0.0]), v])


# name -> (description, needs CW mean motion). "nominal" keeps the scenario's x0.
INITIAL_SAMPLERS = {
    "nominal": "the scenario's initial state (then --vary x0...)",
    "paper003": "paper 003 Sec. 4: range U(0.15, 2.5) km in the orbital plane, no-drift "
    "velocity + N(0, 0.5 m/s) per axis (3-D CW families)",
}
