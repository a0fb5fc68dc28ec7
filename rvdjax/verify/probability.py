"""Failure probabilities P(margin < 0) under xi ~ N(0, I), beyond crude Monte Carlo.

* ``mc``: crude Monte Carlo, p = k / n, CoV sqrt((1 - p) / (n p)), 95 % Clopper-Pearson
  interval.
* ``subset``: subset simulation with adaptive conditional sampling (Papaioannou et al.
  2015) as ``replicates`` independent runs side by side; the CoV is the replicates' empirical
  standard error (:mod:`rvdjax.verify.subset`, which says why).
* ``is``: importance sampling centred on the failure points of a design-point search
  (:mod:`rvdjax.verify.worst`'s ``design-point``, 8 starts from a stream of the estimate's
  own, its runs counted in the budget): each start's smallest-norm failing point c_j is a
  centre (a start that found none gives its lowest-margin point), and xi is drawn from the
  defensive
  mixture q = a N(0, I) + (1 - a) / J sum_j N(c_j, I) with a = 0.2 (Hesterberg 1995; a
  failure region of several parts, e.g. one per approach side, is covered by the centres, and
  the N(0, I) share bounds the weights). Weight phi(xi) / q(xi) = 1 / (a + (1 - a) / J sum_j
  exp(c_j.xi - |c_j|^2 / 2)); p = mean(w 1[fail]), CoV from the sample variance, 95 %
  interval p +- 1.96 sd (clipped at 0). With no failing draw the sample variance is 0 and
  says nothing: the interval is then [0, u / a], u the 97.5 % Clopper-Pearson bound of the
  mixture's mass on the failure set (no failure in n draws) and 1 / a the largest weight.

Every estimate draws from a stream of its own: its seed, the method and the problem's
definition hash (:meth:`~rvdjax.verify.evaluate.Problem.definition`), so two thresholds of
one margin never share their draws. Every run goes through the
:class:`~rvdjax.verify.store.EvalStore`, so an estimate resumes.
``runs_for_cov(0.3)`` scales the measured CoV to the runs a CoV of 0.3 needs (CoV^2 ~ 1 / n).
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
from scipy import stats

from rvdjax.verify.evaluate import Problem
from rvdjax.verify.store import EvalStore

__all__ = ["ProbabilitySpec", "estimate", "PROB_METHODS", "clopper_pearson"]

PROB_METHODS = ("subset", "is", "mc")
IS_DESIGN_FRACTION = 0.2  # the share of the IS budget spent finding the design point
IS_DEFENSIVE = 0.2  # the N(0, I) share of the importance-sampling mixture
DEFAULT_REPLICATES = 4


@dataclasses.dataclass(frozen=True)
class ProbabilitySpec:
    """A probability estimate (plain data).

    Attributes:
        method: "subset", "is" or "mc".
        budget: closed-loop runs at most.
        level_size: subset simulation's N per level and replicate (None: a quarter of a
            replicate's share of the budget, at least 50).
        replicates: subset simulation's independent replicates (>= 2: their spread is the
            CoV).
        block: runs handed to the engine at once (mc, is).
        seed: the estimate's seed.
    """

    method: str = "subset"
    budget: int = 2000
    level_size: int | None = None
    replicates: int = DEFAULT_REPLICATES
    block: int = 512
    seed: int = 0

    def __post_init__(self):
        if self.method not in PROB_METHODS:
            raise ValueError(
                f"--method must be one of {', '.join(PROB_METHODS)}, got {self.method!r}"
            )
        if not (isinstance(self.budget, (int, np.integer)) and self.budget >= 1):
            raise ValueError(f"--budget must be an integer >= 1, got {self.budget!r}")
        if not (isinstance(self.replicates, (int, np.integer)) and self.replicates >= 2):
            raise ValueError(f"--replicates must be an integer >= 2, got {self.replicates!r}")
        need = {"mc": 10, "subset": 50 * self.replicates, "is": 50}[self.method]
        if self.budget < need:
            raise ValueError(f"--budget {self.budget}: {self.method} needs at least {need} runs")
        share = self.budget // self.replicates
        if self.level_size is not None and not (50 <= self.level_size <= share):
            raise ValueError(
                f"--level-size must be in [50, budget / replicates = {share}], got "
                f"{self.level_size}"
            )

    @property
    def n_level(self) -> int:
        if self.level_size is not None:
            return int(self.level_size)
        return int(max(50, self.budget // self.replicates // 4))


def _stream(pb, spec: ProbabilitySpec, method_tag: int) -> list[int]:
    """The entropy of one estimate's draws: seed, method and the problem's definition."""
    from rvdjax import provenance

    defn = getattr(pb, "definition", None)
    h = int(provenance.digest(defn())[:8], 16) if callable(defn) else 0
    return [int(spec.seed), method_tag, h]


def clopper_pearson(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    a = 1.0 - level
    lo = 0.0 if k == 0 else float(stats.beta.ppf(a / 2, k, n - k + 1))
    hi = 1.0 if k == n else float(stats.beta.ppf(1 - a / 2, k + 1, n - k))
    return lo, hi


def _result(method, p, cov, ci, runs, wall, **extra) -> dict:
    out = {
        "method": method,
        "p": float(p),
        "cov": float(cov) if np.isfinite(cov) else None,
        "ci95": [float(ci[0]), float(ci[1])],
        "runs": int(runs),
        "wall_s": float(wall),
    }
    if out["cov"] is not None and out["cov"] > 0:
        fixed = extra.pop("fixed_runs", 0)
        out["runs_for_cov_0.3"] = int(np.ceil(fixed + (runs - fixed) * (cov / 0.3) ** 2))
    else:
        extra.pop("fixed_runs", None)
    out.update(extra)
    return out


# ----------------------------------------------------------------------------- crude MC


def _mc(pb: Problem, spec: ProbabilitySpec, store: EvalStore, bar) -> dict:
    rng = np.random.default_rng(_stream(pb, spec, 10))
    n, k = spec.budget, 0
    t0 = time.perf_counter()
    history = []
    for lo in range(0, n, spec.block):
        xs = rng.standard_normal((min(spec.block, n - lo), pb.dim))
        res = store.evaluate(f"mc-{lo}", "mc", xs, pb.forward)
        k += int(np.sum(res["margin"] < 0))
        done = lo + len(xs)
        ph = k / done
        history.append((done, ph, *clopper_pearson(k, done)))
        if bar is not None:
            bar.update(len(xs))
    p = k / n
    cov = np.sqrt((1 - p) / (n * p)) if k else float("inf")
    return _result(
        "mc",
        p,
        cov,
        clopper_pearson(k, n),
        n,
        time.perf_counter() - t0,
        failures=k,
        history=history,
    )


# ----------------------------------------------------------------------------- subset


def _subset(pb: Problem, spec: ProbabilitySpec, store: EvalStore, bar) -> dict:
    from rvdjax.verify.subset import subset_simulation

    res = subset_simulation(pb, spec, store, bar, _stream(pb, spec, 20))
    return _result("subset", res.pop("p"), res.pop("cov"), res.pop("ci95"), res.pop("runs"),
                   res.pop("wall_s"), **res)  # fmt: skip


# ----------------------------------------------------------------------------- IS


def _is_interval(p: float, sd: float, n: int) -> tuple[float, float]:
    """Importance sampling's 95 % interval (module docstring)."""
    if p > 0:
        return max(0.0, p - 1.96 * sd), p + 1.96 * sd
    return 0.0, float(1.0 - 0.025 ** (1.0 / n)) / IS_DEFENSIVE


def _is(pb: Problem, spec: ProbabilitySpec, store: EvalStore, bar) -> dict:
    from rvdjax.verify.worst import SearchSpec, search

    t0 = time.perf_counter()
    dp_budget = max(1, int(IS_DESIGN_FRACTION * spec.budget))
    starts = 8
    seed = int(np.random.default_rng(_stream(pb, spec, 31)).integers(2**31))
    sspec = SearchSpec(
        methods=("design-point",),
        budget=max(1, dp_budget // starts),
        repeats=starts,
        starts=1,
        seed=seed,
    )
    tr = search(pb, sspec, store, progress=False)["design-point"]
    dp = tr.extra.get("design_point")
    # a centre per start: its smallest-norm failing point, else its lowest-margin point (the
    # estimate is unbiased for any centres: the N(0, I) share keeps the support whole)
    centres = np.asarray(tr.worst_xi, float).copy()
    fails = tr.extra.get("failure_starts") or []
    for r, x in zip(fails, tr.extra.get("failure_points") or [], strict=True):
        centres[r] = x
    dp_runs = int(np.ceil(sum(float(e[-1]) for e in tr.evals)))
    if bar is not None:
        bar.update(dp_runs)
    J = len(centres)
    rng = np.random.default_rng(_stream(pb, spec, 30))
    n = max(1, spec.budget - dp_runs)
    terms = []
    history = []
    for lo in range(0, n, spec.block):
        m = min(spec.block, n - lo)
        comp = rng.integers(0, J, m)
        shift = np.where((rng.uniform(size=m) < IS_DEFENSIVE)[:, None], 0.0, centres[comp])
        xs = shift + rng.standard_normal((m, pb.dim))
        res = store.evaluate(f"is-{lo}", "is", xs, pb.forward)
        lr = xs @ centres.T - 0.5 * np.sum(centres * centres, axis=1)  # (m, J)
        w = 1.0 / (IS_DEFENSIVE + (1 - IS_DEFENSIVE) * np.mean(np.exp(lr), axis=1))
        terms.append(np.where(np.asarray(res["margin"]) < 0, w, 0.0))
        t = np.concatenate(terms)
        ph = t.mean()
        sd = t.std(ddof=1) / np.sqrt(len(t)) if len(t) > 1 else np.inf
        history.append((dp_runs + len(t), ph, *_is_interval(ph, sd, len(t))))
        if bar is not None:
            bar.update(len(xs))
    t = np.concatenate(terms)
    p = float(t.mean())
    sd = float(t.std(ddof=1) / np.sqrt(len(t)))
    cov = sd / p if p > 0 else float("inf")
    return _result(
        "is",
        p,
        cov,
        _is_interval(p, sd, len(t)),
        dp_runs + len(t),
        time.perf_counter() - t0,
        design_point=None if dp is None else [float(v) for v in dp],
        design_point_norm=None if dp is None else float(np.linalg.norm(dp)),
        centres=int(J),
        centres_failing=len(fails),
        design_point_runs=dp_runs,
        fixed_runs=dp_runs,
        history=history,
    )


def estimate(pb: Problem, spec: ProbabilitySpec, store: EvalStore | None = None, progress=True):
    """The failure probability of ``pb`` by ``spec.method`` (module docstring): a dict with
    at least p, cov, ci95, runs and wall_s."""
    store = EvalStore(None, pb.effort_key) if store is None else store
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=spec.budget, unit="run", desc=f"verify probability: {spec.method}")
    try:
        fn = {"mc": _mc, "subset": _subset, "is": _is}[spec.method]
        return fn(pb, spec, store, bar)
    finally:
        if bar is not None:
            bar.close()
