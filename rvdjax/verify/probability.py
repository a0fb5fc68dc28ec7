"""Failure probabilities P(margin < 0) under xi ~ N(0, I), beyond crude Monte Carlo.

* ``mc``: crude Monte Carlo, p = k / n, CoV sqrt((1 - p) / (n p)), 95 % Clopper-Pearson
  interval.
* ``subset``: subset simulation (Au & Beck 2001, Probabilistic Engineering Mechanics 16:
  263-277) with adaptive conditional sampling (Papaioannou, Betz, Zwirglmaier & Straub 2015,
  Probabilistic Engineering Mechanics 41: 89-103). Level 0 draws ``level_size`` xi; each
  level keeps the fraction p0 = 0.1 with the smallest margins as seeds and grows each seed
  into a chain of 1 / p0 states, the chains flying side by side as one batch per chain step.
  A candidate is rho xi + sigma z (z ~ N(0, I), rho = sqrt(1 - sigma^2): a move that keeps
  N(0, I) invariant), accepted when its exact margin stays at or below the level's
  threshold. sigma = min(1, lambda) is adapted after every chain step toward an acceptance
  rate of 0.44 (lambda <- lambda exp((a - 0.44) / sqrt(step))), and lambda carries over to
  the next level. (Component-wise modified Metropolis, tried first, stalled on thesis-vbar's
  thin failure region: acceptance 0-3 %.) Estimate: p0^(L-1) times the failing fraction of
  the last level. CoV: sqrt(sum_j (1 - p_j) / (N p_j) (1 + gamma_j)) with gamma_j from the
  chains' indicator correlation (Au & Beck Eq. 29); 95 % interval from a lognormal with
  that CoV.
* ``is``: importance sampling centred on the failure points of a design-point search
  (:mod:`rvdjax.verify.worst`'s ``design-point``, 8 starts, its runs counted in the budget):
  each start's smallest-norm failing point c_j is a centre, and xi is drawn from the defensive
  mixture q = a N(0, I) + (1 - a) / J sum_j N(c_j, I) with a = 0.2 (Hesterberg 1995; a
  failure region of several parts, e.g. one per approach side, is covered by the centres, and
  the N(0, I) share bounds the weights). Weight phi(xi) / q(xi) = 1 / (a + (1 - a) / J sum_j
  exp(c_j.xi - |c_j|^2 / 2)); p = mean(w 1[fail]), CoV from the sample variance, 95 %
  interval p +- 1.96 sd (clipped at 0).

Every run goes through the :class:`~rvdjax.verify.store.EvalStore`, so an estimate resumes.
``runs_for_cov(0.3)`` scales the measured CoV to the runs a CoV of 0.3 needs (CoV^2 ~ 1 / n).
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
from scipy import stats

from rvdjax.verify.evaluate import Problem
from rvdjax.verify.store import EvalStore

__all__ = ["ProbabilitySpec", "estimate", "PROB_METHODS", "clopper_pearson", "P0"]

PROB_METHODS = ("subset", "is", "mc")
P0 = 0.1  # subset simulation's conditional probability per level
IS_DESIGN_FRACTION = 0.2  # the share of the IS budget spent finding the design point
IS_DEFENSIVE = 0.2  # the N(0, I) share of the importance-sampling mixture
MAX_LEVELS = 12


@dataclasses.dataclass(frozen=True)
class ProbabilitySpec:
    """A probability estimate (plain data).

    Attributes:
        method: "subset", "is" or "mc".
        budget: closed-loop runs at most.
        level_size: subset simulation's N per level (None: budget / 5, at least 100).
        block: runs handed to the engine at once (mc, is).
        seed: the estimate's seed.
    """

    method: str = "subset"
    budget: int = 2000
    level_size: int | None = None
    block: int = 512
    seed: int = 0

    def __post_init__(self):
        if self.method not in PROB_METHODS:
            raise ValueError(
                f"--method must be one of {', '.join(PROB_METHODS)}, got {self.method!r}"
            )
        if not (isinstance(self.budget, (int, np.integer)) and self.budget >= 1):
            raise ValueError(f"--budget must be an integer >= 1, got {self.budget!r}")
        need = {"mc": 10, "subset": 100, "is": 50}[self.method]
        if self.budget < need:
            raise ValueError(f"--budget {self.budget}: {self.method} needs at least {need} runs")
        if self.level_size is not None and not (100 <= self.level_size <= self.budget):
            raise ValueError(
                f"--level-size must be in [100, budget = {self.budget}], got {self.level_size}"
            )

    @property
    def n_level(self) -> int:
        if self.level_size is not None:
            return int(self.level_size)
        return int(max(100, min(self.budget, self.budget // 5)) // 10 * 10)


def clopper_pearson(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    a = 1.0 - level
    lo = 0.0 if k == 0 else float(stats.beta.ppf(a / 2, k, n - k + 1))
    hi = 1.0 if k == n else float(stats.beta.ppf(1 - a / 2, k + 1, n - k))
    return lo, hi


def _lognormal_ci(p: float, cov: float) -> list[float]:
    if not (p > 0 and np.isfinite(cov)):
        return [0.0, float("nan")]
    s = np.sqrt(np.log1p(cov * cov))
    return [float(p * np.exp(-1.96 * s)), float(p * np.exp(1.96 * s))]


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
    rng = np.random.default_rng([spec.seed, 10])
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


def _gamma(ind) -> float:
    """Au & Beck Eq. 29: gamma from the failure indicators of the chains (Nc, Ns)."""
    Nc, Ns = ind.shape
    p = ind.mean()
    var = p * (1 - p)
    if var <= 0 or Ns < 2:
        return 0.0
    g = 0.0
    for k in range(1, Ns):
        r = np.mean(ind[:, : Ns - k] * ind[:, k:]) - p * p
        g += 2 * (1 - k / Ns) * (r / var)
    return float(max(g, 0.0))


def _subset(pb: Problem, spec: ProbabilitySpec, store: EvalStore, bar) -> dict:
    rng = np.random.default_rng([spec.seed, 20])
    N, d = spec.n_level, pb.dim
    Nc = int(round(P0 * N))
    Ns = int(round(1 / P0))
    t0 = time.perf_counter()
    xs = rng.standard_normal((N, d))
    g = np.asarray(store.evaluate("subset-L0", "subset", xs, pb.forward)["margin"])
    runs = N
    if bar is not None:
        bar.update(N)
    lam = 0.6  # sigma = min(1, lam): adapted toward an acceptance of 0.44, kept across levels
    levels, delta2 = [], 0.0
    p_prod = 1.0
    prev = None  # (Nc, Ns) margins of the previous level's chains (None: level 0, i.i.d.)
    converged = False
    for level in range(1, MAX_LEVELS + 1):
        order = np.argsort(g, kind="stable")
        b = float(g[order[Nc - 1]])
        converged = b <= 0  # the level's threshold reached the failure domain
        if converged or runs + N - Nc > spec.budget:
            break
        # this level's conditional probability is P0 by construction
        p_j = P0
        p_prod *= p_j
        gam = 0.0 if prev is None else _gamma(prev <= b)
        delta2 += (1 - p_j) / (N * p_j) * (1 + gam)
        levels.append({"threshold": b, "gamma": gam})
        seeds_x, seeds_g = xs[order[:Nc]], g[order[:Nc]]
        chain_x = [seeds_x]
        chain_g = [seeds_g]
        cur_x, cur_g = seeds_x.copy(), seeds_g.copy()
        accepted = 0
        for step in range(1, Ns):
            sigma = min(1.0, lam)
            rho = np.sqrt(1.0 - sigma * sigma)
            cand = rho * cur_x + sigma * rng.standard_normal(cur_x.shape)
            res = store.evaluate(f"subset-L{level}-s{step}", "subset", cand, pb.forward)
            gc = np.asarray(res["margin"])
            runs += len(cand)
            if bar is not None:
                bar.update(len(cand))
            ok = gc <= b
            accepted += int(ok.sum())
            lam = float(np.clip(lam * np.exp((ok.mean() - 0.44) / np.sqrt(step)), 1e-3, 1.0))
            cur_x = np.where(ok[:, None], cand, cur_x)
            cur_g = np.where(ok, gc, cur_g)
            chain_x.append(cur_x.copy())
            chain_g.append(cur_g.copy())
        levels[-1]["acceptance"] = accepted / max(1, Nc * (Ns - 1))
        levels[-1]["sigma"] = min(1.0, lam)
        xs = np.concatenate(chain_x)  # (N, d): seeds first, then each step's states
        g = np.concatenate(chain_g)
        prev = np.stack(chain_g, axis=1)
    # last level: the fraction below 0 of the current population
    k = int(np.sum(g < 0))
    p_last = k / N
    if p_last > 0:
        gam = 0.0 if prev is None else _gamma(prev < 0)
        delta2 += (1 - p_last) / (N * p_last) * (1 + gam)
    p = p_prod * p_last
    cov = float(np.sqrt(delta2)) if p > 0 else float("inf")
    return _result(
        "subset",
        p,
        cov,
        _lognormal_ci(p, cov),
        runs,
        time.perf_counter() - t0,
        level_size=N,
        levels=levels,
        converged=converged,
    )


# ----------------------------------------------------------------------------- IS


def _is(pb: Problem, spec: ProbabilitySpec, store: EvalStore, bar) -> dict:
    from rvdjax.verify.worst import SearchSpec, search

    t0 = time.perf_counter()
    dp_budget = max(1, int(IS_DESIGN_FRACTION * spec.budget))
    starts = 8
    sspec = SearchSpec(
        methods=("design-point",),
        budget=max(1, dp_budget // starts),
        repeats=starts,
        seed=spec.seed,
        lr=1.0,
    )
    tr = search(pb, sspec, store, progress=False)["design-point"]
    dp = tr.extra.get("design_point")
    centres = np.asarray(tr.extra.get("failure_points") or [], float).reshape(-1, pb.dim)
    dp_runs = int(np.ceil(sum(float(e[-1]) for e in tr.evals)))
    if bar is not None:
        bar.update(dp_runs)
    if dp is None:
        return _result(
            "is",
            float("nan"),
            float("inf"),
            (float("nan"), float("nan")),
            dp_runs,
            time.perf_counter() - t0,
            note="the design-point search found no failure: no centre for importance sampling",
        )
    c = np.asarray(dp, float)
    J = len(centres)
    rng = np.random.default_rng([spec.seed, 30])
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
        history.append((dp_runs + len(t), ph, max(0.0, ph - 1.96 * sd), ph + 1.96 * sd))
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
        (max(0.0, p - 1.96 * sd), p + 1.96 * sd),
        dp_runs + len(t),
        time.perf_counter() - t0,
        design_point=[float(v) for v in c],
        design_point_norm=float(np.linalg.norm(c)),
        centres=int(J),
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
