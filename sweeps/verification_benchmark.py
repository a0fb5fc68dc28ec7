"""The verification's benchmarks on paper 003's thesis-vbar under its initial-condition
distribution (``--dispersion paper003``): worst-case search against the baselines, the
failure probability by subset simulation and importance sampling against a large crude Monte
Carlo, a rarer event, and OpenTURNS on the same limit-state function.

    python sweeps/verification_benchmark.py worst --out DIR [--requirement keep-out]
    python sweeps/verification_benchmark.py probability --out DIR [--mc 20000]
    python sweeps/verification_benchmark.py rare --out DIR --depth 20 --loose 2
    python sweeps/verification_benchmark.py openturns --out DIR [--level-size 1000]
    python sweeps/verification_benchmark.py gradcheck --out DIR

Every part writes its evaluations under DIR (resumable: run the same command again) and
prints a table; ``--json`` prints the figures. The keep-out margins of the Monte Carlo are the
clearances, so one Monte Carlo gives P(breach deeper than X) for every X.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from rvdjax.verify.evaluate import ProblemSpec, problem_for
from rvdjax.verify.probability import ProbabilitySpec, clopper_pearson, estimate
from rvdjax.verify.store import EvalStore, read_evals
from rvdjax.verify.worst import SearchSpec, search

SCENARIO, DISPERSION = "thesis-vbar", "paper003"


def _problem(requirement: str):
    return problem_for(ProblemSpec(SCENARIO, requirement, DISPERSION))


def _store(out: Path, name: str, pb):
    d = out / name
    d.mkdir(parents=True, exist_ok=True)
    return EvalStore(d, pb.effort_key, {"problem": pb.definition()})


def cmd_worst(args) -> dict:
    pb = _problem(args.requirement)
    spec = SearchSpec(
        methods=tuple(args.methods.split(",")),
        budget=args.budget,
        repeats=args.repeats,
        lr=args.lr,
        seed=args.seed,
    )
    tag = args.requirement.replace(">=", "_ge_").replace("<=", "_le_")
    traces = search(pb, spec, _store(Path(args.out), f"worst-{tag}", pb))
    rows = {m: t.summary() for m, t in traces.items()}
    print(
        f"worst case: {SCENARIO} {args.requirement} under {DISPERSION}, {spec.repeats} repeats, "
        f"budget {spec.budget} forward evaluations each"
    )
    print(f"  {'method':<10}{'falsified':>10}{'median':>9}{'mean':>9}{'worst':>10}{'wall s':>8}")
    for m, r in rows.items():
        med = "-" if r["median_evaluations"] is None else f"{r['median_evaluations']:.1f}"
        mean = "-" if r["mean_evaluations"] is None else f"{r['mean_evaluations']:.1f}"
        print(
            f"  {m:<10}{r['falsification_rate']:>10.0%}{med:>9}{mean:>9}"
            f"{r['worst_margin']:>10.3g}{r['wall_s']:>8.0f}"
        )
    g, rnd = rows.get("gradient"), rows.get("random")
    if g and rnd and g["median_evaluations"] and rnd["median_evaluations"]:
        print(
            f"  gradient / random median evaluations: "
            f"{g['median_evaluations'] / rnd['median_evaluations']:.2f} "
            f"(a gradient costs {g['gradient_cost']:.2f} forward evaluations)"
        )
    return {"worst": rows}


def _mc_margins(out: Path) -> np.ndarray:
    df = read_evals(out / "mc")
    return df["margin"].to_numpy(float)


def cmd_probability(args) -> dict:
    out = Path(args.out)
    pb = _problem("keep-out")
    res = {}
    budgets = {"mc": args.mc, "subset": args.subset, "is": args.is_budget}
    for method in args.methods.split(","):
        budget, name = budgets[method], method
        t0 = time.perf_counter()
        r = estimate(pb, ProbabilitySpec(method, budget, seed=args.seed), _store(out, name, pb))
        r["wall_s"] = time.perf_counter() - t0
        r.pop("history", None)
        res[method] = r
    if "mc" not in res:  # read the Monte Carlo already flown
        g = _mc_margins(out)
        k = int(np.sum(g < 0))
        res = {"mc": {"p": k / len(g), "ci95": clopper_pearson(k, len(g)), "runs": len(g),
                      "cov": float(np.sqrt((1 - k / len(g)) / k))}, **res}  # fmt: skip
    lo, hi = res["mc"]["ci95"]
    print(f"P(keep-out breach) on {SCENARIO} under {DISPERSION}:")
    print(
        f"  {'method':<8}{'p':>10}{'CoV':>7}{'95 % interval':>24}{'runs':>7}{'CoV 0.3 needs':>14}"
    )
    for m, r in res.items():
        cov = "-" if r["cov"] is None else f"{r['cov']:.3f}"
        inside = "" if m == "mc" else ("  in MC's interval" if lo <= r["p"] <= hi else "  OUTSIDE")
        print(
            f"  {m:<8}{r['p']:>10.3e}{cov:>7}  [{r['ci95'][0]:.2e}, {r['ci95'][1]:.2e}]"
            f"{r['runs']:>7}{r.get('runs_for_cov_0.3', '-'):>14}{inside}"
        )
    return {"probability": res}


def cmd_rare(args) -> dict:
    out = Path(args.out)
    g = _mc_margins(out)
    res = {}
    for depth, budget in ((args.loose, args.budget), (args.depth, args.budget)):
        req = f"keep-out>={-depth:g}"
        pb = _problem(req)
        t0 = time.perf_counter()
        r = estimate(
            pb,
            ProbabilitySpec("subset", budget, level_size=args.level_size, seed=args.seed),
            _store(out, f"rare-{depth:g}", pb),
        )
        r["wall_s"] = time.perf_counter() - t0
        k = int(np.sum(g < -depth))
        r["mc"] = {"p": k / len(g), "ci95": clopper_pearson(k, len(g)), "runs": len(g)}
        if r["cov"]:
            r["mc_runs_for_cov"] = float((1 - r["p"]) / (r["p"] * r["cov"] ** 2))
        res[req] = r
        print(
            f"  {req}: subset p = {r['p']:.3e} (CoV {r['cov']}, [{r['ci95'][0]:.2e}, "
            f"{r['ci95'][1]:.2e}]) in {r['runs']} runs, {r['wall_s']:.0f} s; crude MC of "
            f"{len(g)}: {k} failures, p = {k / len(g):.2e} [{r['mc']['ci95'][0]:.1e}, "
            f"{r['mc']['ci95'][1]:.1e}]; MC for this CoV: {r.get('mc_runs_for_cov', 0):.3g} runs"
        )
    return {"rare": res}


def cmd_openturns(args) -> dict:
    import openturns as ot

    out = Path(args.out)
    pb = _problem("keep-out")
    store = _store(out, "openturns", pb)
    count = {"n": 0, "batch": 0}

    def g(X):
        X = np.asarray(X, float)
        r = store.evaluate(f"ot-{count['batch']}", "openturns", X, pb.forward)
        count["n"] += len(X)
        count["batch"] += 1
        return [[float(v)] for v in r["margin"]]

    f = ot.PythonFunction(pb.dim, 1, func_sample=g)
    X = ot.RandomVector(ot.Normal(pb.dim))
    Y = ot.CompositeRandomVector(f, X)
    event = ot.ThresholdEvent(Y, ot.Less(), 0.0)
    ot.RandomGenerator.SetSeed(args.seed)
    t0 = time.perf_counter()
    algo = ot.SubsetSampling(event)
    algo.setMaximumOuterSampling(1)
    algo.setBlockSize(args.level_size)
    algo.run()
    r = algo.getResult()
    ss = {
        "p": r.getProbabilityEstimate(),
        "cov": r.getCoefficientOfVariation(),
        "runs": count["n"],
        "wall_s": time.perf_counter() - t0,
    }
    n0 = count["n"]
    t0 = time.perf_counter()
    solver = ot.Cobyla()  # derivative-free: OpenTURNS' FORM on the exact margin
    solver.setMaximumCallsNumber(args.form_calls)
    solver.setStartingPoint(ot.Point(pb.dim, 0.0))
    print(
        f"OpenTURNS SubsetSampling: p = {ss['p']:.3e} (CoV {ss['cov']:.3f}) in {ss['runs']} runs,"
        f" {ss['wall_s']:.0f} s"
    )
    form = ot.FORM(solver, event)
    try:
        form.run()
        fr = form.getResult()
        fm = {
            "p": fr.getEventProbability(),
            "beta": fr.getHasoferReliabilityIndex(),
            "design_point": list(fr.getStandardSpaceDesignPoint()),
        }
        print(f"OpenTURNS FORM (Cobyla): p = {fm['p']:.3e}, beta = {fm['beta']:.3f}")
    except RuntimeError as err:  # e.g. the design point is not on the limit state
        fm = {"error": str(err).splitlines()[-1]}
        print(f"OpenTURNS FORM (Cobyla) failed: {fm['error']}")
    fm.update(runs=count["n"] - n0, wall_s=time.perf_counter() - t0)
    print(f"  FORM: {fm['runs']} runs, {fm['wall_s']:.0f} s")
    return {"openturns": {"subset": ss, "form": fm}}


def cmd_gradcheck(args) -> dict:
    """The smooth margin's gradient at the worst point of the ``worst`` part against central
    differences of the smooth margin."""
    pb = _problem("keep-out")
    df = read_evals(Path(args.out) / "worst-keep-out")
    xi = np.asarray(df.loc[df["margin"].idxmin(), "xi"], float)
    out = {}
    for h in (1e-4, 1e-5, 1e-6):
        pts = np.concatenate([[xi], xi + h * np.eye(pb.dim), xi - h * np.eye(pb.dim)])
        r = pb.gradient(pts)
        fd = (r["smooth"][1 : 1 + pb.dim] - r["smooth"][1 + pb.dim :]) / (2 * h)
        g = r["grad"][0]
        rel = float(np.linalg.norm(g - fd) / np.linalg.norm(fd))
        out[f"{h:g}"] = {"grad": g.tolist(), "central": fd.tolist(), "relative_error": rel}
        print(f"  h = {h:g}: |grad - central| / |central| = {rel:.2e}")
    print(f"  at xi = {np.round(xi, 3).tolist()}, exact margin {float(df['margin'].min()):.3g} m")
    return {"gradcheck": out}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    w = sub.add_parser("worst")
    w.add_argument("--requirement", default="keep-out")
    w.add_argument("--methods", default="gradient,random,lhs,cma-es")
    w.add_argument("--budget", type=int, default=200)
    w.add_argument("--repeats", type=int, default=20)
    w.add_argument("--lr", type=float, default=2.0)
    p = sub.add_parser("probability")
    p.add_argument("--mc", type=int, default=20000)
    p.add_argument("--subset", type=int, default=3000)
    p.add_argument("--is-budget", type=int, default=3000)
    p.add_argument("--methods", default="mc,subset,is")
    r = sub.add_parser("rare")
    r.add_argument("--depth", type=float, required=True, help="breach depth of the rare event [m]")
    r.add_argument("--loose", type=float, required=True, help="a depth MC resolves [m]")
    r.add_argument("--budget", type=int, default=8000)
    r.add_argument("--level-size", type=int, default=1000)
    gc = sub.add_parser("gradcheck")
    o = sub.add_parser("openturns")
    o.add_argument("--level-size", type=int, default=1000)
    o.add_argument("--form-calls", type=int, default=200)
    for q in (w, p, r, o, gc):
        q.add_argument("--out", required=True)
        q.add_argument("--seed", type=int, default=0)
        q.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    res = {
        "worst": cmd_worst,
        "probability": cmd_probability,
        "rare": cmd_rare,
        "gradcheck": cmd_gradcheck,
    }.get(args.cmd, cmd_openturns)(args)
    path = Path(args.out) / f"{args.cmd}.json"
    path.write_text(json.dumps(res, indent=2, default=float))
    if args.json:
        print(json.dumps(res, indent=2, default=float))


if __name__ == "__main__":
    main()
