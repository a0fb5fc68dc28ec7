"""The set-up of a tuning: :class:`TuneSpec` (the run as plain data), the training and held-out
sets (study samplers' runs, :func:`rvdjax.study.run_inputs`) and :class:`Tuner`, the compiled
surrogate loss and its gradient over a ``vmap`` of :func:`rvdjax.loop.fly`, shared by the runs of
:mod:`rvdjax.tune.trainer`.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from rvdjax.loop import fly
from rvdjax.tune.loss import LossWeights, combine, run_terms
from rvdjax.tune.parameters import ParameterSpace

__all__ = ["TuneSpec", "Tuner", "tuner_for", "heldout_summary", "DEFAULT_VARY_SD"]

DEFAULT_VARY_SD = 0.05  # default sets: each position component of x0 times N(1, 0.05)


@dataclasses.dataclass(frozen=True)
class TuneSpec:
    """A tuning run as plain data.

    Attributes:
        scenario: scenario name.
        params: the tuned names (the family's :class:`~rvdjax.loop.family.Tuning`; "kappa" in
            paper mode).
        loss: the surrogate's weights.
        train, heldout: maneuvers in the training and held-out sets.
        steps: optimiser steps (the random search gets steps + 1 evaluations, as many as the
            gradient run).
        lr: Adam's initial step size on theta (log scale for weights: 0.05 = 5 %).
        seed: training set seed (held-out: seed + 1; random search: seed + 2).
        mode, truth, disturbed, nav_filter: the closed loop (ideal forces: see
            ``judge_thrusters``).
        initial: initial-state sampler ("nominal" or "paper003").
        vary: ((name, distribution), ...) as ``rvdjax study --vary``; default: each position
            component of x0 multiplied by N(1, 0.05).
        n_steps: MPC steps per maneuver (default: the scenario's).
        time_limit_s: a maneuver not docked by then ends [s] (default: no limit).
        random_search: also run the derivative-free baseline.
        search_sigma: the random search's spread on theta.
        remat: ``jax.checkpoint`` the closed-loop step (bounded memory, ~1 more forward pass).
        clip: global-norm clip of the gradient on theta.
        judge_thrusters: also judge every tuning on the held-out maneuvers flown with the
            scenario's thrusters. The gradients always come from the ideal-force plant: the
            pulse train is piecewise constant in the parameters (its derivative is zero almost
            everywhere), so a thruster plant gives no gradient to follow.
    """

    scenario: str
    params: tuple = ("Q", "R")
    loss: LossWeights = LossWeights()
    train: int = 16
    heldout: int = 64
    steps: int = 30
    lr: float = 0.05
    seed: int = 0
    mode: str = "accurate"
    truth: str = "linear"
    disturbed: bool = False
    nav_filter: bool = False
    initial: str = "nominal"
    vary: tuple | None = None
    n_steps: int | None = None
    time_limit_s: float | None = None
    random_search: bool = True
    search_sigma: float = 0.3
    remat: bool = True
    clip: float = 1.0
    judge_thrusters: bool = False

    def __post_init__(self):
        for name in ("train", "heldout"):
            v = getattr(self, name)
            if not (isinstance(v, (int, np.integer)) and v >= 1):
                raise ValueError(f"--{name} must be an integer >= 1, got {v!r}")
        if not (isinstance(self.steps, (int, np.integer)) and self.steps >= 0):
            raise ValueError(f"--steps must be an integer >= 0, got {self.steps!r}")
        for name in ("lr", "search_sigma", "clip"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0 < v < float("inf")):
                raise ValueError(f"{name} must be a number > 0, got {v!r}")
        if self.n_steps is not None and not isinstance(self.n_steps, (int, np.integer)):
            raise ValueError(f"n_steps must be an integer >= 1, got {self.n_steps!r}")
        self.flight_options()  # mode, truth, nav_filter, n_steps, time_limit_s
        if isinstance(self.params, str):
            object.__setattr__(self, "params", tuple(self.params.split(",")))
        object.__setattr__(self, "params", tuple(str(p).strip() for p in self.params))

    def flight_options(self, thrusters: bool = False):
        """The :class:`~rvdjax.scenarios.flight.FlightOptions` of the tuned loop (ideal forces;
        ``thrusters``: the judging loop of ``judge_thrusters``)."""
        from rvdjax.scenarios.flight import FlightOptions

        return FlightOptions.of(self, thrusters=thrusters, seed=0)  # (the runs' keys: seed)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["loss"] = dataclasses.asdict(self.loss)
        return d


def _default_vary(scenario) -> tuple:
    pos = scenario.guidance_family.layout.pos
    return tuple((f"x0[{i}]", f"*normal(1,{DEFAULT_VARY_SD:g})") for i in pos)


def _run_set(spec: TuneSpec, scenario, n: int, seed: int):
    """(x0s (n, nx), keys (n,)) of n runs of a study with this seed."""
    from rvdjax.study.runner import run_inputs
    from rvdjax.study.spec import StudySpec

    vary = _default_vary(scenario) if spec.vary is None else spec.vary
    study = StudySpec(
        kind="montecarlo",
        scenario=scenario.name,
        n_initial=n,
        seed=seed,
        initial=spec.initial,
        vary=vary,
        mode=spec.mode,
        disturbed=spec.disturbed,
        nav_filter=spec.nav_filter,
    )
    study.validate(scenario)
    for name, _ in study.vary:
        if not name.startswith("x0"):
            raise ValueError(f"--vary {name}: tuning draws initial states only (x0, x0[k])")
    rs = run_inputs(study, scenario, np.arange(n))
    return jnp.asarray(rs.x0), rs.keys


def _mean_finite(a) -> float | None:
    a = np.asarray(a, float)
    a = a[np.isfinite(a)]
    return float(a.mean()) if a.size else None


def heldout_summary(metrics, effort_key: str, loss=None) -> dict:
    """Exact held-out figures: mean effort, mean time to dock (docked runs), docked fraction,
    largest truth violation; plus the surrogate loss when given."""
    docked = np.asarray(metrics.docked, bool)
    eff = np.asarray(getattr(metrics, effort_key), float)
    out = {
        "effort": _mean_finite(eff),
        "effort_metric": effort_key,
        "effort_std": float(np.std(eff[np.isfinite(eff)])) if np.isfinite(eff).any() else None,
        "time_to_dock_s": _mean_finite(np.where(docked, metrics.time_to_dock_s, np.nan)),
        "docked_fraction": float(docked.mean()),
        "max_violation_m": float(np.max(np.asarray(metrics.max_violation_m, float))),
    }
    if loss is not None:
        out["loss"] = float(np.mean(loss))
    return out


_TUNERS: dict = {}


def tuner_for(spec: TuneSpec) -> Tuner:
    """The :class:`Tuner` of ``spec``, shared with earlier specs that differ only in what is
    traced (loss weights, sets, steps, step size, seeds): a trade-off curve compiles once."""
    key = (
        spec.scenario,
        tuple(spec.params),
        spec.mode,
        spec.disturbed,
        spec.nav_filter,
        spec.n_steps,
        spec.remat,
    )
    if key not in _TUNERS:
        _TUNERS.clear()  # one set-up at a time: compiled programs hold memory
        _TUNERS[key] = Tuner(spec)
    return _TUNERS[key]


class Tuner:
    """The compiled pieces of one tuning set-up (shared by the gradient run, the random
    search and the evaluations): ``terms(theta, x0s, keys)`` and ``value_and_grad(theta,
    x0s, keys, refs, weights)``; the loss weights and the reference scales are traced."""

    def __init__(self, spec: TuneSpec, settings=None, solver_params=None):
        """``settings``, ``solver_params``: override the scenario's solver settings and traced
        solver parameters of ``spec.mode`` (e.g. paper mode iterated to convergence)."""
        from rvdjax.scenarios import get_scenario
        from rvdjax.study.runner import effort_metric

        self.spec = spec
        sc = get_scenario(spec.scenario)
        self.scenario = sc
        flight = sc.flight(spec.flight_options(), settings=settings)
        loop, params = flight.loop, flight.params
        self.loop = loop
        self.params = params
        self.sp = flight.solver_params if solver_params is None else solver_params
        self.space = ParameterSpace.of(sc, spec.params, params, self.sp, spec.mode)
        self.effort_key = effort_metric(sc)
        space, effort_key = self.space, self.effort_key

        def batch_terms(theta, x0s, keys, remat):
            p, sp = space.apply(params, self.sp, space.values(theta))

            def one(x, k):
                infos, m = fly(loop, p, x, k, sp, remat=remat)
                return run_terms(loop, p, infos, effort_key), m

            return jax.vmap(one)(x0s, keys)

        def batch_loss(theta, x0s, keys, refs, weights):
            (E, T, M), m = batch_terms(theta, x0s, keys, spec.remat)
            L = combine(weights, E, T, M, refs[0], refs[1])
            return jnp.mean(L), (L, E, T, M, m)

        self._terms = jax.jit(lambda th, x, k: batch_terms(th, x, k, False))
        self._vg = jax.jit(jax.value_and_grad(batch_loss, has_aux=True))
        self._terms_thr = None
        if spec.judge_thrusters:
            judged = sc.flight(spec.flight_options(thrusters=True), settings=settings)
            params_thr, loop_thr = judged.params, judged.loop

            def terms_thr(theta, x0s, keys):
                p, sp = space.apply(params_thr, self.sp, space.values(theta))

                def one(x, k):
                    infos, m = fly(loop_thr, p, x, k, sp)
                    return run_terms(loop_thr, p, infos, effort_key), m

                return jax.vmap(one)(x0s, keys)

            self._terms_thr = jax.jit(terms_thr)

    # ------------------------------------------------------------------ evaluations

    def terms(self, theta, x0s, keys):
        """((E, T, M) per run, Metrics per run) at theta (forward only)."""
        return self._terms(theta, x0s, keys)

    def losses(self, theta, x0s, keys, refs, weights, chunk: int, thrusters: bool = False):
        """(L per run, Metrics per run) in batches of ``chunk`` (one compiled shape);
        ``thrusters``: flown with the scenario's thrusters (``judge_thrusters``)."""
        terms = self._terms_thr if thrusters else self.terms
        n = x0s.shape[0]
        pad = (-n) % chunk
        idx = np.concatenate([np.arange(n), np.zeros(pad, int)])
        Ls, ms = [], []
        for s in range(0, n + pad, chunk):
            sel = idx[s : s + chunk]
            (E, T, M), m = terms(theta, x0s[sel], keys[sel])
            Ls.append(np.asarray(combine(weights, E, T, M, refs[0], refs[1])))
            ms.append(jax.tree.map(np.asarray, m))
        L = np.concatenate(Ls)[:n]
        m = jax.tree.map(lambda *a: np.concatenate(a)[:n], *ms)
        return L, m

    def value_and_grad(self, theta, x0s, keys, refs, weights):
        w = weights.array() if isinstance(weights, LossWeights) else jnp.asarray(weights)
        return self._vg(theta, x0s, keys, refs, w)
