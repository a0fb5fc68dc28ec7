"""Failure probabilities P(margin < 0) under xi ~ N(0, I), beyond crude Monte Carlo.

* ``mc``: crude Monte Carlo, p = k / n, CoV sqrt((1 - p) / (n p)), 95 % Clopper-Pearson
  interval.
* ``subset``: subset simulation with adaptive conditional sampling (Papaioannou et al.
  2015) as ``replicates`` independent runs side by side; the CoV is the replicates' empirical
  standard error (:mod:`rvdjax.verify.subset`, which says why).
* ``is``: adaptive importance sampling: Gaussians and unit kernels fitted to the failing draws,
  learnt in stages as the cross-entropy method does, mixed with a defensive N(0, I) share;
  only the final stage enters the estimate, and the interval's t quantile has the effective
  number of failing draws less one as its degrees of freedom
  (:mod:`rvdjax.verify.importance`, which says why).

Every estimate draws from a stream of its own: its seed, the method and the problem's
definition hash (:meth:`~rvdjax.verify.evaluate.Problem.definition`), so two thresholds of
one margin never share their draws. Every run goes through the
:class:`~rvdjax.verify.store.EvalStore`, so an estimate resumes.
``runs_for_cov(0.3)`` scales the measured CoV to the runs a CoV of 0.3 needs (CoV^2 ~ 1 / n).
"""

from __future__ import annotations

import contextlib
import dataclasses
import time

import numpy as np
from scipy import stats

from rvdjax.verify.evaluate import Problem
from rvdjax.verify.store import EvalStore

__all__ = [
    "ProbabilitySpec",
    "estimate",
    "importance_side_by_side",
    "PROB_METHODS",
    "clopper_pearson",
]

PROB_METHODS = ("subset", "is", "mc")
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
        block: runs handed to the engine at once (mc).
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


def _is(pb: Problem, spec: ProbabilitySpec, store: EvalStore, bar) -> dict:
    return _is_many(pb, [spec], store, bar)[0]


def _is_many(pb: Problem, specs, store: EvalStore, bar) -> list[dict]:
    from rvdjax.verify.importance import check_dim, importance_sampling

    check_dim(pb.dim)
    streams = [_stream(pb, s, 32) for s in specs]
    return [
        _result(
            "is", r.pop("p"), r.pop("cov"), r.pop("ci95"), r.pop("runs"), r.pop("wall_s"), **r
        )  # fmt: skip
        for r in importance_sampling(pb, specs, store, bar, streams)
    ]


def importance_side_by_side(pb: Problem, specs, store: EvalStore, progress=True) -> list[dict]:
    """Importance-sampling estimates for several specs (seeds) flown side by side, each
    stage of all of them one engine batch; each estimate is the one :func:`estimate` gives
    for its spec alone (its draws come from its own stream)."""
    total = sum(s.budget for s in specs)
    with _progress(progress, total, f"is x {len(specs)}") as bar:
        return _is_many(pb, specs, store, bar)


def estimate(pb: Problem, spec: ProbabilitySpec, store: EvalStore | None = None, progress=True):
    """The failure probability of ``pb`` by ``spec.method`` (module docstring): a dict with
    at least p, cov, ci95, runs and wall_s."""
    store = EvalStore(None, pb.effort_key) if store is None else store
    fn = {"mc": _mc, "subset": _subset, "is": _is}[spec.method]
    with _progress(progress, spec.budget, spec.method) as bar:
        return fn(pb, spec, store, bar)


@contextlib.contextmanager
def _progress(show: bool, total: int, what: str):
    """A run-counting progress bar (None when not shown), closed on the way out."""
    if not show:
        yield None
        return
    from tqdm.auto import tqdm

    bar = tqdm(total=total, unit="run", desc=f"verify probability: {what}")
    try:
        yield bar
    finally:
        bar.close()
