"""The smooth closed-loop surrogate the tuner minimises (DESIGN §7: discrete events).

Docking time, the docked flag, phase switches and holding-radius shrinks are piecewise
constant in the parameters: their derivative is zero almost everywhere. The tuner therefore
minimises a surrogate built from continuous quantities of the flown trajectory, and every
result is judged with the exact metrics (:class:`rvdjax.loop.Metrics`). Per run:

    L = w_e E / E_ref + w_t T / T_ref + w_m M

* E, the effort: the scenario's headline effort (delta-v [m/s] or impulse [N s], L1 or L2 as
  the paper counts it, :func:`rvdjax.study.effort_metric`) summed over the steps flown, with
  the norms smoothed, sqrt(|v|^2 + eps^2) - eps (eps = 1e-9), so that a zero input has a
  finite derivative.
* T, a soft time to dock [s]: sum_k dt_k s(d_k), with d_k the distance left to the docking
  region at the start of step k (the family's ``dock_error``: a smooth max(0, distance -
  docking tolerance), so a run that docks one step earlier or later changes T by almost
  nothing) and s(d) = log(1 + d / d0) / log(1 + d_0 / d0),
  d_0 the run's initial distance and d0 = d_0 / 100. s falls from 1 at the start to 0 at the
  port on a logarithmic scale, so every stretch of the approach (the long drift and the last
  metre alike) pulls, and a run that has docked adds nothing (dt = 0 once finished). A run
  that has not docked by the last step keeps adding dt s(d): the surrogate also penalises
  not docking in time. This is rvdjax's choice, not a paper's.
* M, a margin penalty: sum over the steps and the rows of the family's hard truth blocks
  (keep-out, cones, overshoot, velocity bounds; the same rows as ``max_violation_m``) of
  (max(0, -g) / d0)^2, g the row's truth slack [m]: zero while every constraint holds.
* E_ref and T_ref are the means of E and T over the training set at the hand-tuned values
  (constants), so L = w_e + w_t at the start and the weights read as relative trade-offs.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from rvdjax.loop.kernel import Loop, StepInfo

__all__ = ["LossWeights", "parse_loss", "run_terms", "combine", "SCALE_FRACTION", "EPS"]

EPS = 1e-9  # smoothing of the effort norms [units of the effort]
SCALE_FRACTION = 0.01  # d0 = SCALE_FRACTION * initial distance to docking


@dataclasses.dataclass(frozen=True)
class LossWeights:
    """Weights of the surrogate's terms (module docstring): effort, soft time to dock,
    constraint-margin penalty. All >= 0, not all zero."""

    effort: float = 1.0
    time: float = 1.0
    margin: float = 10.0

    def __post_init__(self):
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if not (isinstance(v, (int, float)) and v >= 0 and v == v and v != float("inf")):
                raise ValueError(f"--loss {f.name} must be a finite number >= 0, got {v!r}")
        if self.effort == 0 and self.time == 0:
            raise ValueError("--loss: effort and time cannot both be 0")

    def array(self):
        """(effort, time, margin) as an array (a traced argument: no recompile per weight)."""
        return jnp.asarray([self.effort, self.time, self.margin], float)

    def label(self) -> str:
        return f"effort={self.effort:g},time={self.time:g},margin={self.margin:g}"


def parse_loss(text: str | None) -> LossWeights:
    """``"effort=1,time=0.5,margin=10"`` (any subset; the rest keep their defaults)."""
    if text is None or not text.strip():
        return LossWeights()
    out = {}
    names = [f.name for f in dataclasses.fields(LossWeights)]
    for part in text.split(","):
        if "=" not in part:
            raise ValueError(f"--loss: expected NAME=WEIGHT items, got {part!r} in {text!r}")
        k, v = (s.strip() for s in part.split("=", 1))
        if k not in names:
            raise ValueError(f"--loss: unknown term {k!r}; terms: {', '.join(names)}")
        try:
            out[k] = float(v)
        except ValueError:
            raise ValueError(f"--loss {k}: {v!r} is not a number") from None
    return LossWeights(**out)


def _smooth_l2(v):
    return jnp.sqrt(jnp.sum(v * v, axis=-1) + EPS * EPS) - EPS


def _smooth_l1(v):
    return jnp.sum(jnp.sqrt(v * v + EPS * EPS) - EPS, axis=-1)


def _effort(loop: Loop, params, infos: StepInfo, effort_key: str):
    """The headline effort of the flown steps (smoothed norms), as the metrics count it."""
    lay = loop.family.layout
    idx = jnp.asarray(lay.force, int)
    u = infos.u[:, idx]
    act = infos.active[:, None]
    if lay.input == "force":
        imp = u * infos.dt[:, None]
        dv = imp / params.plant.mass
    else:  # impulsive: u is a delta-v applied at the step start
        dv = jnp.where(act, u, 0.0)
        imp = dv * params.plant.mass
    if effort_key == "delta_v_m_s":
        per = _smooth_l2(imp) / params.plant.mass if lay.input == "force" else _smooth_l2(dv)
    elif effort_key == "effort_l1_N_s":
        per = _smooth_l1(imp)
    elif effort_key == "total_impulse_N_s":
        per = _smooth_l2(imp)
    elif effort_key == "delta_v_l1_m_s":
        per = _smooth_l1(dv)
    else:
        raise ValueError(f"unknown effort metric {effort_key!r}")
    return jnp.sum(jnp.where(infos.active, per, 0.0))


def _hard_names(loop: Loop, params, infos: StepInfo) -> list[str]:
    g0 = jax.tree.map(lambda a: a[0], infos.guidance)
    blocks = loop.family.truth_blocks(params, loop.config.family_config, g0, infos.x[0], infos.t[0])
    return [b.name for b in blocks if b.kind == "hard"]


def run_terms(loop: Loop, params, infos: StepInfo, effort_key: str):
    """(E, T, M) of one run from its step records (module docstring; leading axis = step)."""
    fam, fc = loop.family, loop.config.family_config
    if fam.dock_error is None:
        raise ValueError(f"family {fam.name!r} has no dock_error: it cannot be tuned")
    d = jax.vmap(lambda g, x, t: fam.dock_error(params, fc, g, x, t))(
        infos.guidance, infos.x, infos.t
    )
    d_start = jax.lax.stop_gradient(d[0])
    d0 = SCALE_FRACTION * d_start
    s = jnp.log1p(d / d0) / jnp.log1p(1.0 / SCALE_FRACTION)
    T = jnp.sum(infos.dt * s)
    E = _effort(loop, params, infos, effort_key)
    M = jnp.zeros((), d.dtype)
    for name in _hard_names(loop, params, infos):
        g = infos.margins[name]  # (steps, m) truth slacks [m], +inf where inactive
        viol = jnp.maximum(-g, 0.0) / d0
        M = M + jnp.sum(jnp.where(infos.active[:, None], viol * viol, 0.0))
    return E, T, M


def combine(weights, E, T, M, E_ref, T_ref):
    """L per run (module docstring); a non-finite run counts 0 (it is reported by status).
    ``weights``: :class:`LossWeights` or a traced (3,) array (effort, time, margin)."""
    w = weights.array() if isinstance(weights, LossWeights) else weights
    L = w[0] * E / E_ref + w[1] * T / T_ref + w[2] * M
    return jnp.where(jnp.isfinite(L), L, 0.0)
