"""Adaptive importance sampling of P(margin < 0) under xi ~ N(0, I).

The proposal is learnt from the margins in stages, as the cross-entropy method learns it
(Rubinstein & Kroese 2004), with a mixture of kernels on the elite draws as its family
(Ang, Ang & Tang 1992):

1. Stage 0 draws from N(0, I).
2. After each stage, the threshold gamma is the rho-quantile of its margins (rho = 0.1,
   midway between the (rho n)-th and (rho n + 1)-th smallest), and its elites are the draws
   with margin < gamma. Once rho n draws of a stage fail (gamma <= 0), the elites are the
   failing draws of every stage so far; one more stage (``IS_REFINE``) is drawn from them,
   which adds its failing draws, and the next one is the final stage.
3. Each proposal is the defensive mixture (Hesterberg 1995)
   q = a N(0, I) + (1 - a) sum_k pi_k N(c_k, I), a = 0.2: a unit kernel on every elite c_k,
   pi_k its importance weight phi / q_t normalised, so that the kernels approximate
   phi 1[margin < gamma], the optimal density. The kernels have unit covariance because
   narrower ones (a bandwidth of the elites' spread, or one Gaussian fitted to them) have
   thinner tails than phi 1[fail] and gave rare large weights: on linear limit states at
   p = 5e-3 and 1e-5 their 95 % intervals covered the truth 55-80 % of the time, unit
   kernels 85-100 %.
4. Adaptation stops at 60 % of the budget in any case; the rest (at least 40 %) is the final
   stage, drawn from the last proposal.

Only the final stage enters the estimate: p = mean(w 1[fail]), w = phi / q <= 1 / a, the CoV
from the sample variance and the 95 % interval p +- 1.96 sd, clipped at 0. The final proposal
depends only on earlier stages, so the estimate is unbiased and its variance estimate honest
(pooling the adaptive stages' draws would bias it: the proposal was chosen on them). With no
failing draw the sample variance says nothing: the interval is then [0, u / a], u the 97.5 %
Clopper-Pearson bound of the proposal's mass on the failure set after no failure in n draws,
which holds whatever the weights, because q >= a phi.

Dispersions of more than 20 coordinates are refused: a unit kernel on a draw of norm
sqrt(d) carries a weight of about exp(-d / 2), so in the noise sequences' hundreds of
dimensions the estimate would be crude Monte Carlo on the defensive fifth of the draws (Au &
Beck 2003 on importance sampling in high dimension). Subset simulation is the estimator
there.

Several estimates fly side by side (:func:`importance_sampling` takes a list of specs): each
stage of every estimate is one engine batch, and each estimate's draws come from its own
stream, so an estimate is the same flown alone or with others.
"""

from __future__ import annotations

import time

import numpy as np
from scipy.special import logsumexp

__all__ = ["importance_sampling", "check_dim", "IS_MAX_DIM"]

IS_DEFENSIVE = 0.2  # the N(0, I) share of every proposal after stage 0
IS_RHO = 0.1  # the elite fraction of a stage
IS_STAGE = 8  # a stage is budget / IS_STAGE draws (at least 50)
IS_ADAPT = 0.6  # the adaptive stages' share of the budget, at most
IS_REFINE = 1  # stages drawn from the failing draws' kernels before the final one
IS_MAX_DIM = 20  # dispersions of more coordinates: subset simulation (module docstring)
IS_MAX_CENTRES = 256  # kernels of a proposal, at most (resampled by weight beyond it)


class _Proposal:
    """a N(0, I) + (1 - a) sum_k pi_k N(c_k, I); without kernels, N(0, I) itself."""

    def __init__(self, centres=None, log_pi=None):
        self.centres, self.log_pi = centres, log_pi

    def sample(self, rng, m: int, dim: int) -> np.ndarray:
        z = rng.standard_normal((m, dim))
        if self.centres is None:
            return z
        k = rng.choice(len(self.centres), size=m, p=np.exp(self.log_pi))
        kern = rng.uniform(size=m) >= IS_DEFENSIVE
        return np.where(kern[:, None], self.centres[k] + z, z)

    def weight(self, x: np.ndarray) -> np.ndarray:
        """phi(x) / q(x), <= 1 / a."""
        if self.centres is None:
            return np.ones(len(x))
        c = self.centres
        lr = x @ c.T - 0.5 * np.sum(c * c, axis=1)[None]  # log N(x; c, I) - log phi(x)
        L = logsumexp(lr + self.log_pi[None], axis=1)
        return 1.0 / (IS_DEFENSIVE + (1.0 - IS_DEFENSIVE) * np.exp(np.minimum(L, 700.0)))


def _fit(x: np.ndarray, w: np.ndarray, rng) -> _Proposal:
    """Unit kernels on the elites x, weighted by w (module docstring, step 3)."""
    pi = w / w.sum()
    if len(x) > IS_MAX_CENTRES:  # resampled by weight: the same density, fewer kernels
        idx = rng.choice(len(x), size=IS_MAX_CENTRES, p=pi)
        return _Proposal(x[idx], np.full(IS_MAX_CENTRES, -np.log(IS_MAX_CENTRES)))
    return _Proposal(x, np.log(pi))


def check_dim(dim: int) -> None:
    """Raise for a dispersion of more than ``IS_MAX_DIM`` coordinates (module docstring)."""
    if dim > IS_MAX_DIM:
        raise ValueError(
            f"--method is: the dispersion has {dim} coordinates; importance sampling takes at "
            f"most {IS_MAX_DIM} (its weights degenerate above): use --method subset or mc"
        )


def _threshold(m: np.ndarray, k: int) -> float:
    """Midway between the k-th and (k+1)-th smallest margins."""
    s = np.sort(m)
    return 0.5 * (s[k - 1] + s[k]) if k < len(s) else float(s[-1])


class _Run:
    """One estimate's state between stages."""

    def __init__(self, budget: int, dim: int, rng):
        self.budget, self.dim, self.rng = budget, dim, rng
        self.n_stage = max(50, budget // IS_STAGE)
        self.cap = int(IS_ADAPT * budget)
        self.prop = _Proposal()
        self.spent = 0
        self.found = 0  # stages since rho n draws first failed
        self.final = False
        self.done = False
        self.stages = []
        self.fail_x, self.fail_w = [], []
        self.result = None

    def next_draws(self) -> np.ndarray:
        if self.spent + self.n_stage > self.cap:
            self.final = True
        n = self.budget - self.spent if self.final else self.n_stage
        self.x = self.prop.sample(self.rng, n, self.dim)
        return self.x

    def absorb(self, m: np.ndarray):
        x, w = self.x, self.prop.weight(self.x)
        fail = m < 0
        self.spent += len(x)
        if fail.any():
            self.fail_x.append(x[fail])
            self.fail_w.append(w[fail])
        if self.final:
            self.result = (x, w, m)
            self.done = True
            self.stages.append({"draws": len(x), "failures": int(fail.sum()), "final": True})
            return
        k = max(1, int(np.ceil(IS_RHO * len(m))))
        gamma = _threshold(m, k)
        self.stages.append({"draws": len(x), "failures": int(fail.sum()), "gamma": float(gamma)})
        if self.found or fail.sum() >= k:  # the kernels on every failing draw so far
            self.prop = _fit(np.concatenate(self.fail_x), np.concatenate(self.fail_w), self.rng)
            self.found += 1
            self.final = self.found > IS_REFINE
            return
        elite = m < gamma
        if elite.any():  # on a plateau (no margin below gamma) the proposal stays
            self.prop = _fit(x[elite], w[elite], self.rng)


def _interval(p: float, sd: float, n: int) -> tuple[float, float]:
    if p > 0:
        return max(0.0, p - 1.96 * sd), p + 1.96 * sd
    return 0.0, float(1.0 - 0.025 ** (1.0 / n)) / IS_DEFENSIVE


def importance_sampling(pb, specs, store, bar, streams) -> list[dict]:
    """Adaptive importance sampling (module docstring) for each spec (its budget) with its
    stream's draws, side by side: every stage is one ``store.evaluate`` batch. Returns a
    dict per spec: p, cov, ci95, runs, wall_s, fixed_runs (the adaptive stages' draws),
    stages, design_point (the failing draw of least norm), design_point_norm."""
    t0 = time.perf_counter()
    runs = [
        _Run(s.budget, pb.dim, np.random.default_rng(st))
        for s, st in zip(specs, streams, strict=True)
    ]
    stage = 0
    while not all(r.done for r in runs):
        live = [r for r in runs if not r.done]
        xs = [r.next_draws() for r in live]
        res = store.evaluate(f"is-stage-{stage}", "is", np.concatenate(xs), pb.forward)
        margin = np.asarray(res["margin"], float)
        lo = 0
        for r, x in zip(live, xs, strict=True):
            r.absorb(margin[lo : lo + len(x)])
            lo += len(x)
        if bar is not None:
            bar.update(len(margin))
        stage += 1
    wall = time.perf_counter() - t0
    out = []
    for r in runs:
        x, w, m = r.result
        t = np.where(m < 0, w, 0.0)
        p = float(t.mean())
        sd = float(t.std(ddof=1) / np.sqrt(len(t)))
        fx = np.concatenate(r.fail_x) if r.fail_x else np.zeros((0, pb.dim))
        dp = fx[np.argmin(np.linalg.norm(fx, axis=1))] if len(fx) else None
        out.append(
            {
                "p": p,
                "cov": sd / p if p > 0 else float("inf"),
                "ci95": _interval(p, sd, len(t)),
                "runs": r.spent,
                "wall_s": wall / len(runs),  # side by side: the wall time shared out
                "fixed_runs": r.spent - len(t),
                "final_failing": float(np.mean(m < 0)),
                "stages": r.stages,
                "design_point": None if dp is None else [float(v) for v in dp],
                "design_point_norm": None if dp is None else float(np.linalg.norm(dp)),
            }
        )
    return out
