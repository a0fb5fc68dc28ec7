"""Worst-case search over the dispersions: gradient steps on the smooth margin against
derivative-free baselines, at the same budget of closed-loop evaluations.

Methods (every repeat is seeded; the repeats of a method fly as one batch):

* ``gradient``: ``starts`` points per repeat (drawn from N(0, I)), all repeats' starts in
  one gradient batch. At each start the smooth margin's gradient gives a direction d (unit,
  in standard deviations); one forward batch then judges, by the exact margin, the points
  xi + a d for a line-search ladder a = step x (0.5, 1, 2, 4) (scaled per start: doubled
  after a success, halved after a failed search) and the HL-RF point, where the linear model
  of the exact margin m with the smooth slope |g| crosses below zero (a = 1.05 m / |g|). The
  start moves to its best candidate when that improves its exact margin. An iteration costs
  ``starts`` x (gradient cost + ladder + 1) forward evaluations per repeat.
* ``design-point``: the most probable failure point (FORM's design point) by improved HL-RF
  iterations (Zhang & Der Kiureghian 1995) on the same linearisation (the exact margin's
  value, the smooth margin's gradient), with a batched line search on the merit
  |xi|^2 / 2 + c |m|. Every start's smallest-norm failing point is kept.
* ``random``: xi drawn from the dispersion (N(0, I), kept in the region): crude Monte Carlo.
* ``lhs``: a Latin hypercube of the budget's size per repeat (scipy.stats.qmc), mapped
  through the normal quantile.
* ``cma-es``: CMA-ES (the ``cma`` package) on the exact margin, population lambda.

A gradient evaluation is counted at its measured cost (:meth:`Problem.gradient_cost`): its
wall time per run over that of the same runs flown forward in the same way (a ``vmap`` of
the loop in which every run pays every step, as the gradient does). Zeroed back-solves and
non-finite gradients are counted and reported.

ARCH-COMP's figures: the *falsification rate* is the fraction of repeats that found a
violation (exact margin < 0); *evaluations* are the forward evaluations spent up to and
including the one that found it (a batch counts whole: a CMA-ES generation, a gradient
iteration or a line search of every start of a repeat).
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from rvdjax.verify.evaluate import Problem
from rvdjax.verify.store import EvalStore

__all__ = ["SearchSpec", "search", "METHODS", "project"]

METHODS = ("gradient", "random", "lhs", "cma-es", "design-point")
TAIL = 1e-6  # the default search region leaves out this much of N(0, I)


@dataclasses.dataclass(frozen=True)
class SearchSpec:
    """A worst-case search (plain data).

    Attributes:
        methods: the methods flown (:data:`METHODS`).
        budget: forward evaluations per repeat and method.
        repeats: seeded repeats of every method.
        region: "ball" or "box"; radius: its k (in standard deviations; None: the radius
            of the ball that holds all but 1e-6 of N(0, I) in the dispersion's dimension,
            sqrt(chi2.ppf(1 - 1e-6, d)): 6.0 for 5 coordinates, 18.9 for 240).
        starts: gradient starts per repeat.
        step: the line search's base step [sigma]: the ladder is step x (0.5, 1, 2, ...),
            scaled per start (doubled after a success, halved after a failed search).
        ladder: line-search steps per start and iteration (plus the HL-RF point).
        popsize: CMA-ES population.
        seed: the first repeat's seed (repeat r uses seed + r).
        gradient_cost: forward evaluations a gradient evaluation counts for (None: measured
            in the run, :meth:`Problem.gradient_cost`).
        engine_cost: also measure, for the report only, a gradient's wall time over the
            batch engine's per run (:meth:`Problem.gradient_cost_engine`: two engine flights
            of 64 runs; the command line and the benchmark report it).
    """

    methods: tuple = ("gradient", "random", "lhs", "cma-es")
    budget: int = 100
    repeats: int = 20
    region: str = "ball"
    radius: float | None = None
    starts: int = 2
    step: float = 1.0
    ladder: int = 4
    popsize: int = 8
    seed: int = 0
    gradient_cost: float | None = None
    engine_cost: bool = False

    def __post_init__(self):
        object.__setattr__(self, "methods", tuple(self.methods))
        for m in self.methods:
            if m not in METHODS:
                raise ValueError(f"--methods: unknown method {m!r}; allowed: {', '.join(METHODS)}")
        if self.region not in ("ball", "box"):
            raise ValueError(f"--region must be ball or box, got {self.region!r}")
        if self.radius is not None and not (0 < self.radius < float("inf")):
            raise ValueError(f"--radius must be > 0 (standard deviations), got {self.radius}")
        for name in ("repeats", "starts", "popsize", "ladder"):
            v = getattr(self, name)
            if not (isinstance(v, (int, np.integer)) and v >= 1):
                raise ValueError(f"--{name} must be an integer >= 1, got {v!r}")
        if not (0 < self.step < float("inf")):
            raise ValueError(f"--step must be > 0 (standard deviations), got {self.step}")

    def resolved(self, dim: int) -> SearchSpec:
        """The spec with its region's radius for ``dim`` coordinates (module docstring): a
        ball of radius 5 holds almost none of N(0, I) in 240 dimensions, where draws lie
        near sqrt(240) = 15.5."""
        if self.radius is not None:
            return self
        from scipy.stats import chi2

        return dataclasses.replace(self, radius=float(np.sqrt(chi2.ppf(1 - TAIL, dim))))

    def check_budget(self, gradient_cost: float = 1.0) -> None:
        """ValueError when the budget cannot hold one round of every method."""
        one = int(np.ceil(self.starts * (gradient_cost + self.ladder + 1)))
        need = {"random": 1, "lhs": 2, "cma-es": self.popsize, "gradient": one, "design-point": one}
        for m in self.methods:
            if self.budget < need[m]:
                raise ValueError(
                    f"--budget {self.budget}: {m} needs at least {need[m]} forward evaluations "
                    "per repeat"
                )


def project(xi, region: str, radius: float):
    """xi (..., d) moved into the search region."""
    xi = np.asarray(xi, float)
    if region == "box":
        return np.clip(xi, -radius, radius)
    n = np.linalg.norm(xi, axis=-1, keepdims=True)
    return xi * np.minimum(1.0, radius / np.maximum(n, 1e-300))


@dataclasses.dataclass
class Trace:
    """One method's record per repeat: evaluations spent and best margin after each batch,
    the evaluations to the first violation (None: none found), the worst point."""

    evals: list  # per repeat: (n,) cumulative evaluations after each batch
    best: list  # per repeat: (n,) best exact margin so far
    first: list  # per repeat: evaluations to the first violation or None
    worst_margin: np.ndarray  # (R,)
    worst_xi: np.ndarray  # (R, d)
    worst_run: np.ndarray  # (R,) run number of the worst point
    wall_s: float
    extra: dict = dataclasses.field(default_factory=dict)

    def summary(self) -> dict:
        found = [f for f in self.first if f is not None]
        return {
            "falsification_rate": len(found) / len(self.first),
            "median_evaluations": float(np.median(found)) if found else None,
            "mean_evaluations": float(np.mean(found)) if found else None,
            "worst_margin": float(np.min(self.worst_margin)),
            "wall_s": self.wall_s,
            **self.extra,
        }


class _Tracker:
    def __init__(self, R: int, d: int):
        self.evals = [[] for _ in range(R)]
        self.best = [[] for _ in range(R)]
        self.first = [None] * R
        self.spent = np.zeros(R)
        self.worst = np.full(R, np.inf)
        self.worst_xi = np.zeros((R, d))
        self.worst_run = np.full(R, -1)

    def add(self, r: int, cost: float, margins, xis, runs, sequential: bool = False):
        """A batch of repeat r: ``cost`` evaluations; ``sequential``: its points count one
        by one (independent draws), else the batch counts whole."""
        margins = np.asarray(margins, float)
        if self.first[r] is None and np.any(margins < 0):
            k = int(np.argmax(margins < 0))
            self.first[r] = self.spent[r] + (k + 1 if sequential else cost)
        self.spent[r] += cost
        i = int(np.argmin(margins))
        if margins[i] < self.worst[r]:
            self.worst[r], self.worst_xi[r], self.worst_run[r] = margins[i], xis[i], runs[i]
        self.evals[r].append(self.spent[r])
        self.best[r].append(self.worst[r])

    def trace(self, wall: float, **extra) -> Trace:
        return Trace(
            [np.asarray(e) for e in self.evals],
            [np.asarray(b) for b in self.best],
            self.first,
            self.worst,
            self.worst_xi,
            self.worst_run,
            wall,
            extra,
        )


def _split(res: dict, sizes) -> list[dict]:
    out, lo = [], 0
    for n in sizes:
        out.append({k: v[lo : lo + n] for k, v in res.items() if isinstance(v, np.ndarray)})
        lo += n
    return out


def _sampling(pb: Problem, spec: SearchSpec, store: EvalStore, method: str, bar) -> Trace:
    """random / lhs: per repeat ``budget`` points, flown in blocks across the repeats."""
    from scipy.stats import norm, qmc

    R, d, B = spec.repeats, pb.dim, spec.budget
    pts = []
    for r in range(R):
        rng = np.random.default_rng([spec.seed + r, 1 if method == "random" else 2])
        if method == "random":
            x = rng.standard_normal((B, d))
            if spec.region == "ball":  # keep the draws inside (rejection)
                bad = np.linalg.norm(x, axis=1) > spec.radius
                while bad.any():
                    x[bad] = rng.standard_normal((int(bad.sum()), d))
                    bad = np.linalg.norm(x, axis=1) > spec.radius
            else:
                x = np.clip(x, -spec.radius, spec.radius)
        else:
            u = qmc.LatinHypercube(d=d, seed=rng).random(B)
            x = project(norm.ppf(np.clip(u, 1e-12, 1 - 1e-12)), spec.region, spec.radius)
        pts.append(x)
    tr = _Tracker(R, d)
    t0 = time.perf_counter()
    block = max(1, 256 // R)
    for lo in range(0, B, block):
        xs = np.concatenate([p[lo : lo + block] for p in pts])
        res = store.evaluate(f"{method}-{lo}", method, xs, pb.forward)
        n = min(block, B - lo)
        for r, part in enumerate(_split(res, [n] * R)):
            tr.add(r, n, part["margin"], part["xi"], part["run"], sequential=True)
        if bar is not None:
            bar.update(len(xs))
    return tr.trace(time.perf_counter() - t0)


def _cma(pb: Problem, spec: SearchSpec, store: EvalStore, bar) -> Trace:
    import cma

    R, d, lam = spec.repeats, pb.dim, spec.popsize
    opts = {"popsize": lam, "verbose": -9, "tolfun": 0, "tolx": 0, "tolstagnation": 10**9}
    if spec.region == "box":
        opts["bounds"] = [-spec.radius, spec.radius]
    es = []
    for r in range(R):
        o = dict(opts, seed=int(spec.seed + r + 1))
        es.append(cma.CMAEvolutionStrategy(np.zeros(d), 1.0, o))
    tr = _Tracker(R, d)
    t0 = time.perf_counter()
    gens = spec.budget // lam
    for gen in range(gens):
        asked = [np.asarray(e.ask()) for e in es]
        xs = np.concatenate([project(a, spec.region, spec.radius) for a in asked])
        res = store.evaluate(f"cma-es-{gen}", "cma-es", xs, pb.forward)
        for r, part in enumerate(_split(res, [lam] * R)):
            # CMA-ES sees the exact margin of the projected point, plus the distance it was
            # moved (a penalty that keeps it inside the ball)
            moved = np.linalg.norm(part["xi"] - asked[r], axis=1)
            es[r].tell(list(asked[r]), list(part["margin"] + moved))
            tr.add(r, lam, part["margin"], part["xi"], part["run"])
        if bar is not None:
            bar.update(len(xs))
    return tr.trace(time.perf_counter() - t0)


def _directions(g, rng):
    """Unit descent directions -g/|g| (rows); a zero or non-finite gradient gets a random
    direction (counted by the caller)."""
    n = np.linalg.norm(g, axis=1, keepdims=True)
    ok = np.isfinite(n) & (n > 0)
    rand = rng.standard_normal(g.shape)
    rand /= np.linalg.norm(rand, axis=1, keepdims=True)
    return np.where(ok, -g / np.where(ok, n, 1.0), rand), n[:, 0], ok[:, 0]


def _gradient(pb: Problem, spec: SearchSpec, store: EvalStore, method: str, bar) -> Trace:
    """Multi-start descent in units of sigma (module docstring): a gradient batch at every
    start, then one forward batch of candidates per start (the line-search ladder and the
    HL-RF point for ``gradient``; the iHL-RF line search for ``design-point``); each start
    moves to its best candidate."""
    R, d, K = spec.repeats, pb.dim, spec.starts
    cost = spec.gradient_cost or pb.gradient_cost(R * K)
    L = spec.ladder
    per_iter = K * (cost + L + 1)  # forward evaluations per repeat and iteration
    iters = max(1, int(spec.budget // per_iter))
    rng = np.random.default_rng([spec.seed, 3])
    xi = np.stack(
        [
            project(
                np.random.default_rng([spec.seed + r, 3]).standard_normal((K, d)),
                spec.region,
                spec.radius,
            )
            for r in range(R)
        ]
    ).reshape(R * K, d)
    ladder = spec.step * 2.0 ** np.arange(-1, L - 1)  # e.g. 0.5, 1, 2, 4 sigma
    trust = np.ones(R * K)  # per start: the ladder's scale (halved after a failed search)
    tr = _Tracker(R, d)
    best_norm = np.full(R, np.inf)
    best_dp = np.full((R, d), np.nan)
    counts = {"zeroed_backsolves": 0, "nonfinite_gradients": 0, "random_directions": 0}
    t0 = time.perf_counter()

    def note_failures(xs, ms, per: int):
        """Keep each repeat's smallest-norm failing point (``per`` points a repeat)."""
        for j in np.flatnonzero(ms < 0):
            r = j // per
            nj = float(np.linalg.norm(xs[j]))
            if nj < best_norm[r]:
                best_norm[r], best_dp[r] = nj, xs[j]

    for it in range(iters):
        res = store.evaluate(f"{method}-{it}", method, xi, pb.gradient)
        m, g = np.asarray(res["margin"], float), np.asarray(res["grad"], float)
        counts["zeroed_backsolves"] += int(np.sum(res.get("zeroed", 0)))
        counts["nonfinite_gradients"] += int(np.sum(res.get("nonfinite", 0)))
        for r, part in enumerate(_split(res, [K] * R)):
            tr.add(r, K * cost, part["margin"], part["xi"], part["run"])
        note_failures(xi, m, K)
        dirn, gnorm, ok = _directions(g, rng)
        counts["random_directions"] += int(np.sum(~ok))
        slope = np.where(ok, gnorm, 1.0)
        if method == "gradient":
            # along the smooth margin's descent direction: a ladder of steps in sigma (scaled
            # per start) and the HL-RF point, where the linear model of the exact margin m
            # with the smooth slope |g| crosses below 0
            steps = ladder[None, :] * trust[:, None]
            hl = np.clip((m + 0.05 * np.abs(m) + 1e-12) / slope, 0.0, 2 * spec.radius)
            steps = np.concatenate([steps, hl[:, None]], axis=1)  # (S, L + 1)
            cand = xi[:, None, :] + steps[:, :, None] * dirn[:, None, :]
        else:
            # iHL-RF (Zhang & Der Kiureghian 1995): the HL-RF point of the linearisation
            # (exact value m, smooth gradient) and a line search toward it
            gu = -dirn * slope[:, None]  # the gradient (a random one where it failed)
            target = ((np.sum(gu * xi, axis=1) - m) / slope**2)[:, None] * gu
            lam = np.concatenate([[1.0], 0.5 ** np.arange(1, L + 1)])
            cand = xi[:, None, :] + lam[None, :, None] * (target - xi)[:, None, :]
        cand = project(cand.reshape(-1, d), spec.region, spec.radius)
        res_c = store.evaluate(f"{method}-{it}-line", method, cand, pb.forward)
        mc = np.asarray(res_c["margin"], float).reshape(R * K, L + 1)
        cand = cand.reshape(R * K, L + 1, d)
        for r, part in enumerate(_split(res_c, [K * (L + 1)] * R)):
            tr.add(r, K * (L + 1), part["margin"], part["xi"], part["run"])
        note_failures(cand.reshape(-1, d), mc.reshape(-1), K * (L + 1))
        if method == "gradient":
            j = np.argmin(mc, axis=1)
            better = mc[np.arange(R * K), j] < m
        else:
            # merit 1/2 |xi|^2 + c |m| (c from the slope: a unit of margin costs 1/|g| sigma)
            c = (np.linalg.norm(xi, axis=1) / slope + 1.0)[:, None]
            merit = 0.5 * np.sum(cand**2, axis=2) + c * np.abs(mc)
            now = 0.5 * np.sum(xi**2, axis=1) + c[:, 0] * np.abs(m)
            j = np.argmin(merit, axis=1)
            better = merit[np.arange(R * K), j] < now
        xi = np.where(better[:, None], cand[np.arange(R * K), j], xi)
        trust = np.where(better, np.minimum(trust * (2.0 if method == "gradient" else 1.0), 4.0),
                         trust * 0.5)  # fmt: skip
        if bar is not None:
            bar.update(int(np.ceil(R * per_iter)))
    extra = {"gradient_cost": cost, "iterations": iters, **counts}
    if spec.engine_cost and hasattr(pb, "gradient_cost_engine"):
        extra["gradient_cost_vs_engine"] = pb.gradient_cost_engine(R * K)
    if method == "design-point":
        ok = np.isfinite(best_norm)
        extra["design_point_norm"] = float(np.min(best_norm)) if ok.any() else None
        extra["design_point"] = (
            [float(v) for v in best_dp[int(np.argmin(best_norm))]] if ok.any() else None
        )
    return tr.trace(time.perf_counter() - t0, **extra)


def search(pb: Problem, spec: SearchSpec, store: EvalStore | None = None, progress=True) -> dict:
    """Fly the search's methods; return {method: Trace}."""
    store = EvalStore(None, pb.effort_key) if store is None else store
    spec = spec.resolved(pb.dim)
    out = {}
    for method in spec.methods:
        bar = None
        if progress:
            from tqdm.auto import tqdm

            total = spec.repeats * spec.budget
            bar = tqdm(total=total, unit="eval", desc=f"verify worst: {method}", leave=False)
        if method in ("random", "lhs"):
            out[method] = _sampling(pb, spec, store, method, bar)
        elif method == "cma-es":
            out[method] = _cma(pb, spec, store, bar)
        else:
            out[method] = _gradient(pb, spec, store, method, bar)
        if bar is not None:
            bar.close()
    return out
