"""The tuned parameters: which values, their transforms to unconstrained numbers, and the
map back into a family's traced parameters (DESIGN §7).

The optimiser works on theta, an unconstrained dict of arrays. Each named value v has a
transform that keeps it valid whatever theta is: weights, penalties, sample times and margins
are positive (v = exp(theta): log-diagonals of Q and R, as DESIGN §7 asks), gamma lies in
(0, 1) (v = sigmoid(theta)). What each family offers is its :class:`~rvdjax.loop.family.
Tuning` table; ``kappa`` (paper mode's fixed barrier weight, a traced solver parameter) is
offered by every family in paper mode. Fields derived from tuned values (the DARE terminal
weight from Q and R, the discrete model from Ts) are recomputed inside the map, so their
derivatives flow too.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from rvdjax.loop.family import Tunable
from rvdjax.solver import SolverParams

__all__ = ["KAPPA", "ParameterSpace", "parse_names", "tunables_of"]

KAPPA = Tunable(
    "paper-mode barrier weight kappa (paper 000 Sec. IV.A: 0.05)",
    get=lambda sp: sp.kappa,
    set=lambda sp, v: sp._replace(kappa=v),
)


def tunables_of(scenario, mode: str) -> dict[str, Tunable]:
    """{name: Tunable} the scenario's family offers in solver ``mode``."""
    fam = scenario.guidance_family
    if fam.tuning is None:
        raise ValueError(f"family {fam.name!r} of {scenario.name!r} declares no tunable values")
    out = dict(fam.tuning.tunables)
    if mode == "paper":
        out["kappa"] = KAPPA
    return out


def parse_names(text, scenario, mode: str) -> tuple[str, ...]:
    """``"Q,R,gamma"`` -> ("Q", "R", "gamma"), checked against what the family offers."""
    names = tuple(n.strip() for n in (text.split(",") if isinstance(text, str) else text))
    names = tuple(n for n in names if n)
    offered = tunables_of(scenario, mode)
    if not names:
        raise ValueError(f"--params: name at least one of {', '.join(offered)}")
    for n in names:
        if n not in offered:
            extra = " (kappa only in paper mode: --mode paper)" if n == "kappa" else ""
            raise ValueError(
                f"--params: {n!r} is not tunable for {scenario.name!r} in {mode} mode{extra}; "
                f"choose from {', '.join(offered)}"
            )
    if len(set(names)) != len(names):
        raise ValueError(f"--params: a name is given twice in {','.join(names)}")
    return names


def _to_theta(t: Tunable, v):
    if t.transform == "log":
        return jnp.log(v)
    lo, hi = t.bounds
    s = (v - lo) / (hi - lo)
    return jnp.log(s) - jnp.log1p(-s)


def _from_theta(t: Tunable, th):
    if t.transform == "log":
        return jnp.exp(th)
    lo, hi = t.bounds
    return lo + (hi - lo) * jax.nn.sigmoid(th)


@dataclasses.dataclass(frozen=True, eq=False)
class ParameterSpace:
    """The tuned values of one scenario: names, their hand (paper) values and transforms.

    Attributes:
        names: the tuned names (static).
        tunables: {name: Tunable}.
        hand: {name: NumPy array} the scenario's own (hand-tuned) values.
        derive: the family's ``Tuning.derive``.
    """

    names: tuple[str, ...]
    tunables: dict
    hand: dict
    derive: object

    @classmethod
    def of(cls, scenario, names, params, sp: SolverParams, mode: str) -> ParameterSpace:
        offered = tunables_of(scenario, mode)
        names = parse_names(names, scenario, mode)
        tun = {n: offered[n] for n in names}
        hand = {n: np.asarray(t.get(sp if n == "kappa" else params), float) for n, t in tun.items()}
        return cls(names, tun, hand, scenario.guidance_family.tuning.derive)

    # ------------------------------------------------------------------ transforms

    def theta(self, values: dict | None = None) -> dict:
        """Unconstrained theta of ``values`` (default: the hand values)."""
        values = self.hand if values is None else values
        return {n: _to_theta(self.tunables[n], jnp.asarray(values[n], float)) for n in self.names}

    def values(self, theta: dict) -> dict:
        """The natural values of ``theta`` (jittable)."""
        return {n: _from_theta(self.tunables[n], theta[n]) for n in self.names}

    def apply(self, params, sp: SolverParams, values: dict):
        """(params, solver params) with ``values`` set and the derived fields recomputed
        (pure, jittable, differentiable)."""
        derived = tuple(n for n in self.names if self.tunables[n].derived)
        for n in self.names:
            v = jnp.asarray(values[n], float)
            if n == "kappa":
                sp = self.tunables[n].set(sp, v)
            else:
                params = self.tunables[n].set(params, v)
        return self.derive(params, derived), sp

    # ------------------------------------------------------------------ checks and files

    def check_values(self, values: dict, source: str) -> dict:
        """Shapes, finiteness and bounds of natural values read from a file (ValueError naming
        the value and the allowed range); NumPy arrays back."""
        out = {}
        for n in self.names:
            if n not in values:
                raise ValueError(f"{source}: no value for {n!r} (tuned: {', '.join(self.names)})")
            v = np.asarray(values[n], float)
            if v.shape != self.hand[n].shape:
                raise ValueError(
                    f"{source}: {n} must have shape {self.hand[n].shape}, got {v.shape}"
                )
            lo, hi = self.tunables[n].bounds
            if not (np.all(np.isfinite(v)) and np.all(v > lo) and np.all(v < hi)):
                rng = f"({lo:g}, {'inf' if math.isinf(hi) else f'{hi:g}'})"
                raise ValueError(f"{source}: every entry of {n} must lie in {rng}, got {v}")
            out[n] = v
        extra = set(values) - set(self.names)
        if extra:
            raise ValueError(f"{source}: unknown values {sorted(extra)}")
        return out

    def describe(self) -> dict:
        """{name: {description, transform, shape}} for the output files."""
        return {
            n: {
                "description": t.description,
                "transform": t.transform,
                "shape": list(self.hand[n].shape),
            }
            for n, t in self.tunables.items()
        }

    @property
    def size(self) -> int:
        return int(sum(v.size for v in self.hand.values()))
