"""Subset simulation with adaptive conditional sampling, as independent replicates.

Subset simulation (Au & Beck 2001, Probabilistic Engineering Mechanics 16: 263-277) writes a
small P(g < 0) as a product of larger conditional probabilities P(g < b_j | g < b_{j-1}).
The chains follow the adaptive conditional sampling of Papaioannou, Betz, Zwirglmaier and
Straub (2015), "MCMC algorithms for subset simulation", Probabilistic Engineering Mechanics
41: 89-103 (their Algorithm 5, and the ERA group's reference code ``aCS``):

* **level 0**: ``N`` draws of xi ~ N(0, I), from a stream of its own for every estimate
  (the seed, the method, the replicate and the problem's definition hash: two thresholds of
  one margin, or two seeds, never share their draws);
* **threshold**: b_j is the midpoint between the (p0 N)-th and (p0 N + 1)-th smallest
  margins, so exactly the p0 N smallest satisfy g < b_j (ties: those strictly below). Every
  level and the failure event use the same strict comparison, g < b (a requirement fails
  when its margin is < 0);
* **seeds** (the states with g < b_j) are put in random order and each grows a chain, N
  states in all (seeds included);
* **proposal**, per dimension k: v_k ~ N(rho_k u_k, sigma_k^2) with sigma_k = min(1,
  lambda sigma_hat_k), rho_k = sqrt(1 - sigma_k^2) (N(0, 1) stays invariant), sigma_hat_k the
  seeds' sample standard deviation; accepted when g(v) < b_j;
* **adaptation** between groups of chains: the chains fly in groups of p_a = 10 % of the
  seeds with a fixed proposal; after each group lambda <- lambda exp((a_hat - 0.44) /
  sqrt(i)) (a_hat: the group's mean acceptance, i: the group's number in the level).
  lambda starts at 0.6 and carries over to the next level;
* **stop**: when at least p0 N states already fail (g < 0), or when the next level does not
  fit in the replicate's share of the budget;
* **the whole budget**: what the levels leave of a replicate's share extends the last
  level's chains (a fixed proposal: the chains stay in F_L's conditional distribution) or,
  at level 0, draws more i.i.d. points; the last level's fraction is counted over all of
  its states.

**The CoV: independent replicates.** The budget is split into R replicates
(``ProbabilitySpec.replicates``), each a complete subset simulation with its own level 0,
flown side by side (one engine batch holds every replicate's chains). The estimate is their
mean and its standard error their sample standard deviation over sqrt(R). The 95 % interval
is lognormal with that CoV and Student's t quantile of R - 1 degrees of freedom (the
standard error of a few replicates is itself uncertain). When no replicate ends with a
failing state the estimate is 0 and the spread says nothing; the interval is then [0, u],
u the 97.5 % Clopper-Pearson bound after no failure in the replicates' level-0 draws (i.i.d.;
a failing draw there would have stayed a seed to the last level). A tighter bound from the
levels' product and the last chains missed the reference in both of two such estimates at
10 m (docs/verification.md): it trusts chains that a zero estimate shows did not explore.

Why replicates and not Au & Beck's formula (Eq. 29) or Zuev et al.'s Bayesian
post-processor (2012): both treat the levels as independent and Zuev's also treats a level's
states as independent draws, while a level's seeds are the previous level's states and a
chain's states are correlated. On the two-part failure region of the tests the formula
under-reports the spread; replicates are independent by construction and their spread
holds every correlation. What they cost: each replicate pays its own level 0, and a few
replicates give a noisy standard error (hence the t quantile). Each replicate's Au & Beck
CoV is still reported (``cov_au_beck``) for comparison.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
from scipy import stats

__all__ = ["subset_simulation", "combine", "P0", "ADAPT_FRACTION", "TARGET_ACCEPTANCE", "LAMBDA0"]

P0 = 0.1  # conditional probability per level
ADAPT_FRACTION = 0.1  # p_a: chains per adaptation group, as a fraction of the seeds
TARGET_ACCEPTANCE = 0.44
LAMBDA0 = 0.6
MAX_LEVELS = 30


@dataclasses.dataclass
class _Replicate:
    """One subset simulation's state."""

    rng: np.random.Generator
    share: int  # runs it may spend
    runs: int = 0
    xs: np.ndarray | None = None  # the current level's states (n, d)
    g: np.ndarray | None = None  # their margins
    chains: list | None = None  # the current level's chains: lists of state indices
    lam: float = LAMBDA0
    probs: list = dataclasses.field(default_factory=list)  # p_j of the levels passed
    levels: list = dataclasses.field(default_factory=list)  # per level: threshold, ...
    delta2: float = 0.0  # Au & Beck's CoV^2 of the levels passed
    final: bool = False
    converged: bool = False
    threshold: float = float("inf")  # b of the current population (inf at level 0)
    sigma_hat: np.ndarray | None = None  # the seeds' standard deviations (d,)
    new_x: list | None = None  # chains being grown: states per chain
    new_g: list | None = None  # and their margins
    lengths: np.ndarray | None = None  # states per chain of the level being grown
    left: int = 0  # runs left for the extension
    p_last: float = 0.0


def _gamma(ind: np.ndarray) -> float:
    """Au & Beck Eq. 29's gamma from the indicators of equal-length chains (Nc, Ns)."""
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


def _chain_indicators(rep: _Replicate, b: float) -> np.ndarray | None:
    """(chains, shortest length) indicators g < b of the current chains (None at level 0)."""
    if rep.chains is None:
        return None
    L = min(len(c) for c in rep.chains)
    return np.stack([rep.g[c[:L]] < b for c in rep.chains]).astype(float)


def _next_level(rep: _Replicate, N: int, d: int) -> None:
    """Decide the replicate's next step from its current population: stop (converged or
    out of budget), or set the threshold, the seeds and their chains."""
    g = rep.g
    n = len(g)
    nc = int(round(P0 * n))
    n_fail = int(np.sum(g < 0))
    if n_fail >= nc:
        rep.final, rep.converged = True, True
        return
    order = np.argsort(g, kind="stable")
    b = 0.5 * (g[order[nc - 1]] + g[order[nc]])
    seeds = np.flatnonzero(g < b)
    if len(seeds) == 0 or rep.runs + N - len(seeds) > rep.share or len(rep.probs) >= MAX_LEVELS:
        rep.final = True
        return
    p_j = len(seeds) / n
    ind = _chain_indicators(rep, b)
    gam = 0.0 if ind is None else _gamma(ind)
    rep.delta2 += (1 - p_j) / (n * p_j) * (1 + gam)
    rep.probs.append(p_j)
    seeds = rep.rng.permutation(seeds)  # random order: the adaptation groups are mixed
    sx = rep.xs[seeds]
    sd = sx.std(axis=0, ddof=1) if len(seeds) > 1 else np.ones(d)
    lengths = np.full(len(seeds), N // len(seeds))
    lengths[: N % len(seeds)] += 1
    rep.levels.append({"threshold": float(b), "p": p_j, "gamma": gam, "seeds": len(seeds)})
    rep.threshold = float(b)
    rep.sigma_hat = np.where(sd > 0, sd, 1.0)
    # the new population: each chain's states, the seed first
    rep.new_x = [[sx[i]] for i in range(len(seeds))]
    rep.new_g = [[rep.g[s]] for s in seeds]
    rep.lengths = lengths


def subset_simulation(pb, spec, store, bar, stream) -> dict:
    """Subset simulation of ``pb`` under ``spec`` (module docstring). ``stream``: the
    entropy that makes this estimate's draws its own."""
    R, N, d = spec.replicates, spec.n_level, pb.dim
    share = spec.budget // R
    t0 = time.perf_counter()
    reps = [_Replicate(rng=np.random.default_rng([*stream, r]), share=share) for r in range(R)]
    xs = [rep.rng.standard_normal((N, d)) for rep in reps]
    res = store.evaluate("subset-L0", "subset", np.concatenate(xs), pb.forward)
    g = np.asarray(res["margin"], float)
    for r, rep in enumerate(reps):
        rep.xs, rep.g, rep.runs = xs[r], g[r * N : (r + 1) * N], N
    if bar is not None:
        bar.update(R * N)
    level = 0
    while True:
        level += 1
        active = []
        for rep in reps:
            if not rep.final:
                _next_level(rep, N, d)
                if not rep.final:
                    active.append(rep)
        if not active:
            break
        _grow_level(pb, store, bar, active, level)
    _extend(pb, store, bar, reps)
    return _estimate(reps, spec, time.perf_counter() - t0)


def _propose(rep: _Replicate, u: np.ndarray) -> np.ndarray:
    sigma = np.minimum(1.0, rep.lam * rep.sigma_hat)
    rho = np.sqrt(1.0 - sigma * sigma)
    return rho * u + sigma * rep.rng.standard_normal(u.shape)


def _grow_level(pb, store, bar, active: list, level: int) -> None:
    """Grow every active replicate's chains, group by group (all replicates' chains of one
    group step in one batch), adapting lambda after each group."""
    groups = []
    for rep in active:
        ns = len(rep.new_x)
        na = max(1, int(np.ceil(ADAPT_FRACTION * ns)))
        groups.append([list(range(lo, min(ns, lo + na))) for lo in range(0, ns, na)])
    for gi in range(max(len(gs) for gs in groups)):
        in_group = [(rep, gs[gi]) for rep, gs in zip(active, groups, strict=True) if gi < len(gs)]
        acc = {(id(rep), c): [] for rep, cs in in_group for c in cs}
        steps = max(int(rep.lengths[c]) for rep, cs in in_group for c in cs)
        for s in range(1, steps):
            batch = []  # (rep, chain, candidate)
            for rep, cs in in_group:
                for c in cs:
                    if s < rep.lengths[c]:
                        batch.append((rep, c, _propose(rep, rep.new_x[c][-1])))
            cand = np.stack([v for _, _, v in batch])
            out = store.evaluate(f"subset-L{level}-g{gi}-s{s}", "subset", cand, pb.forward)
            gc = np.asarray(out["margin"], float)
            for (rep, c, v), gv in zip(batch, gc, strict=True):
                ok = gv < rep.threshold
                rep.new_x[c].append(v if ok else rep.new_x[c][-1])
                rep.new_g[c].append(gv if ok else rep.new_g[c][-1])
                acc[(id(rep), c)].append(ok)
                rep.runs += 1
            if bar is not None:
                bar.update(len(batch))
        for rep, cs in in_group:  # Papaioannou et al. Eq. 25-26, the ERA code's aCS
            per_chain = [np.mean(acc[(id(rep), c)]) for c in cs if acc[(id(rep), c)]]
            a_hat = float(np.mean(per_chain)) if per_chain else 0.0
            rep.lam = float(np.exp(np.log(rep.lam) + (a_hat - TARGET_ACCEPTANCE) / np.sqrt(gi + 1)))
            rep.levels[-1].setdefault("acceptance", []).append(a_hat)
    for rep in active:
        _collect(rep)
        lv = rep.levels[-1]
        lv["acceptance"] = float(np.mean(lv["acceptance"]))
        lv["lambda"] = rep.lam
        lv["sigma"] = [float(v) for v in np.minimum(1.0, rep.lam * rep.sigma_hat)]


def _collect(rep: _Replicate) -> None:
    """The grown chains become the replicate's population."""
    rep.chains, xs, gs, k = [], [], [], 0
    for cx, cg in zip(rep.new_x, rep.new_g, strict=True):
        rep.chains.append(list(range(k, k + len(cx))))
        xs.extend(cx)
        gs.extend(cg)
        k += len(cx)
    rep.xs, rep.g = np.asarray(xs), np.asarray(gs, float)


def _extend(pb, store, bar, reps: list) -> None:
    """Spend what each replicate has left on its last population: more steps of its chains
    (the last level's proposal, fixed) or, at level 0, more i.i.d. draws."""
    for rep in reps:
        rep.left = rep.share - rep.runs
    # level-0 replicates: i.i.d. draws, one batch
    iid = [rep for rep in reps if rep.chains is None and rep.left > 0]
    if iid:
        xs = [rep.rng.standard_normal((rep.left, rep.xs.shape[1])) for rep in iid]
        out = store.evaluate("subset-X0", "subset", np.concatenate(xs), pb.forward)
        gc, lo = np.asarray(out["margin"], float), 0
        for rep, x in zip(iid, xs, strict=True):
            rep.xs = np.concatenate([rep.xs, x])
            rep.g = np.concatenate([rep.g, gc[lo : lo + len(x)]])
            rep.runs += len(x)
            lo += len(x)
        if bar is not None:
            bar.update(lo)
    # chain replicates: rounds of one step of (some of) their chains
    todo = [rep for rep in reps if rep.chains is not None and rep.left > 0]
    for rep in todo:
        rep.new_x = [[rep.xs[c[-1]]] for c in rep.chains]
        rep.new_g = [[rep.g[c[-1]]] for c in rep.chains]
    s = 0
    while True:
        batch = []
        for rep in todo:
            for c in range(len(rep.chains)):
                if rep.left > 0:
                    batch.append((rep, c, _propose(rep, rep.new_x[c][-1])))
                    rep.left -= 1
        if not batch:
            break
        cand = np.stack([v for _, _, v in batch])
        out = store.evaluate(f"subset-X-s{s}", "subset", cand, pb.forward)
        for (rep, c, v), gv in zip(batch, np.asarray(out["margin"], float), strict=True):
            ok = gv < rep.threshold
            rep.new_x[c].append(v if ok else rep.new_x[c][-1])
            rep.new_g[c].append(gv if ok else rep.new_g[c][-1])
            rep.runs += 1
        if bar is not None:
            bar.update(len(batch))
        s += 1
    for rep in todo:  # append the extension to the chains (the first entry is the chain's end)
        n = len(rep.g)
        xs, gs = list(rep.xs), list(rep.g)
        for c, (cx, cg) in enumerate(zip(rep.new_x, rep.new_g, strict=True)):
            extra = list(range(n, n + len(cx) - 1))
            rep.chains[c] = rep.chains[c] + extra
            xs.extend(cx[1:])
            gs.extend(cg[1:])
            n += len(cx) - 1
        rep.xs, rep.g = np.asarray(xs), np.asarray(gs, float)


def _estimate(reps: list, spec, wall: float) -> dict:
    rows = []
    for rep in reps:
        n = len(rep.g)
        p_last = float(np.mean(rep.g < 0))
        d2 = rep.delta2
        if p_last > 0:
            ind = _chain_indicators(rep, 0.0)
            gam = 0.0 if ind is None else _gamma(ind)
            d2 += (1 - p_last) / (n * p_last) * (1 + gam)
        p = float(np.prod(rep.probs)) * p_last
        rows.append(
            {
                "p": p,
                # level 0's i.i.d. draws (more when no level followed and the budget's rest
                # drew more of them)
                "iid_draws": int(n if rep.chains is None else spec.n_level),
                "cov_au_beck": float(np.sqrt(d2)) if p > 0 else None,
                "levels": rep.levels,
                "p_last": p_last,
                "states_last": int(n),
                "runs": int(rep.runs),
                "converged": bool(rep.converged),
            }
        )
    return {
        **combine(rows),
        "wall_s": wall,
        "replicates": rows,
        "level_size": int(spec.n_level),
    }


def _upper_without_failures(replicates: list[dict]) -> float:
    """The 95 % interval's upper end when no replicate ends with a failing state: the
    97.5 % Clopper-Pearson bound after no failure in the replicates' level-0 draws, which are
    i.i.d. from N(0, I) (a failing draw there would have stayed a seed to the last level).
    The levels' product would give a tighter bound, but one that rests on the chains having
    explored F_L, which is what a zero estimate puts in doubt. nan for replicates without
    the count."""
    try:
        n = sum(int(r["iid_draws"]) for r in replicates)
    except KeyError:
        return float("nan")
    return float(1.0 - 0.025 ** (1.0 / max(n, 1)))


def combine(replicates: list[dict]) -> dict:
    """The estimate of independent replicates (dicts with p, cov_au_beck, runs, converged,
    iid_draws): their mean, its CoV from their sample standard deviation,
    and the 95 % interval, lognormal with that CoV and Student's t quantile of R - 1 degrees
    of freedom; with no failure in any replicate, [0, an upper bound]
    (:func:`_upper_without_failures`)."""
    ps = np.asarray([r["p"] for r in replicates], float)
    R = len(ps)
    p = float(ps.mean())
    se = float(ps.std(ddof=1) / np.sqrt(R)) if R > 1 else float("inf")
    cov = se / p if p > 0 else float("inf")
    t = float(stats.t.ppf(0.975, R - 1)) if R > 1 else float("inf")
    if p > 0 and np.isfinite(cov):
        s = np.sqrt(np.log1p(cov * cov))
        ci = [p * float(np.exp(-t * s)), p * float(np.exp(t * s))]
    else:
        ci = [0.0, _upper_without_failures(replicates)]
    ab = [r.get("cov_au_beck") for r in replicates]
    return {
        "p": p,
        "cov": cov,
        "ci95": ci,
        "runs": int(sum(r["runs"] for r in replicates)),
        # the formula's CoV of the mean, for comparison (None: a replicate saw no failure)
        "cov_au_beck": (
            float(np.sqrt(np.mean(np.square(ab)) / R)) if all(c is not None for c in ab) else None
        ),
        # every replicate ended at a population with >= p0 N failures (else its budget
        # ended the levels: its last fraction, below p0, is still counted)
        "converged": bool(all(r["converged"] for r in replicates)),
    }
