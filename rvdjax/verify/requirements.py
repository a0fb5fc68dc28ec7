"""Requirements as signed margins of one run: satisfied when the margin is >= 0.

Each requirement has two values per run:

* the **exact** margin, judged on the truth from the run's :class:`~rvdjax.loop.Metrics`
  (what the batch engine returns), used to decide pass or fail;
* a **smooth** margin from the run's step records (:class:`~rvdjax.loop.StepInfo`, what
  :func:`rvdjax.loop.fly` returns), used for gradients. It is a lower bound of the exact one
  where the exact one is a minimum (soft-min), so a smooth margin >= 0 implies a pass.

The requirements (``--requirement``; ``NAME``, ``NAME>=X`` or ``NAME<=X``):

| name | unit | exact margin |
| --- | --- | --- |
| ``keep-out[>=X]`` | m | smallest clearance of the keep-out zones over the truth, minus X |
| ``entry-cone[>=X]`` | m | smallest distance inside the entry (docking) cone, minus X |
| ``overshoot[>=X]`` | m | smallest distance before the overshoot plane, minus X |
| ``contact-speed<=V`` | m/s | V minus the truth's speed at docking (V when it never docks) |
| ``time-to-dock<=T`` | s | T minus the time to dock (-T when it never docks) |
| ``effort<=B`` | * | B minus the headline effort (the paper's delta-v or impulse) |
| ``docks`` | - | +1 when the run docks, -1 when it does not |

The keep-out clearance is taken at the samples and between them (the families' sub-samples);
X is 0 by default (X < 0: a breach deeper than -X fails).

Smooth margins:

* zones (keep-out, entry-cone, overshoot): ``-tau log sum_k exp(-g_k / tau)`` over the rows
  and samples g_k [m] of the run (a soft-min, <= min g_k, and within tau log(count) of it);
  ``tau`` is the temperature (default 0.3 % of the initial distance to the target, stated in
  the output: a narrow soft-min that stays within a few tau of the exact margin, so that the
  worst-case search can step by the exact margin's value and the smooth margin's slope);
* contact speed: the exact value (the speed at docking is smooth in the inputs between
  changes of the docking step);
* time to dock: T - sum_k dt_k d_k / (d_k + d0), d_k the distance left to the docking region
  at step k (the family's ``dock_error``) and d0 = 1 % of its initial value;
* effort: B minus the effort with smoothed norms (:mod:`rvdjax.tune.loss`);
* docks: 1 - 2 d_end / (d_end + d0), d_end the distance left to the docking region at the
  end of the run.

Requirements of one unit compose by min: ``keep-out,entry-cone``.
"""

from __future__ import annotations

import dataclasses
import re

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["Requirement", "Composite", "parse_requirement", "REQUIREMENTS", "zone_blocks"]

# requirement -> (unit, block names that stand for it in any family, default comparison)
ZONES = {
    "keep-out": ("keep_out", "target_keep_out", "obstacles"),
    "entry-cone": ("entry_cone", "docking_cone"),
    "overshoot": ("overshoot",),
}
REQUIREMENTS = {
    "keep-out": ("m", ">=", 0.0, "clearance of the keep-out zones, between samples too"),
    "entry-cone": ("m", ">=", 0.0, "distance inside the entry (docking) cone"),
    "overshoot": ("m", ">=", 0.0, "distance before the overshoot plane"),
    "contact-speed": ("m/s", "<=", None, "speed at docking"),
    "time-to-dock": ("s", "<=", None, "time to dock"),
    "effort": ("effort", "<=", None, "headline effort (delta-v [m/s] or impulse [N s])"),
    "docks": ("-", None, None, "+1 docked, -1 not"),
}
SOFT_FRACTION = 0.01  # d0 of the soft docking indicator: 1 % of the initial distance
# default tau: 0.3 % of the initial distance to the target (5 m on thesis-vbar, where the
# smooth margin then sits 4-9 m below the exact one; at 10 %, 300-450 m below)
TEMPERATURE_FRACTION = 0.003

_RE = re.compile(r"^\s*([a-z-]+)\s*(?:(>=|<=)\s*([-+0-9.eE]+))?\s*$")


def zone_blocks(name: str, available) -> tuple[str, ...]:
    """The truth-block names of ``available`` that stand for zone requirement ``name``."""
    return tuple(b for b in ZONES[name] if b in available)


@dataclasses.dataclass(frozen=True)
class Requirement:
    """One requirement: ``name``, its threshold and (zones) the block names it reads."""

    name: str
    threshold: float
    blocks: tuple[str, ...] = ()

    @property
    def unit(self) -> str:
        return REQUIREMENTS[self.name][0]

    def label(self) -> str:
        op = REQUIREMENTS[self.name][1]
        if op is None:
            return self.name
        if op == ">=" and self.threshold == 0.0:
            return self.name
        return f"{self.name}{op}{self.threshold:g}"

    # -------------------------------------------------------------------- exact (Metrics)

    def exact(self, metrics, effort_key: str):
        """Exact margin(s) of runs from their Metrics (any leading shape)."""
        if self.name in ZONES:
            m = jnp.min(jnp.stack([jnp.asarray(metrics.margins_m[b]) for b in self.blocks]), 0)
            return m - self.threshold
        docked = jnp.asarray(metrics.docked)
        if self.name == "contact-speed":
            return jnp.where(docked, self.threshold - metrics.contact_speed_m_s, self.threshold)
        if self.name == "time-to-dock":
            return jnp.where(docked, self.threshold - metrics.time_to_dock_s, -self.threshold)
        if self.name == "effort":
            return self.threshold - jnp.asarray(getattr(metrics, effort_key))
        return jnp.where(docked, 1.0, -1.0)  # docks

    # -------------------------------------------------------------------- smooth (StepInfo)

    def smooth(self, loop, params, infos, metrics, effort_key: str, tau):
        """Smooth margin of one run from its step records (module docstring)."""
        if self.name in ZONES:
            g = jnp.concatenate([infos.margins[b] for b in self.blocks], axis=-1)  # (S, m)
            ok = infos.active[:, None] & jnp.isfinite(g)
            g = jnp.where(ok, g, 0.0)
            # a soft-min over the judged samples; an empty set gives +inf -> a large margin
            z = jnp.where(ok, -g / tau, -jnp.inf)
            zmax = jax.lax.stop_gradient(jnp.max(z))
            zmax = jnp.where(jnp.isfinite(zmax), zmax, 0.0)
            lse = zmax + jnp.log(jnp.sum(jnp.where(ok, jnp.exp(z - zmax), 0.0)))
            soft = -tau * lse
            return jnp.where(jnp.any(ok), soft, 1e6) - self.threshold
        if self.name == "contact-speed":
            return jnp.where(
                metrics.docked, self.threshold - metrics.contact_speed_m_s, self.threshold
            )
        if self.name == "effort":
            from rvdjax.tune.loss import _effort

            return self.threshold - _effort(loop, params, infos, effort_key)
        d = _dock_distances(loop, params, infos)
        d0 = SOFT_FRACTION * jax.lax.stop_gradient(d[0])
        if self.name == "time-to-dock":
            return self.threshold - jnp.sum(infos.dt * d / (d + d0))
        last = jnp.maximum(jnp.sum(infos.active) - 1, 0)
        d_end = d[last]
        return 1.0 - 2.0 * d_end / (d_end + d0)  # docks


def _dock_distances(loop, params, infos):
    fam, fc = loop.family, loop.config.family_config
    return jax.vmap(lambda g, x, t: fam.dock_error(params, fc, g, x, t))(
        infos.guidance, infos.x, infos.t
    )


@dataclasses.dataclass(frozen=True)
class Composite:
    """Requirements of one unit composed by min (a single requirement is a composite of
    one)."""

    parts: tuple[Requirement, ...]

    @property
    def unit(self) -> str:
        return self.parts[0].unit

    def label(self) -> str:
        return ",".join(p.label() for p in self.parts)

    @property
    def is_zone(self) -> bool:
        return all(p.name in ZONES for p in self.parts)

    def exact(self, metrics, effort_key: str):
        return jnp.min(jnp.stack([p.exact(metrics, effort_key) for p in self.parts]), 0)

    def smooth(self, loop, params, infos, metrics, effort_key: str, tau):
        vals = [p.smooth(loop, params, infos, metrics, effort_key, tau) for p in self.parts]
        if len(vals) == 1:
            return vals[0]
        v = jnp.stack(vals)
        return -tau * jax.nn.logsumexp(-v / tau)


def _allowed() -> str:
    return ", ".join(
        n + ("" if op is None else (f"[{op}X]" if default is not None else f"{op}X"))
        for n, (_, op, default, _) in REQUIREMENTS.items()
    )


def parse_requirement(text: str, available_blocks, can_dock: bool) -> Composite:
    """``"keep-out"``, ``"keep-out>=-5"``, ``"contact-speed<=0.1"``, ``"keep-out,entry-cone"``
    -> :class:`Composite`, checked against what the family computes (``available_blocks``:
    its truth-block names; ``can_dock``: it has a docking region). ValueError naming the
    requirement and the allowed values."""
    parts = []
    for item in str(text).split(","):
        m = _RE.match(item)
        if not m or m.group(1) not in REQUIREMENTS:
            raise ValueError(
                f"--requirement: unknown requirement {item.strip()!r}; allowed: {_allowed()}"
            )
        name, op, value = m.group(1), m.group(2), m.group(3)
        unit, want, default, _ = REQUIREMENTS[name]
        if want is None and op is not None:
            raise ValueError(f"--requirement {item.strip()}: {name} takes no threshold")
        if op is not None and op != want:
            raise ValueError(f"--requirement {item.strip()}: write {name}{want}X")
        if want is not None and op is None and default is None:
            raise ValueError(f"--requirement {name} needs a bound: {name}{want}X ({unit})")
        threshold = float(value) if value is not None else (default or 0.0)
        if not np.isfinite(threshold):
            raise ValueError(f"--requirement {item.strip()}: the threshold must be finite")
        if name in ("contact-speed", "time-to-dock") and threshold <= 0:
            raise ValueError(f"--requirement {item.strip()}: the bound must be > 0 {unit}")
        blocks = ()
        if name in ZONES:
            blocks = zone_blocks(name, available_blocks)
            if not blocks:
                raise ValueError(
                    f"--requirement {name}: this family has no such zone; it computes: "
                    f"{', '.join(_computable(available_blocks, can_dock))}"
                )
        elif not can_dock and name in ("contact-speed", "time-to-dock", "docks"):
            raise ValueError(
                f"--requirement {name}: this family has no docking region; it computes: "
                f"{', '.join(_computable(available_blocks, can_dock))}"
            )
        parts.append(Requirement(name, threshold, blocks))
    units = {p.unit for p in parts}
    if len(units) > 1:
        raise ValueError(
            f"--requirement {text}: compose requirements of one unit only (got "
            f"{', '.join(sorted(units))})"
        )
    return Composite(tuple(parts))


def _computable(available_blocks, can_dock: bool) -> list[str]:
    out = [n for n in ZONES if zone_blocks(n, available_blocks)]
    out += ["effort<=B"]
    if can_dock:
        out += ["contact-speed<=V", "time-to-dock<=T", "docks"]
    return out
