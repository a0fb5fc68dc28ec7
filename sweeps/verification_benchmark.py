"""The verification's benchmarks on paper 003's thesis-vbar under its initial-condition
distribution (``--dispersion paper003``): a 1e5-run crude Monte Carlo reference, the coverage
of subset simulation's and importance sampling's intervals over independent seeds, the
worst-case search against the baselines, the gradient check at the worst case, and
OpenTURNS on the same limit-state function.

    python sweeps/verification_benchmark.py reference --out DIR [--runs 100000]
    python sweeps/verification_benchmark.py coverage --out DIR --method subset --depth 10 \
        [--seeds 20] [--budget 1280] [--level-size 100]
    python sweeps/verification_benchmark.py table --out DIR
    python sweeps/verification_benchmark.py figures --out DIR
    python sweeps/verification_benchmark.py worst --out DIR --requirement keep-out>=-10
    python sweeps/verification_benchmark.py worst --out DIR --scenario poseidyn-lqmpc \
        --dispersion nav --disturbed --n-steps 60 --requirement keep-out>=0.09 --random-p P
    python sweeps/verification_benchmark.py openturns --out DIR [--level-size 1000]
    python sweeps/verification_benchmark.py gradcheck --out DIR
    python sweeps/verification_benchmark.py sense --out DIR [--band-runs 3000] [--sample-runs 6000]

Every part writes its evaluations under DIR with their provenance (resumable: run the same
command again; another code version needs ``--allow-code-change``) and prints a table;
``--json`` prints the figures. The keep-out margins of the reference are the clearances, so
one Monte Carlo gives P(breach deeper than X) for every X.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax
import numpy as np

from rvdjax.solver import Status
from rvdjax.verify.evaluate import ProblemSpec, problem_for
from rvdjax.verify.probability import (
    ProbabilitySpec,
    clopper_pearson,
    estimate,
    importance_side_by_side,
)
from rvdjax.verify.store import PROVENANCE, EvalStore, read_evals, write_json
from rvdjax.verify.worst import SearchSpec, search

SCENARIO, DISPERSION = "thesis-vbar", "paper003"


def _problem(requirement: str):
    return problem_for(ProblemSpec(SCENARIO, requirement, DISPERSION))


ALLOW = {"code_change": False}  # --allow-code-change


def _store(out: Path, name: str, pb, **extra):
    """The evaluations of one part, with their provenance: the problem's definition and
    whatever else (``extra``) the part's batches depend on."""
    d = out / name
    d.mkdir(parents=True, exist_ok=True)
    definition = {"problem": pb.definition(), **extra}
    return EvalStore(d, pb.effort_key, definition, allow_code_change=ALLOW["code_change"])


def _tag(depth: float) -> str:
    return f"{depth:g}m"


# ----------------------------------------------------------------------------- reference


def _reference(out: Path, depth: float) -> dict:
    """P(breach deeper than ``depth``) from the reference's clearances (the verification
    directory ``out/reference``: ``rvdjax verify probability ... --method mc``)."""
    ref = out / "reference"
    g = read_evals(ref)["margin"].to_numpy(float)
    k, n = int(np.sum(g < -depth)), len(g)
    prov = json.loads((ref / PROVENANCE).read_text())
    return {
        "p": k / n,
        "failures": k,
        "runs": n,
        "ci95": list(clopper_pearson(k, n)),
        "cov": float(np.sqrt((1 - k / n) / k)) if k else None,
        "provenance": prov,
    }


def cmd_reference(args) -> dict:
    """Fly (or continue) the reference: crude Monte Carlo of ``--runs`` runs, then print
    P(breach deeper than X) for X = 0, 10, 30 m with Clopper-Pearson intervals."""
    from rvdjax.cli import main as cli

    out = Path(args.out)
    argv = [
        "verify", "probability", SCENARIO, "--requirement", "keep-out", "--dispersion",
        DISPERSION, "--method", "mc", "--budget", str(args.runs), "--seed", str(args.seed),
        "--out", str(out / "reference"), "--quiet",
    ]  # fmt: skip
    if (out / "reference" / "config.json").exists():
        argv.append("--resume")
    if ALLOW["code_change"]:
        argv.append("--allow-code-change")
    if cli(argv) != 0:
        raise SystemExit(2)
    res = {}
    for depth in (0.0, 10.0, 30.0):
        r = _reference(out, depth)
        res[_tag(depth)] = {k: v for k, v in r.items() if k != "provenance"}
        lo, hi = r["ci95"]
        print(f"  breach > {depth:g} m: {r['failures']} of {r['runs']}, p = {r['p']:.4g} "
              f"[{lo:.3g}, {hi:.3g}]")  # fmt: skip
    return {"reference": res}


# ----------------------------------------------------------------------------- coverage


def cmd_coverage(args) -> dict:
    """``--seeds`` independent estimates of P(breach deeper than ``--depth``) by one method,
    each with ``--budget`` runs. Subset simulation flies the seeds side by side: one estimate
    of seeds x replicates independent replicates (each with its own level 0 and stream),
    grouped into the seeds' estimates afterwards. Importance sampling flies the seeds side by
    side too, every stage of every seed in one engine batch.
    Writes ``coverage-METHOD-DEPTH.json``."""
    from rvdjax.verify.subset import combine

    out = Path(args.out)
    req = "keep-out" if args.depth == 0 else f"keep-out>={-args.depth:g}"
    pb = _problem(req)
    name = f"coverage-{args.method}-{_tag(args.depth)}"
    t0 = time.perf_counter()
    estimates = []
    # run again on a finished store, an estimate replays its stored runs in seconds: it keeps
    # the wall time it was flown in
    before = out / f"{name}.json"
    before = json.loads(before.read_text()) if before.exists() else None
    if args.method == "subset":
        R = args.replicates
        spec = ProbabilitySpec(
            "subset",
            args.budget * args.seeds,
            level_size=args.level_size,
            replicates=R * args.seeds,
            seed=args.seed,
        )
        store = _store(out, name, pb, method=dataclasses.asdict(spec))
        flown = store.seq
        res = estimate(pb, spec, store)
        wall = time.perf_counter() - t0
        if store.seq == flown and before is not None:  # nothing flown: a replay
            wall = before["wall_s"]
        reps = res["replicates"]
        for s in range(args.seeds):
            e = combine(reps[s * R : (s + 1) * R])
            e["wall_s"] = wall / args.seeds  # side by side: the wall time shared out
            estimates.append(e)
    else:  # importance sampling: the seeds side by side, each stage one engine batch
        specs = [ProbabilitySpec("is", args.budget, seed=args.seed + s) for s in range(args.seeds)]
        store = _store(out, name, pb, method=[dataclasses.asdict(s) for s in specs])
        flown = store.seq
        estimates = importance_side_by_side(pb, specs, store)
        wall = time.perf_counter() - t0
        if store.seq == flown and before is not None:  # nothing flown: a replay
            wall = before["wall_s"]
        for s, r in enumerate(estimates):
            r["wall_s"] = wall / args.seeds  # side by side: the wall time shared out
            print(f"  seed {s}: p = {r['p']:.4g} [{r['ci95'][0]:.3g}, {r['ci95'][1]:.3g}], "
                  f"{r['runs']} runs")  # fmt: skip
    doc = {
        "method": args.method,
        "depth_m": args.depth,
        "requirement": req,
        "seeds": args.seeds,
        "budget": args.budget,
        "level_size": args.level_size,
        "replicates": args.replicates if args.method == "subset" else None,
        "wall_s": wall,
        "estimates": [
            {
                k: v
                for k, v in e.items()
                if k in ("p", "cov", "ci95", "runs", "wall_s", "cov_au_beck", "converged")
            }  # fmt: skip
            for e in estimates
        ],
        "provenance": store.provenance_summary(),
    }
    write_json(out / f"{name}.json", doc)
    return {"coverage": _coverage_row(out, doc)}


def _coverage_row(out: Path, doc: dict) -> dict:
    p = np.array([e["p"] for e in doc["estimates"]])
    row = {
        "method": doc["method"],
        "threshold": f">= {-doc['depth_m'] + 0.0:g} m",
        "seeds": doc["seeds"],
        "runs": float(np.mean([e["runs"] for e in doc["estimates"]])),
        "wall_s": float(np.mean([e["wall_s"] for e in doc["estimates"]])),
        "mean_p": float(p.mean()),
        "sd_p": float(p.std(ddof=1)),
    }
    # an estimate of 0 (no failing draw) reports no CoV (None or inf): the mean is over the
    # others
    covs = [e["cov"] for e in doc["estimates"] if e["cov"] is not None and np.isfinite(e["cov"])]
    row["mean_cov"] = float(np.mean(covs)) if covs else None
    row["estimates_without_cov"] = len(p) - len(covs)
    row["empirical_cov"] = row["sd_p"] / row["mean_p"] if row["mean_p"] > 0 else None
    if row["empirical_cov"]:  # CoV^2 ~ 1 / n
        row["runs_for_cov_0.3"] = row["runs"] * (row["empirical_cov"] / 0.3) ** 2
    if (out / "reference" / PROVENANCE).exists():
        ref = _reference(out, doc["depth_m"])
        cover = [e["ci95"][0] <= ref["p"] <= e["ci95"][1] for e in doc["estimates"]]
        row.update(
            reference_p=ref["p"],
            coverage=float(np.mean(cover)),
            mean_over_reference=row["mean_p"] / ref["p"],
            mc_runs_for_cov_0_3=(1 - ref["p"]) / (ref["p"] * 0.09),
        )
    return row


def cmd_figures(args) -> dict:
    """The reference's breaches over the initial range and bearing, and the coverage of
    every ``coverage-*.json`` in DIR (PNG files in DIR)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from rvdjax.verify import figures

    out = Path(args.out)
    df = read_evals(out / "reference")
    xi = np.stack(df["xi"].to_numpy())
    g = df["margin"].to_numpy(float)
    r0, bearing = _range_bearing(xi)
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for lo, hi, color, label in ((-10, 0, "0.6", "0 to 10 m"), (-20, -10, "C1", "10 to 20 m"),
                                 (-np.inf, -20, "C3", "deeper than 20 m")):  # fmt: skip
        sel = (g < hi) & (g >= lo)
        ax.scatter(bearing[sel], r0[sel], s=6, color=color, label=f"breach {label} ({sel.sum()})")
    ax.set_xlabel("initial bearing in the orbital plane [deg]")
    ax.set_ylabel("initial range [m]")
    ax.set_title(f"thesis-vbar under paper003: keep-out breaches in {len(g)} runs", fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    paths = [out / "reference-breaches.png"]
    fig.savefig(paths[0], dpi=110)
    plt.close(fig)
    cases = []
    for p in sorted(out.glob("coverage-*-*m.json")):
        doc = json.loads(p.read_text())
        ref = _reference(out, doc["depth_m"])
        label = f"{doc['method']}, breach > {doc['depth_m']:g} m"
        cases.append({"label": label, "estimates": doc["estimates"], "reference": ref})
    if cases:
        paths.append(out / "coverage.png")
        figures.coverage_intervals(
            paths[-1], cases, "95 % intervals of seeded estimates against the reference"
        )
    for path in paths:
        print(f"  wrote {path}")
    return {"figures": [str(p) for p in paths]}


def cmd_table(args) -> dict:
    """The coverage table of every ``coverage-*.json`` in DIR, against the reference."""
    out = Path(args.out)
    docs = [json.loads(p.read_text()) for p in sorted(out.glob("coverage-*-*m.json"))]
    rows = [_coverage_row(out, d) for d in docs]
    cols = [
        ("method", "method", "{:<8}"),
        ("threshold", "threshold", "{:>12}"),
        ("seeds", "seeds", "{:>6}"),
        ("coverage", "coverage", "{:>9.2f}"),
        ("mean_over_reference", "mean/ref", "{:>9.2f}"),
        ("runs", "runs", "{:>7.0f}"),
        ("wall_s", "wall s", "{:>8.0f}"),
        ("empirical_cov", "CoV", "{:>6.2f}"),
        ("runs_for_cov_0.3", "CoV 0.3 needs", "{:>14.0f}"),
        ("mc_runs_for_cov_0_3", "MC needs", "{:>9.0f}"),
    ]
    print("  " + "".join(f"{h:>{len(f.format(0)) if 'f' in f else 8}}" for _, h, f in cols))
    for r in rows:
        cells = []
        for key, _, f in cols:
            v = r.get(key)
            cells.append(f.format(float("nan") if v is None and "f" in f else v))
        print("  " + "".join(cells))
    return {"table": rows}


def _random_median(p: float) -> float:
    """Random sampling's median draws to the first failure (geometric distribution)."""
    return float(np.ceil(np.log(0.5) / np.log1p(-p)))


def cmd_worst(args) -> dict:
    """Worst-case search: every method, ``--repeats`` seeded repeats of ``--budget`` forward
    evaluations. Random sampling's median evaluations to the first failure come from
    ``--random-p`` (a probability measured elsewhere) or, for thesis-vbar's keep-out under
    paper003, from the reference; the budget is then set to a tenth of it unless given."""
    spec_p = ProblemSpec(
        args.scenario,
        args.requirement,
        args.dispersion,
        disturbed=args.disturbed,
        n_steps=args.n_steps,
        temperature=args.temperature,
    )
    pb = problem_for(spec_p)
    p_random, source = args.random_p, "--random-p"
    req = pb.requirement
    if p_random is None and (args.scenario, args.dispersion) == (SCENARIO, DISPERSION):
        if len(req.parts) == 1 and req.parts[0].name == "keep-out":
            if (Path(args.out) / "reference" / PROVENANCE).exists():
                p_random = _reference(Path(args.out), -req.parts[0].threshold)["p"]
                source = "the reference"
    median = _random_median(p_random) if p_random else None
    budget = args.budget or (int(median // 10) if median else None)
    if budget is None:
        raise SystemExit("--budget is needed (no failure probability to derive it from)")
    spec = SearchSpec(
        engine_cost=True,
        methods=tuple(args.methods.split(",")),
        budget=budget,
        repeats=args.repeats,
        starts=args.starts,
        step=args.step,
        ladder=args.ladder,
        popsize=args.popsize,
        radius=args.radius,
        seed=args.seed,
    ).resolved(pb.dim)
    tag = args.name or f"worst-{args.requirement.replace('>=', '_ge_').replace('<=', '_le_')}"
    store = _store(Path(args.out), tag, pb, search=dataclasses.asdict(spec))
    traces = search(pb, spec, store)
    from rvdjax.verify import figures

    figures.margin_curves(
        Path(args.out) / f"{tag}.png",
        traces,
        pb.requirement.unit,
        f"{args.scenario}: {pb.requirement.label()} under {pb.dispersion.label()} "
        f"({pb.dim} coordinates)",
    )
    rows = {m: t.summary() for m, t in traces.items()}
    print(
        f"worst case: {args.scenario} {pb.requirement.label()} under {pb.dispersion.label()} "
        f"({pb.dim} coordinates), {spec.repeats} repeats, budget {spec.budget} forward "
        f"evaluations each; smooth margin tau = {pb.tau:.4g}; search ball radius "
        f"{spec.radius:.3g}"
    )
    if median:
        print(
            f"  random sampling's median to the first failure: {median:.0f} evaluations "
            f"(p = {p_random:.4g} from {source}); a tenth: {median / 10:.1f}"
        )
    print(f"  {'method':<14}{'falsified':>10}{'median':>9}{'mean':>9}{'max':>8}{'worst':>10}"
          f"{'wall s':>8}")  # fmt: skip
    for m, t in traces.items():
        r = rows[m]
        found = [f for f in t.first if f is not None]
        r["max_evaluations"] = float(max(found)) if found else None
        med = "-" if r["median_evaluations"] is None else f"{r['median_evaluations']:.1f}"
        mean = "-" if r["mean_evaluations"] is None else f"{r['mean_evaluations']:.1f}"
        mx = "-" if r["max_evaluations"] is None else f"{r['max_evaluations']:.1f}"
        print(f"  {m:<14}{r['falsification_rate']:>10.0%}{med:>9}{mean:>9}{mx:>8}"
              f"{r['worst_margin']:>10.4g}{r['wall_s']:>8.0f}")  # fmt: skip
        if "gradient_cost" in r:
            print(
                f"  {'':<14}a gradient costs {r['gradient_cost']:.2f} forward evaluations (the "
                f"same runs flown forward by the same vmap; "
                f"{r.get('gradient_cost_vs_engine', float('nan')):.2f} x the engine's wall time "
                f"per run); zeroed back-solves {r['zeroed_backsolves']}, non-finite gradients "
                f"{r['nonfinite_gradients']}"
            )
    return {
        "worst": rows,
        "random_median": median,
        "random_p": p_random,
        "random_p_source": source,
        "budget": budget,
        "radius": spec.radius,
        "tau": pb.tau,
        "dim": pb.dim,
        "provenance": store.provenance_summary(),
    }


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


# the deepest breach the earlier worst-case benchmark found (85 m), to 2 decimals
EARLIER_WORST = (-2.44, -0.75, 0.70, -3.82, -0.24)


def cmd_gradcheck(args) -> dict:
    """The smooth margin's gradient at the worst point (the ``worst`` part's deepest breach,
    else :data:`EARLIER_WORST`) and at ``--near`` points within 0.005 sigma of it, against
    central differences (h = 1e-5) of the smooth margin of the default solver (tol 1e-9,
    max_iter 100) and of a converged one (tol 1e-12, max_iter 300). Also: the solver's
    statuses and iterations along the worst run, and the back-solves each gradient zeroed."""
    from rvdjax.loop import fly
    from rvdjax.verify.evaluate import Problem

    out, h = Path(args.out), 1e-5
    worst = out / "worst-keep-out"
    if (worst / "evals").exists():
        df = read_evals(worst)
        xi = np.asarray(df.loc[df["margin"].idxmin(), "xi"], float)
    else:
        xi = np.asarray(EARLIER_WORST, float)
    rng = np.random.default_rng(args.seed)
    centres = [xi] + [xi + 0.005 * rng.standard_normal(len(xi)) for _ in range(args.near)]
    d = len(xi)
    pts = np.concatenate([[c, *(c + h * np.eye(d)), *(c - h * np.eye(d))] for c in centres])
    res = {}
    for name, extra in (("default", {}), ("converged", {"solver_tol": 1e-12, "max_iter": 300})):
        pb = Problem(ProblemSpec(SCENARIO, "keep-out", DISPERSION, **extra))
        r = pb.gradient(pts)
        s = r["smooth"].reshape(len(centres), 2 * d + 1)
        res[name] = {
            "grad": r["grad"][:: 2 * d + 1],
            "fd": (s[:, 1 : 1 + d] - s[:, 1 + d :]) / (2 * h),
            "zeroed": r["zeroed"][:: 2 * d + 1],
            "zeroed_fd_points": r["zeroed"].reshape(len(centres), -1).max(axis=1),
            "margin": r["margin"][:: 2 * d + 1],
        }
        x0, p = pb.dispersion.apply(xi, pb.x0, pb.params, pb.scenario.guidance_family.layout)
        infos, m = jax.jit(lambda p, x, pb=pb: fly(pb.loop, p, x, pb.key, pb.sp))(p, x0)
        act = np.asarray(infos.active)
        it = np.asarray(infos.iterations)[act]
        st = np.asarray(infos.solver_status)[act]
        res[name]["run"] = {
            "steps": int(act.sum()),
            "iterations_max": int(it.max()),
            "iterations_mean": float(it.mean()),
            "at_cap": int(np.sum(it >= pb.loop.config.settings.max_iter)),
            "statuses": {Status.name(k): int(np.sum(st == k)) for k in np.unique(st)},
        }

    def rel(a, b):
        return np.linalg.norm(a - b, axis=-1) / np.linalg.norm(b, axis=-1)

    ref = res["converged"]["fd"]
    rows = {
        "points": [c.tolist() for c in centres],
        "margin_m": res["default"]["margin"].tolist(),
        "grad_default_vs_fd_converged": rel(res["default"]["grad"], ref).tolist(),
        "fd_default_vs_fd_converged": rel(res["default"]["fd"], ref).tolist(),
        "grad_converged_vs_fd_converged": rel(res["converged"]["grad"], ref).tolist(),
        "zeroed_default": res["default"]["zeroed"].tolist(),
        "zeroed_converged": res["converged"]["zeroed"].tolist(),
        "worst_run": {k: v["run"] for k, v in res.items()},
        "grad_default": res["default"]["grad"].tolist(),
        "fd_converged": ref.tolist(),
    }
    print(f"  gradient check at xi = {np.round(xi, 3).tolist()} and {args.near} points within "
          f"0.005 sigma (relative norm errors against central differences of the converged "
          f"solver, h = {h:g})")  # fmt: skip
    print(f"  {'point':>6}{'margin m':>10}{'grad 1e-9':>11}{'fd 1e-9':>10}{'grad 1e-12':>11}"
          f"{'zeroed 1e-9':>12}{'zeroed 1e-12':>13}")  # fmt: skip
    for j in range(len(centres)):
        print(f"  {j:>6}{rows['margin_m'][j]:>10.2f}"
              f"{rows['grad_default_vs_fd_converged'][j]:>11.2e}"
              f"{rows['fd_default_vs_fd_converged'][j]:>10.2e}"
              f"{rows['grad_converged_vs_fd_converged'][j]:>11.2e}"
              f"{rows['zeroed_default'][j]:>12d}{rows['zeroed_converged'][j]:>13d}")  # fmt: skip
    for k, v in rows["worst_run"].items():
        print(f"  worst run, {k} solver: {v}")
    return {"gradcheck": rows}


# ----------------------------------------------------------------------------- sense


BAND = ((1300.0, 2200.0), (270.0, 340.0))  # initial range [m] and bearing [deg]


def _range_bearing(xi):
    """paper003's initial range [m] and bearing [deg] of dispersion vectors xi (N, 5)."""
    from scipy.stats import norm

    from rvdjax.verify.dispersions import P003_R

    r = P003_R[0] + (P003_R[1] - P003_R[0]) * norm.cdf(xi[:, 0])
    return r, 360.0 * norm.cdf(xi[:, 1])


def _fly_blocks(store, name: str, xs, pb, block: int = 500):
    """Exact margins of ``xs`` flown in blocks of ``block`` runs (batches ``name-LO`` of the
    store: a killed part resumes), with a line per block."""
    g = []
    for lo in range(0, len(xs), block):
        got = store.evaluate(f"{name}-{lo}", name, xs[lo : lo + block], pb.forward)
        g.append(np.asarray(got["margin"], float))
        print(f"{name}: {lo + len(g[-1])} of {len(xs)} runs flown", flush=True)
    return np.concatenate(g)


def cmd_sense(args) -> dict:
    """Where the deep breaches come from: thesis-vbar's keep-out planes turn "the way the
    bearing turns", read afresh each step; near the bearing opposite the approach axis that
    sense flips from step to step. The same runs flown with the sense latched
    (``Config.latch_turn``, from a scenario file written here):

    * a line of 61 starts through the reference's deepest breach in the band of initial
      bearings where the deep breaches lie (``BAND``), 0.01 sigma apart in xi_0 (range), by
      both guidances;
    * every failing run of the reference;
    * ``--band-runs`` of the reference's runs in that band, drawn with ``--seed`` (unbiased
      within the band; their default-guidance margins are the reference's);
    * ``--sample-runs`` of all the reference's runs: with the failing ones above, the latched
      guidance's P(breach) and its interval (Clopper-Pearson on the sample's new failures).
    """
    from rvdjax.scenarios import get_scenario
    from rvdjax.scenarios.files import scenario_to_toml

    out = Path(args.out)
    ev = read_evals(out / "reference")
    xi = np.stack(ev["xi"].to_numpy())
    m = ev["margin"].to_numpy(float)
    sc = get_scenario(SCENARIO)
    latched = dataclasses.replace(
        sc, name=f"{SCENARIO}-latched", config={**sc.config, "latch_turn": True}
    )
    path = out / f"{SCENARIO}-latched.toml"
    path.write_text(scenario_to_toml(latched))
    pb0 = _problem("keep-out")
    pb1 = problem_for(ProblemSpec(str(path), "keep-out", DISPERSION))
    r, b = _range_bearing(xi)
    band = np.flatnonzero((r > BAND[0][0]) & (r < BAND[0][1]) & (b > BAND[1][0]) & (b < BAND[1][1]))
    res = {"band": {"range_m": BAND[0], "bearing_deg": BAND[1], "reference_runs": len(band)}}

    # the line through the deepest breach in the band, by both guidances
    i = band[np.argmin(m[band])]
    line = np.repeat(xi[i][None], 61, axis=0)
    line[:, 0] += np.linspace(-0.3, 0.3, 61)
    for name, pb in (("default", pb0), ("latched", pb1)):
        got = _store(out, f"sense-line-{name}", pb).evaluate("line", "line", line, pb.forward)
        g = np.asarray(got["margin"], float)
        res[f"line_{name}"] = {
            "runs": len(g), "failing": int(np.sum(g < 0)), "deeper_than_10m": int(np.sum(g < -10)),
            "min_m": float(g.min()), "margins_m": [round(float(v), 2) for v in g],
        }  # fmt: skip
    res["line_start"] = [float(v) for v in xi[i]]

    # every failing run of the reference, latched
    fail = np.flatnonzero(m < 0)
    got = _store(out, "sense-failures", pb1).evaluate("failures", "failures", xi[fail], pb1.forward)
    g = np.asarray(got["margin"], float)
    res["reference_failures"] = {
        "runs": len(fail),
        "deeper_than_10m": int(np.sum(m[fail] < -10)),
        "latched_failing": int(np.sum(g < 0)),
        "latched_deeper_than_10m": int(np.sum(g < -10)),
        "latched_unchanged": int(np.sum(np.abs(g - m[fail]) < 1e-6)),
        "latched_failing_start_below_250m": int(np.sum((g < 0) & (r[fail] < 250))),
    }

    # a sample of the band, latched (the default's margins are the reference's)
    n = min(args.band_runs, len(band))
    pick = np.sort(np.random.default_rng(args.seed).choice(band, n, replace=False))
    store = _store(out, "sense-band", pb1, band=BAND, seed=args.seed)
    g = _fly_blocks(store, "band", xi[pick], pb1)
    d = m[pick]
    res["band_sample"] = {
        "runs": n,
        "default_failing": int(np.sum(d < 0)),
        "default_deeper_than_10m": int(np.sum(d < -10)),
        "latched_failing": int(np.sum(g < 0)),
        "latched_deeper_than_10m": int(np.sum(g < -10)),
        "default_ci95": clopper_pearson(int(np.sum(d < 0)), n),
        "latched_ci95": clopper_pearson(int(np.sum(g < 0)), n),
        "latched_min_m": float(g.min()),
    }
    # a uniform sample of the reference, latched: with every failing run of the reference
    # flown above, P(latched breach) = (latched failures among them + the sample's other
    # runs' failure rate x the reference's other runs) / the reference's runs
    n_u = min(args.sample_runs, len(m))
    pick = np.sort(np.random.default_rng([args.seed, 1]).choice(len(m), n_u, replace=False))
    g = _fly_blocks(_store(out, "sense-sample", pb1, seed=args.seed), "sample", xi[pick], pb1)
    ok = m[pick] >= 0  # the sample's runs that did not fail by the default guidance
    latched_f = np.asarray(_store(out, "sense-failures", pb1).batches["failures"]["margin"], float)
    res["latched_p"] = {}
    for depth in (0.0, 10.0):
        k_new, n_ok = int(np.sum(g[ok] < -depth)), int(np.sum(ok))
        lo_new, hi_new = clopper_pearson(k_new, n_ok)
        k_f, rest = int(np.sum(latched_f < -depth)), len(m) - len(fail)
        res["latched_p"][_tag(depth)] = {
            "p": (k_f + k_new / n_ok * rest) / len(m),
            "ci95": [(k_f + lo_new * rest) / len(m), (k_f + hi_new * rest) / len(m)],
            "reference_failures_still_failing": k_f,
            "sample_new_failures": k_new,
            "sample_runs_not_failing_by_default": n_ok,
            "default_p": float(np.mean(m < -depth)),
        }
    res["uniform_sample"] = {
        "runs": n_u,
        "changed": float(np.mean(np.abs(g - m[pick]) > 1e-6)),
        "latched_min_m": float(g.min()),
    }
    f, bs = res["reference_failures"], res["band_sample"]
    print("the line through the deepest band breach (61 starts, 0.01 sigma apart in xi_0):")
    for name in ("default", "latched"):
        ln = res[f"line_{name}"]
        print(f"  {name:8s} failing {ln['failing']:3d}, deeper than 10 m "
              f"{ln['deeper_than_10m']:3d}, deepest {ln['min_m']:.1f} m")  # fmt: skip
    print(f"the reference's {f['runs']} failing runs ({f['deeper_than_10m']} deeper than 10 m), "
          f"latched: {f['latched_failing']} fail ({f['latched_deeper_than_10m']} deeper than "
          f"10 m; {f['latched_unchanged']} with the same margin; "
          f"{f['latched_failing_start_below_250m']} start below 250 m)")  # fmt: skip
    print(f"{n} of the band's {len(band)} reference runs: default {bs['default_failing']} fail "
          f"({bs['default_deeper_than_10m']} deeper than 10 m), latched {bs['latched_failing']} "
          f"({bs['latched_deeper_than_10m']}); deepest latched margin "
          f"{bs['latched_min_m']:.2f} m")  # fmt: skip
    print(f"a uniform sample of {n_u} reference runs, latched: "
          f"{res['uniform_sample']['changed']:.0%} fly differently; deepest latched margin "
          f"{res['uniform_sample']['latched_min_m']:.2f} m")  # fmt: skip
    print("breach deeper than | default (the reference) | latched | 95 % interval")
    for tag, q in res["latched_p"].items():
        print(f"{tag:>18s} | {q['default_p']:.3g} | {q['p']:.3g} | "
              f"[{q['ci95'][0]:.2g}, {q['ci95'][1]:.2g}]")  # fmt: skip
    return res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    ref = sub.add_parser("reference")
    ref.add_argument("--runs", type=int, default=100_000)
    cov = sub.add_parser("coverage")
    cov.add_argument("--method", choices=("subset", "is"), required=True)
    cov.add_argument("--depth", type=float, default=0.0, help="breach depth [m] (0: any)")
    cov.add_argument("--seeds", type=int, default=20)
    cov.add_argument("--budget", type=int, required=True, help="runs per estimate")
    cov.add_argument("--level-size", type=int, help="subset: runs per level and replicate")
    cov.add_argument("--replicates", type=int, default=4, help="subset: replicates per estimate")
    tab = sub.add_parser("table")
    fg = sub.add_parser("figures")
    w = sub.add_parser("worst")
    w.add_argument("--scenario", default=SCENARIO)
    w.add_argument("--dispersion", default=DISPERSION)
    w.add_argument("--disturbed", action="store_true")
    w.add_argument("--n-steps", type=int)
    w.add_argument("--requirement", default="keep-out")
    w.add_argument("--temperature", type=float)
    w.add_argument("--methods", default="gradient,random,cma-es")
    w.add_argument("--budget", type=int, help="default: a tenth of random's median")
    w.add_argument("--random-p", type=float, help="P(failure) for random's median")
    w.add_argument("--repeats", type=int, default=20)
    w.add_argument("--starts", type=int, default=2)
    w.add_argument("--step", type=float, default=1.0)
    w.add_argument("--ladder", type=int, default=4)
    w.add_argument("--popsize", type=int, default=8)
    w.add_argument("--radius", type=float, help="the search ball [sigma] (default: chi2)")
    w.add_argument("--name", help="the part's directory under --out")
    gc = sub.add_parser("gradcheck")
    gc.add_argument("--near", type=int, default=5, help="points near the worst one")
    o = sub.add_parser("openturns")
    o.add_argument("--level-size", type=int, default=1000)
    o.add_argument("--form-calls", type=int, default=200)
    se = sub.add_parser("sense")
    se.add_argument("--band-runs", type=int, default=3000)
    se.add_argument("--sample-runs", type=int, default=6000)
    for q in (ref, cov, tab, fg, w, o, gc, se):
        q.add_argument("--out", required=True)
        q.add_argument("--seed", type=int, default=0)
        q.add_argument("--json", action="store_true")
        q.add_argument("--allow-code-change", action="store_true")
    args = ap.parse_args(argv)
    ALLOW["code_change"] = args.allow_code_change
    res = {
        "reference": cmd_reference,
        "coverage": cmd_coverage,
        "table": cmd_table,
        "figures": cmd_figures,
        "worst": cmd_worst,
        "gradcheck": cmd_gradcheck,
        "openturns": cmd_openturns,
        "sense": cmd_sense,
    }[args.cmd](args)
    name = args.cmd
    if args.cmd == "coverage":
        name = f"coverage-{args.method}-{_tag(args.depth)}-row"
    if args.cmd == "worst":
        name = args.name or "worst-" + args.requirement.replace(">=", "_ge_").replace("<=", "_le_")
        name += "-summary"
    write_json(Path(args.out) / f"{name}.json", json.loads(json.dumps(res, default=float)))
    if args.json:
        print(json.dumps(res, indent=2, default=float))


if __name__ == "__main__":
    main()
