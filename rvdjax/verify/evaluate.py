"""Closed-loop evaluations of a requirement at dispersion vectors xi, in batches.

Two evaluators share one set-up (:class:`Problem`):

* :meth:`Problem.forward`: exact margins of a batch of xi through the batch engine
  (:func:`rvdjax.loop.engine.run_batch`: slots refilled as runs finish), with the runs'
  Metrics. This is one *forward evaluation* per xi, the unit every method's budget counts.
* :meth:`Problem.gradient`: the smooth margin and its gradient with respect to xi of a batch
  (``vmap`` of :func:`rvdjax.loop.fly` under ``jax.value_and_grad``), plus the exact margins
  of the same runs. Its cost in forward evaluations is measured on the same footing
  (:meth:`Problem.gradient_cost`: the same runs flown forward by the same ``vmap``), not
  assumed.

Every evaluation also goes through an :class:`~rvdjax.verify.store.EvalStore` when one is given,
so a killed search or estimate resumes where it stopped: a method is deterministic given its
seed, and a batch already on disk is read back instead of flown.
"""

from __future__ import annotations

import dataclasses
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np

from rvdjax.loop import fly
from rvdjax.loop.engine import EngineConfig, arrays_source, run_batch
from rvdjax.verify.dispersions import Dispersion, parse_dispersion
from rvdjax.verify.requirements import TEMPERATURE_FRACTION, Composite, parse_requirement

__all__ = ["ProblemSpec", "Problem", "problem_for"]


@dataclasses.dataclass(frozen=True)
class ProblemSpec:
    """What is verified (plain data, written to the output directory's config.json).

    Attributes:
        scenario: scenario name (or scenario file).
        requirement: ``--requirement`` text (:mod:`rvdjax.verify.requirements`).
        dispersion: ``--dispersion`` text (:mod:`rvdjax.verify.dispersions`).
        mode, truth, disturbed, nav_filter, thrusters: the closed loop.
        n_steps, time_limit_s: the run's length (None: the scenario's).
        temperature: the smooth margin's tau (None: 10 % of the initial distance) [m].
        seed: seed of the PRNG noise not given by xi (disturbed loops).
        slots, chunk: the batch engine.
        remat: ``jax.checkpoint`` the step in the gradient's forward pass (memory bounded by
            the loop state, about one more forward pass of compute).
        solver_tol, max_iter: the solver's tolerance and iteration cap (None: the
            scenario's), e.g. 1e-12 and 300 to check gradients against central differences
            of a converged solver.
    """

    scenario: str
    requirement: str
    dispersion: str
    mode: str = "accurate"
    truth: str = "linear"
    disturbed: bool = False
    nav_filter: bool = False
    thrusters: bool = False
    n_steps: int | None = None
    time_limit_s: float | None = None
    temperature: float | None = None
    seed: int = 0
    slots: int = 64
    chunk: int = 32
    remat: bool = False
    solver_tol: float | None = None
    max_iter: int | None = None

    def __post_init__(self):
        self.flight_options()  # mode, truth, nav_filter, n_steps, time_limit_s
        if self.temperature is not None and not (0 < self.temperature < float("inf")):
            raise ValueError(f"temperature must be > 0 [m], got {self.temperature}")
        if self.solver_tol is not None and not (0 < self.solver_tol < 1):
            raise ValueError(f"solver_tol must be in (0, 1), got {self.solver_tol}")
        if self.max_iter is not None and not self.max_iter >= 1:
            raise ValueError(f"max_iter must be >= 1, got {self.max_iter}")

    def flight_options(self):
        """The :class:`~rvdjax.scenarios.flight.FlightOptions` of the verified loop."""
        from rvdjax.scenarios.flight import FlightOptions

        return FlightOptions.of(self)


class Problem:
    """The set-up of one verification: loop, nominal parameters, requirement, dispersion and
    the compiled evaluators. Everything here is checked on the host before anything is
    compiled (the constructor compiles nothing)."""

    def __init__(self, spec: ProblemSpec):
        from rvdjax.scenarios import get_scenario
        from rvdjax.study.runner import effort_metric

        self.spec = spec
        sc = get_scenario(spec.scenario)
        self.scenario = sc
        settings = None
        if spec.max_iter is not None:
            settings = dataclasses.replace(sc.settings(spec.mode), max_iter=int(spec.max_iter))
        flight = sc.flight(spec.flight_options(), settings=settings)
        self.flight = flight
        loop, params, x0 = flight.loop, flight.params, flight.x0
        self.loop, self.params, self.x0 = loop, params, np.asarray(x0, float)
        fam = sc.guidance_family
        fc = loop.config.family_config
        # only the zones' names are read: traced abstractly, nothing compiled or flown
        blocks = jax.eval_shape(
            lambda p, x: fam.truth_blocks(p, fc, fam.init(p, fc, x), x, jnp.asarray(0.0)),
            params,
            jnp.asarray(self.x0),
        )
        self.requirement: Composite = parse_requirement(
            spec.requirement, {b.name for b in blocks}, fam.dock_error is not None
        )
        self.dispersion: Dispersion = parse_dispersion(spec.dispersion, sc, loop, spec.thrusters)
        self.effort_key = effort_metric(sc)
        pos = np.asarray(self.x0)[list(fam.layout.pos)]
        self.tau = (
            float(spec.temperature)
            if spec.temperature is not None
            else float(TEMPERATURE_FRACTION * max(np.linalg.norm(pos), 1e-3))
        )
        self.sp = flight.solver_params
        if spec.solver_tol is not None:
            self.sp = self.sp._replace(tol=float(spec.solver_tol))
        self.key = flight.key
        self._costs: dict = {}

    # ------------------------------------------------------------------ properties

    @property
    def dim(self) -> int:
        return self.dispersion.dim

    def definition(self) -> dict:
        """Everything that defines this problem's runs, for provenance
        (:mod:`rvdjax.provenance`): the spec (less the engine's slots, chunk and remat, which
        do not change a run), the scenario's values, the parameters and initial state built
        from them, the loop configuration, the solver parameters, the parsed requirement and
        dispersion and the smooth margin's temperature."""
        from rvdjax import provenance

        spec = {
            k: v
            for k, v in dataclasses.asdict(self.spec).items()
            if k not in ("slots", "chunk", "remat", "truth")  # truth: in the loop's
        }
        return provenance.describe(
            spec=spec,
            scenario=provenance.scenario_values(self.scenario),
            params=self.params,
            x0=self.x0,
            loop=self.loop.config,
            solver=self.sp,
            requirement=self.requirement,
            dispersion={"label": self.dispersion.label(), "names": self.dispersion.names()},
            tau=self.tau,
        )

    def notes(self) -> list[str]:
        """What the output states next to the figures (assumptions and settings)."""
        req = self.requirement
        between = (
            "at the samples and between them"
            if self.scenario.guidance_family.subsamples is not None
            else f"at the samples (family {self.scenario.family!r} has no sub-samples)"
        )
        out = [
            f"requirement {req.label()} [{req.unit}], satisfied when the margin >= 0; exact "
            f"margins judged on the truth (zones: {between})",
            f"dispersion {self.dispersion.label()}: xi ~ N(0, I) of dimension {self.dim}",
        ]
        if req.is_zone:
            out.append(
                f"smooth margin: soft-min over the run with temperature tau = {self.tau:.4g} m"
            )
        return out

    # ------------------------------------------------------------------ inputs

    @functools.cached_property
    def _inputs(self):
        disp, lay = self.dispersion, self.scenario.guidance_family.layout
        x0, params = jnp.asarray(self.x0), self.params

        def f(xis):
            return disp.batch_apply(xis, x0, params, lay)

        return jax.jit(f)

    def inputs(self, xis):
        """(x0s, per-run params) of a batch of xi."""
        return self._inputs(jnp.asarray(xis, float))

    def keys(self, n: int):
        """The runs' PRNG keys: one key for all (the noise xi does not give is the same
        realisation in every run, so a run is a function of xi alone)."""
        return jax.vmap(lambda i: self.key)(jnp.arange(n))

    # ------------------------------------------------------------------ forward (engine)

    def forward(self, xis, progress=None) -> dict:
        """Exact margins of a batch of xi (B, dim) through the batch engine.

        Returns {"margin": (B,), "metrics": Metrics of NumPy arrays}."""
        xis = np.asarray(xis, float).reshape(-1, self.dim)
        n = xis.shape[0]
        # input arrays of 256, 512, ... runs (the padding is never flown): few compiles
        bucket = max(256, 1 << max(0, int(n - 1).bit_length()))
        pad = np.concatenate([xis, np.repeat(xis[:1], bucket - n, axis=0)])
        x0s, per_run = self.inputs(pad)
        per_run = per_run if self.dispersion.touches_params() else None
        source = arrays_source(x0s, self.keys(bucket), per_run)
        # every batch through the same slots, so one engine program serves a search's small
        # batches and an estimate's large ones: a chunk with no run to fly is skipped, and
        # the runs' bits do not depend on the slots (tests/test_engine.py)
        unit = self.spec.chunk
        cfg = EngineConfig(slots=max(unit, self.spec.slots), chunk=unit, iterations=3)
        res = run_batch(
            self.loop,
            source,
            n,
            params=None if per_run is not None else self.params,
            solver_params=self.sp,
            config=cfg,
            progress=progress,
        )
        m = res["metrics"]
        margin = np.asarray(self.requirement.exact(m, self.effort_key), float)
        return {"margin": margin, "metrics": m}

    # ------------------------------------------------------------------ gradient (fly)

    @functools.cached_property
    def _vg(self):
        loop, sp, req, ek, tau = self.loop, self.sp, self.requirement, self.effort_key, self.tau
        remat = self.spec.remat
        disp, lay = self.dispersion, self.scenario.guidance_family.layout
        x0n, params = jnp.asarray(self.x0), self.params

        def one(xi, probe, key):
            x0, p = disp.apply(xi, x0n, params, lay)
            infos, m = fly(loop, p, x0, key, sp._replace(derivative_probe=probe), remat=remat)
            smooth = req.smooth(loop, p, infos, m, ek, tau)
            return smooth, (req.exact(m, ek), m)

        vg = jax.value_and_grad(one, argnums=(0, 1), has_aux=True)

        def batch(xis, keys):
            probes = jnp.zeros(xis.shape[0], xis.dtype)
            (s, (e, m)), (g, zeroed) = jax.vmap(vg)(xis, probes, keys)
            ok = jnp.isfinite(s) & jnp.all(jnp.isfinite(g), axis=-1)
            # no NaN leaves a batch: a non-finite run keeps its exact margin, zero gradient
            # (counted: "nonfinite"); "zeroed": the back-solves the solver zeroed in the run
            return jnp.where(ok, s, e), jnp.where(ok[:, None], g, 0.0), e, m, ~ok, zeroed

        return jax.jit(batch)

    def gradient(self, xis) -> dict:
        """Smooth margins, their gradients and the exact margins of a batch of xi.

        Returns {"smooth": (B,), "grad": (B, dim), "margin": (B,), "metrics": Metrics,
        "nonfinite": (B,) runs whose smooth margin or gradient was not finite (their
        gradient is zero, their smooth margin the exact one), "zeroed": (B,) back-solves the
        solver zeroed inside each run (``SolverParams.derivative_probe``)}."""
        xis = np.asarray(xis, float).reshape(-1, self.dim)
        n = xis.shape[0]
        # batch shapes in multiples of 8 (each compiles once; padding is computed, so keep it
        # small: the gradient's measured cost includes it)
        bucket = 8 * int(np.ceil(n / 8))
        pad = np.concatenate([xis, np.repeat(xis[:1], bucket - n, axis=0)])
        s, g, e, m, bad, zeroed = self._vg(jnp.asarray(pad), self.keys(bucket))
        m = jax.tree.map(lambda a: np.asarray(a)[:n], m)
        return {
            "smooth": np.asarray(s)[:n],
            "grad": np.asarray(g)[:n],
            "margin": np.asarray(e)[:n],
            "metrics": m,
            "nonfinite": np.asarray(bad)[:n],
            "zeroed": np.rint(np.asarray(zeroed)[:n]).astype(int),
        }

    @functools.cached_property
    def _fwd_vmap(self):
        """Exact margins of a batch by ``vmap`` of :func:`rvdjax.loop.fly` (every run pays
        every step, as in :meth:`gradient`): the forward side of the fair cost."""
        loop, sp, req, ek = self.loop, self.sp, self.requirement, self.effort_key
        disp, lay = self.dispersion, self.scenario.guidance_family.layout
        x0n, params = jnp.asarray(self.x0), self.params

        def one(xi, key):
            x0, p = disp.apply(xi, x0n, params, lay)
            _, m = fly(loop, p, x0, key, sp)
            return req.exact(m, ek)

        return jax.jit(jax.vmap(one))

    def _timed(self, fn, *args) -> float:
        jax.block_until_ready(fn(*args))  # compiled (and warm) first
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        return time.perf_counter() - t0

    def gradient_cost(self, n_grad: int = 8, seed: int = 12345) -> float:
        """The cost of one gradient evaluation in forward evaluations, measured on the same
        footing: the wall time of :meth:`gradient` on ``n_grad`` runs (rounded up to its
        batch of a multiple of 8, so no padding is timed) over that of the same runs flown
        forward the same way (``vmap`` of the loop, every run paying every step), both
        compiled. At least 1. Cached per size."""
        n = 8 * int(np.ceil(n_grad / 8))
        if n not in self._costs:
            xs = jnp.asarray(np.random.default_rng(seed).standard_normal((n, self.dim)))
            keys = self.keys(n)
            t_f = self._timed(self._fwd_vmap, xs, keys)
            t_g = self._timed(self._vg, xs, keys)
            self._costs[n] = max(1.0, t_g / max(t_f, 1e-12))
        return self._costs[n]

    def gradient_cost_engine(self, n_grad: int = 8, n_fwd: int = 64, seed: int = 12345) -> float:
        """For comparison only: the gradient's wall time per run over the batch engine's
        forward wall time per run (which refills finished slots, so a short run costs
        less there than in a ``vmap``)."""
        key = ("engine", 8 * int(np.ceil(n_grad / 8)), int(n_fwd))
        if key not in self._costs:
            rng = np.random.default_rng(seed)
            xf = rng.standard_normal((n_fwd, self.dim))
            xg = jnp.asarray(rng.standard_normal((key[1], self.dim)))
            self.forward(xf)
            t0 = time.perf_counter()
            self.forward(xf)
            t_f = (time.perf_counter() - t0) / n_fwd
            t_g = self._timed(self._vg, xg, self.keys(key[1])) / key[1]
            self._costs[key] = t_g / max(t_f, 1e-12)
        return self._costs[key]


_PROBLEMS: dict = {}


def problem_for(spec: ProblemSpec) -> Problem:
    """The :class:`Problem` of ``spec``, shared by later calls with the same spec (its
    compiled evaluators are reused)."""
    if spec not in _PROBLEMS:
        _PROBLEMS.clear()
        _PROBLEMS[spec] = Problem(spec)
    return _PROBLEMS[spec]
