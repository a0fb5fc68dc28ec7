"""Importance sampling's coverage on a surrogate of thesis-vbar's failure set, in seconds.

The surrogate: each point xi's margin is that of its nearest neighbour among the crude Monte
Carlo reference's runs (``DIR/reference``, ``sweeps/verification_benchmark.py``), so its
failure set is the reference's scattered needles; its p is measured by 2e6 draws. Beside it,
limit states with exact probabilities: linear at 5e-3 and 1e-5, two half-spaces. For each,
``--seeds`` estimates at the coverage benchmark's budgets, and the share of 95 % intervals
that hold the truth: today's (t quantile of ess - 1) and, from the same estimates, a normal
quantile (p +- 1.96 sd).

    python sweeps/is_surrogate.py --out DIR [--seeds 100]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import norm

from rvdjax.verify.probability import ProbabilitySpec, importance_side_by_side
from rvdjax.verify.store import EvalStore, read_evals


class Nearest:
    """The margin of the nearest reference run, offset by ``depth`` (a breach deeper than
    ``depth`` metres fails)."""

    effort_key = "x"
    dim = 5

    def __init__(self, xi, margin, depth):
        self.tree, self.margin, self.depth = cKDTree(xi), margin, depth

    def forward(self, xi):
        return {"margin": self.margin[self.tree.query(xi)[1]] + self.depth}

    def definition(self):
        return {"surrogate": "nearest reference run", "depth": self.depth}


class Linear:
    effort_key = "x"

    def __init__(self, beta, dim=5, two_sided=False):
        self.beta, self.dim, self.two = beta, dim, two_sided
        self.a = np.ones(dim) / np.sqrt(dim)

    def forward(self, xi):
        s = xi @ self.a
        return {"margin": self.beta - (np.abs(s) if self.two else s)}

    def definition(self):
        return {"beta": self.beta, "two_sided": self.two}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, help="the benchmark's DIR (holds reference/)")
    ap.add_argument("--seeds", type=int, default=100)
    args = ap.parse_args(argv)
    ref = read_evals(Path(args.out) / "reference")
    xi, g = np.stack(ref["xi"].to_numpy()), ref["margin"].to_numpy(float)
    z = np.random.default_rng(123).standard_normal((2_000_000, 5))
    cases = []
    for depth, budget in ((0.0, 800), (10.0, 1280)):
        pb = Nearest(xi, g, depth)
        cases.append((f"surrogate, {depth:g} m", pb, budget, np.mean(pb.forward(z)["margin"] < 0)))
    beta = -norm.ppf(5e-3)
    cases += [
        ("linear, 5e-3", Linear(beta), 800, 5e-3),
        ("linear, 1e-5", Linear(4.265), 1500, norm.cdf(-4.265)),
        ("two half-spaces", Linear(3.0, two_sided=True), 3000, 2 * norm.cdf(-3.0)),
    ]
    print("| case | p | runs | coverage (t of ess - 1) | coverage (normal) | mean / p | CoV |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for name, pb, budget, p in cases:
        specs = [ProbabilitySpec("is", budget, seed=s) for s in range(args.seeds)]
        runs = importance_side_by_side(pb, specs, EvalStore(), progress=False)
        est = np.array([r["p"] for r in runs])
        t_cov = np.mean([r["ci95"][0] <= p <= r["ci95"][1] for r in runs])
        n_cov = np.mean(
            [
                abs(r["p"] - p) <= 1.96 * r["cov"] * r["p"]
                if r["p"] > 0
                else r["ci95"][0] <= p <= r["ci95"][1]
                for r in runs
            ]
        )
        print(f"| {name} | {p:.3g} | {budget} | {t_cov:.0%} | {n_cov:.0%} | "
              f"{est.mean() / p:.2f} | {est.std(ddof=1) / est.mean():.2f} |")  # fmt: skip


if __name__ == "__main__":
    main()
