"""Verification: requirements as margins (against an independent STL monitor), dispersions,
the estimators against the normal tail, the searches, gradients against central differences,
resume, replay and bad input."""

from __future__ import annotations

import json
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import norm

from rvdjax.cli import main
from rvdjax.disturbances import Draws
from rvdjax.loop import fly
from rvdjax.loop.plant import with_plant
from rvdjax.scenarios import get_scenario
from rvdjax.verify.evaluate import ProblemSpec, problem_for
from rvdjax.verify.probability import ProbabilitySpec, estimate
from rvdjax.verify.store import read_evals
from rvdjax.verify.worst import SearchSpec, search

# ------------------------------------------------------------------ analytic limit states


class Linear:
    """g(xi) = beta - a.xi, |a| = 1: P(g < 0) = Phi(-beta) exactly; the design point is
    beta a."""

    effort_key = "x"

    def __init__(self, beta, dim=5):
        self.beta, self.dim = beta, dim
        self.a = np.ones(dim) / np.sqrt(dim)
        self.calls = 0

    def forward(self, xi):
        self.calls += len(xi)
        return {"margin": self.beta - xi @ self.a}

    def gradient(self, xi):
        self.calls += len(xi)
        g = self.beta - xi @ self.a
        return {"margin": g, "smooth": g, "grad": -np.tile(self.a, (len(xi), 1))}

    def gradient_cost(self, *_):
        return 1.0

    def definition(self):
        return {"limit_state": type(self).__name__, "beta": self.beta, "dim": self.dim}


@pytest.mark.parametrize(
    ("beta", "method", "budget"),
    [(2.326, "mc", 20000), (2.326, "is", 1500), (4.265, "is", 1500)],
)
def test_estimators_bracket_the_normal_tail(beta, method, budget):
    exact = norm.cdf(-beta)  # 1e-2 and 1e-5
    res = estimate(Linear(beta), ProbabilitySpec(method=method, budget=budget, seed=3), None, False)
    assert res["runs"] <= budget
    lo, hi = res["ci95"]
    assert lo <= exact <= hi, res
    assert res["cov"] < (0.5 if beta > 4 else 0.3)
    if method == "is":  # no failing point lies closer than the design point beta a
        assert beta <= res["design_point_norm"] < 1.2 * beta
        assert res["final_failing"] > 0.2  # the learnt proposal, not N(0, I)


def test_importance_sampling_intervals_cover_the_normal_tail():
    """Over 30 seeds at p = 5e-3 (800 runs), importance sampling's 95 % intervals hold
    Phi(-beta) at least 80 % of the time and its mean is within 3 standard errors; flown side
    by side, the seeds give the estimates they give alone."""
    from rvdjax.verify.probability import importance_side_by_side
    from rvdjax.verify.store import EvalStore

    exact = 5e-3
    pb = Linear(-norm.ppf(exact))
    specs = [ProbabilitySpec("is", 800, seed=s) for s in range(30)]
    runs = importance_side_by_side(pb, specs, EvalStore(), progress=False)
    assert all(r["runs"] == 800 for r in runs)
    cover = np.mean([r["ci95"][0] <= exact <= r["ci95"][1] for r in runs])
    p = np.array([r["p"] for r in runs])
    assert cover >= 0.8, cover
    assert abs(p.mean() - exact) < 3 * p.std(ddof=1) / np.sqrt(len(p))
    alone = estimate(pb, specs[7], None, False)
    assert alone["p"] == runs[7]["p"] and alone["ci95"] == runs[7]["ci95"]


def test_importance_weights_against_scipy_densities():
    """phi / q of the defensive mixture (Gaussians and unit kernels), against scipy's normal
    densities, and no weight above 1 / a."""
    from scipy.stats import multivariate_normal as mvn

    from rvdjax.verify.importance import IS_DEFENSIVE, IS_GMM_SHARE, _Proposal

    rng = np.random.default_rng(0)
    alpha = np.array([0.5, 0.3, 0.2])
    mu = rng.normal(2.0, 1.0, (3, 3))
    cov = [(lambda m: m @ m.T + 0.1 * np.eye(3))(rng.normal(size=(3, 3))) for _ in range(3)]
    centres, pi = rng.normal(1.0, 1.0, (5, 3)), rng.dirichlet(np.ones(5))
    q = _Proposal(alpha, mu, cov, centres, pi)
    x = q.sample(rng, 400, 3)
    phi = mvn(np.zeros(3)).pdf(x)
    b = IS_GMM_SHARE
    fitted = sum(b * a * mvn(m, c).pdf(x) for a, m, c in zip(alpha, mu, cov, strict=True))
    fitted += sum((1 - b) * p * mvn(c).pdf(x) for p, c in zip(pi, centres, strict=True))
    want = phi / (IS_DEFENSIVE * phi + (1 - IS_DEFENSIVE) * fitted)
    np.testing.assert_allclose(q.weight(x), want, rtol=1e-10)
    assert q.weight(x).max() <= 1 / IS_DEFENSIVE


class Needles(Linear):
    """Failure inside any of 2 000 balls of radius 0.2 scattered over xi_1 > 0.5 (5-D), p about
    4.6e-3: a thin, scattered failure set like thesis-vbar's keep-out breaches, where one or
    two draws carry an importance-sampling estimate."""

    def __init__(self):
        super().__init__(0.0)
        from scipy.spatial import cKDTree

        c = np.random.default_rng(42).standard_normal((40000, 5))
        self.tree = cKDTree(c[c[:, 1] > 0.5][:2000])

    def forward(self, xi):
        return {"margin": self.tree.query(xi)[0] - 0.2}

    def definition(self):
        return {"limit_state": "needles"}


def test_importance_sampling_on_needles_widens_its_interval():
    """On scattered needles a few failing draws (ess) carry the estimate; the interval's t
    quantile (ess - 1 degrees of freedom) keeps its coverage over 30 seeds."""
    from rvdjax.verify.probability import importance_side_by_side
    from rvdjax.verify.store import EvalStore

    pb = Needles()
    z = np.random.default_rng(7).standard_normal((400_000, 5))
    exact = float(np.mean(pb.forward(z)["margin"] < 0))  # about 4.6e-3, CoV 0.023
    specs = [ProbabilitySpec("is", 800, seed=s) for s in range(30)]
    runs = importance_side_by_side(pb, specs, EvalStore(), progress=False)
    cover = np.mean([r["ci95"][0] <= exact <= r["ci95"][1] for r in runs])
    assert cover >= 0.9, cover
    assert np.median([r["ess_failing"] for r in runs]) < 10


def test_importance_sampling_refuses_high_dimension(tmp_path, capsys):
    """Above 20 coordinates a mixture fitted to tens of elites is no density of theirs:
    refused in one line with status 2, after the problem's set-up and before any flight."""
    with pytest.raises(ValueError, match="--method is.*at most 20"):
        estimate(Linear(3.0, dim=21), ProbabilitySpec("is", 500), None, False)
    argv = ["verify", "probability", "thesis-vbar", "--requirement", "keep-out", "--disturbed",
            "--dispersion", "nav", "--method", "is", "--budget", "500", "--out",
            str(tmp_path / "v")]  # fmt: skip
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "--method is" in err and "coordinates" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "v").exists()


@pytest.mark.parametrize(
    ("beta", "budget", "level_size"), [(2.326, 2000, None), (4.265, 8000, 300)]
)
def test_subset_intervals_cover_the_normal_tail(beta, budget, level_size):
    """Over 30 seeds, subset simulation's 95 % intervals (4 replicates, lognormal with a t
    quantile) hold Phi(-beta) (1e-2, 1e-5) at least 80 % of the time, its mean is within 3
    standard errors, and it spends the whole budget."""
    exact = norm.cdf(-beta)
    runs = [
        estimate(Linear(beta), ProbabilitySpec("subset", budget, level_size, seed=s), None, False)
        for s in range(30)
    ]
    assert all(r["runs"] == budget for r in runs)
    assert all(r["converged"] for r in runs)
    cover = np.mean([r["ci95"][0] <= exact <= r["ci95"][1] for r in runs])
    p = np.array([r["p"] for r in runs])
    assert cover >= 0.8, cover
    assert abs(p.mean() - exact) < 3 * p.std(ddof=1) / np.sqrt(len(p))


def test_subset_levels_are_independent_and_adapted():
    """Level 0 is drawn afresh for every seed and every threshold; the proposal's scale is
    per dimension (only xi_0 matters here: its conditional spread, and so its sigma, is the
    smallest); the acceptance is steered toward 0.44."""
    from rvdjax.verify.store import EvalStore

    def level0(beta, seed):
        store = EvalStore()
        pb = Linear(beta)
        pb.a = np.eye(pb.dim)[0]
        res = estimate(pb, ProbabilitySpec("subset", 2000, seed=seed), store, False)
        return store.batches["subset-L0"]["xi"], res

    x_a, res = level0(3.0, 0)
    x_b, _ = level0(3.5, 0)
    x_c, _ = level0(3.0, 1)
    assert not np.allclose(x_a[:10], x_b[:10]) and not np.allclose(x_a[:10], x_c[:10])
    for rep in res["replicates"]:
        for lv in rep["levels"]:
            sigma = np.asarray(lv["sigma"])
            assert sigma[0] < sigma[1:].min()
            assert 0.15 < lv["acceptance"] < 0.8


class Stepped(Linear):
    """beta - a.xi rounded down to 0.25: ties (plateaus), the same P(g < 0) = Phi(-beta)."""

    def forward(self, xi):
        return {"margin": np.floor(4 * (self.beta - xi @ self.a)) / 4}


def test_subset_with_tied_margins():
    """Thresholds between tied margins keep every comparison strict: the estimate still
    brackets Phi(-beta) on a margin with plateaus."""
    beta = 3.0
    runs = [
        estimate(Stepped(beta), ProbabilitySpec("subset", 2000, seed=s), None, False)
        for s in range(20)
    ]
    p = np.array([r["p"] for r in runs])
    assert abs(p.mean() / norm.cdf(-beta) - 1) < 3 * p.std(ddof=1) / p.mean() / np.sqrt(20)


class TwoSided(Linear):
    """g(xi) = beta - |a.xi|: two failure regions, P = 2 Phi(-beta)."""

    def forward(self, xi):
        return {"margin": self.beta - np.abs(xi @ self.a)}

    def gradient(self, xi):
        s = np.sign(xi @ self.a)[:, None]
        g = self.beta - np.abs(xi @ self.a)
        return {"margin": g, "smooth": g, "grad": -s * self.a}


def test_importance_sampling_covers_two_failure_regions():
    """The kernels on the failing draws of both half-spaces find both (a proposal on one
    side would see half the probability)."""
    beta = 3.0
    res = estimate(TwoSided(beta), ProbabilitySpec("is", 3000, seed=5), None, False)
    lo, hi = res["ci95"]
    assert lo <= 2 * norm.cdf(-beta) <= hi, res


class Slab(Linear):
    """g = 1 where |xi_0| < beta, else -1: a flat margin no search can follow, P(g < 0) =
    2 Phi(-beta)."""

    def forward(self, xi):
        return {"margin": np.where(np.abs(xi[:, 0]) < self.beta, 1.0, -1.0)}

    def gradient(self, xi):
        g = self.forward(xi)["margin"]
        return {"margin": g, "smooth": g, "grad": np.zeros_like(xi)}


def test_importance_sampling_without_a_failing_draw_still_bounds_p():
    """When no draw fails (here p = 6e-7 and 400 draws), the estimate is 0 but the interval
    is not [0, 0]: it still holds the probability."""
    exact = 2 * norm.cdf(-5.0)
    res = estimate(Slab(5.0), ProbabilitySpec("is", 400, seed=1), None, False)
    assert res["p"] == 0.0
    lo, hi = res["ci95"]
    assert lo == 0.0 and exact <= hi < 0.1, res


def test_subset_simulation_without_a_failing_state_still_bounds_p():
    """When no replicate's last population holds a failure (p = 6e-7, 400 runs), the
    estimate is 0 and its interval [0, u] holds the probability (it was [0, nan])."""
    exact = 2 * norm.cdf(-5.0)
    res = estimate(Slab(5.0), ProbabilitySpec("subset", 400, seed=1), None, False)
    assert res["p"] == 0.0
    lo, hi = res["ci95"]
    assert lo == 0.0 and exact <= hi < 0.1, res


def test_subset_cov_matches_its_spread():
    """The CoV subset simulation reports (its replicates' standard error) against the spread
    of 40 seeded estimates of p = 1e-3."""
    beta = -norm.ppf(1e-3)
    runs = [
        estimate(Linear(beta), ProbabilitySpec("subset", 1600, seed=s), None, False)
        for s in range(40)
    ]
    p = np.array([r["p"] for r in runs])
    reported = np.sqrt(np.mean(np.square([r["cov"] for r in runs])))
    empirical = p.std(ddof=1) / p.mean()
    assert 0.6 < empirical / reported < 1.6, (empirical, reported)
    assert abs(p.mean() / 1e-3 - 1) < 3 * empirical / np.sqrt(len(p))


def test_searches_on_a_linear_limit_state():
    pb = Linear(3.0)
    spec = SearchSpec(
        methods=("gradient", "design-point", "random", "lhs", "cma-es"), budget=64, repeats=6
    )
    tr = search(pb, spec, progress=False)
    s = {m: t.summary() for m, t in tr.items()}
    # the HL-RF point of the first gradient crosses the (linear) limit state: found in the
    # first iteration, 2 starts x (1 gradient + 4 ladder points + 1 HL-RF point)
    assert s["gradient"]["falsification_rate"] == 1.0
    assert s["gradient"]["median_evaluations"] <= 12
    # the design point of g = beta - a.xi is beta a
    assert s["design-point"]["design_point_norm"] == pytest.approx(3.0, rel=0.1)
    # p = 1.3e-3: 64 draws rarely fail; CMA-ES climbs the linear slope
    assert s["random"]["falsification_rate"] <= 0.5
    assert s["cma-es"]["falsification_rate"] == 1.0
    assert s["gradient"]["worst_margin"] < s["random"]["worst_margin"]


def test_search_region_holds_the_dispersion_in_high_dimension():
    """The default ball holds all but 1e-6 of N(0, I): 6.0 sigma in 5-D, 18.9 in 240-D (a
    ball of 5 holds none of a 240-D dispersion, whose draws lie near 15.5), and random
    sampling there draws without rejecting forever."""
    assert SearchSpec().resolved(5).radius == pytest.approx(5.99, abs=0.01)
    assert SearchSpec().resolved(240).radius == pytest.approx(18.94, abs=0.01)
    pb = Linear(3.0, dim=240)
    tr = search(pb, SearchSpec(methods=("random",), budget=20, repeats=2), progress=False)
    assert np.all(np.linalg.norm(tr["random"].worst_xi, axis=1) > 10)


# ------------------------------------------------------------------ the closed loop


@pytest.fixture(scope="module")
def poseidyn():
    """poseidyn-lqmpc, contact speed under initial-state offsets: the module's small case."""
    spec = ProblemSpec("poseidyn-lqmpc", "keep-out", "x0:0.05,0.005", n_steps=60)
    return problem_for(spec)


def test_keep_out_margin_against_an_stl_monitor(poseidyn):
    """The exact keep-out margin against rtamt's robustness of always(d >= 0), d the
    clearance of the obstacle circle on the truth at the samples and between them, the
    between-sample states integrated here by SciPy from the applied force."""
    rtamt = pytest.importorskip("rtamt")
    from scipy.integrate import solve_ivp

    pb = poseidyn
    xis = np.random.default_rng(0).standard_normal((3, pb.dim))
    res = pb.gradient(xis)
    M = pb.loop.config.family_config.substeps
    flown = jax.jit(lambda p, x: fly(pb.loop, p, x, pb.key, pb.sp))  # one compile for the three
    for i, xi in enumerate(xis):
        x0, params = pb.dispersion.apply(xi, pb.x0, pb.params, pb.scenario.guidance_family.layout)
        infos, m = flown(params, x0)
        infos = jax.tree.map(np.asarray, infos)
        centre, r_obs = np.asarray(params.obstacle), float(params.r_obs)
        Ac, Bc = np.asarray(params.plant.Ac), np.asarray(params.plant.Bc)
        d = []
        for k in np.flatnonzero(infos.active):
            x, u, dt = infos.x[k], infos.u[k], float(infos.dt[k])
            d.append(np.linalg.norm(x[:2] - centre) - r_obs)
            taus = float(params.ts) * np.arange(1, M + 1) / M
            taus = taus[taus <= dt + 1e-12]
            if len(taus):
                sol = solve_ivp(
                    lambda t, y, u=u, A=Ac, B=Bc: A @ y + B @ u,
                    (0, taus[-1]),
                    x,
                    t_eval=taus,
                    rtol=1e-11,
                    atol=1e-12,
                )
                d.extend(np.linalg.norm(sol.y[:2].T - centre, axis=1) - r_obs)
        spec = rtamt.StlDiscreteTimeOfflineSpecification()
        spec.declare_var("d", "float")
        spec.spec = "always (d >= 0)"
        spec.parse()
        rob = spec.evaluate({"time": list(range(len(d))), "d": [float(v) for v in d]})
        assert res["margin"][i] == pytest.approx(rob[0][1], abs=1e-7)


@pytest.mark.slow  # 26 s; `pytest -m slow`
def test_smooth_gradient_against_central_differences(poseidyn):
    """At the worst point of a short gradient search, the smooth margin's gradient against
    central differences of the smooth margin."""
    pb = poseidyn
    spec = SearchSpec(
        methods=("gradient",), budget=12, repeats=2, starts=1, ladder=2, step=0.5, gradient_cost=1.0
    )
    tr = search(pb, spec, progress=False)
    t = tr["gradient"]
    xi = t.worst_xi[int(np.argmin(t.worst_margin))]
    h = 1e-5
    pts = np.concatenate([[xi], xi + h * np.eye(pb.dim), xi - h * np.eye(pb.dim)])
    r = [pb.gradient(pts[i : i + 8]) for i in range(0, len(pts), 8)]  # one batch shape
    smooth = np.concatenate([a["smooth"] for a in r])
    fd = (smooth[1 : 1 + pb.dim] - smooth[1 + pb.dim :]) / (2 * h)
    np.testing.assert_allclose(r[0]["grad"][0], fd, rtol=2e-3, atol=1e-6 * np.abs(fd).max())


@pytest.mark.slow  # 13 s; `pytest -m slow`
def test_draws_replace_the_prng_exactly():
    """A disturbed run fed the standard normals its PRNG key would draw flies the same bits."""
    sc = get_scenario("poseidyn-lqmpc")
    params, x0 = sc.build()
    loop = sc.loop("accurate", disturbed=True, n_steps=20)
    key = jax.random.key(7)
    lay = sc.guidance_family.layout
    steps = jax.random.fold_in(key, 1)
    ks = [jax.random.split(jax.random.fold_in(steps, k)) for k in range(20)]
    nav = jnp.stack([jax.random.normal(k[0], (lay.nx,)) for k in ks])
    gm = jnp.stack([jax.random.normal(k[1], (lay.nu, 2)) for k in ks])
    gm0 = jax.random.normal(jax.random.fold_in(key, 0), (lay.nu,))
    d = params.plant.disturbances._replace(draws=Draws(nav=nav, gm0=gm0, gm=gm))
    run = jax.jit(lambda p, k: fly(loop, p, x0, k))
    a, _ = run(params, key)
    b, _ = run(with_plant(params, disturbances=d), jax.random.key(99))
    np.testing.assert_array_equal(np.asarray(a.x), np.asarray(b.x))
    np.testing.assert_array_equal(np.asarray(a.u), np.asarray(b.u))


# ------------------------------------------------------------------ command line


@pytest.mark.slow  # 28 s; `pytest -m slow`
def test_worst_resumes_and_replays(tmp_path, capsys):
    out = tmp_path / "v"
    argv = [
        "verify", "worst", "poseidyn-lqmpc", "--requirement", "keep-out", "--dispersion",
        "x0:0.05,0.005", "--n-steps", "60", "--budget", "12", "--repeats", "2", "--methods",
        "gradient,random", "--starts", "1", "--ladder", "2", "--out", str(out), "--json", "--quiet",
    ]  # fmt: skip
    assert main(argv) == 0
    first = json.loads(capsys.readouterr().out)
    n = len(read_evals(out))
    assert main(argv) == 2  # the directory holds it: --resume to continue
    assert "--resume" in capsys.readouterr().err
    assert main([*argv, "--resume"]) == 0
    again = json.loads(capsys.readouterr().out)
    assert len(read_evals(out)) == n  # nothing flown again
    assert again["worst"]["margin"] == first["worst"]["margin"]
    assert set(first["methods"]) == {"gradient", "random"}
    # the worst run replays as a study run, to the same margin
    run = first["worst"]["run"]
    assert main(["run", "poseidyn-lqmpc", "--study", str(out), "--run", str(run), "--json"]) == 0
    replay = json.loads(capsys.readouterr().out)
    assert min(replay["margins_m"]["keep_out"], np.inf) == pytest.approx(
        first["worst"]["margin"], abs=1e-9
    )


@pytest.mark.parametrize(
    ("extra", "needle"),
    [
        (["--requirement", "keepout", "--dispersion", "x0:1,1"], "--requirement"),
        (["--requirement", "overshoot", "--dispersion", "x0:1,1"], "no such zone"),
        (["--requirement", "keep-out", "--dispersion", "paper004"], "--dispersion"),
        (["--requirement", "keep-out", "--dispersion", "paper003"], "3-D CW"),
        (["--requirement", "keep-out", "--dispersion", "nav"], "--disturbed"),
        (["--requirement", "keep-out,docks", "--dispersion", "x0:1,1"], "one unit"),
    ],
)
def test_bad_input_names_the_parameter(tmp_path, capsys, extra, needle):
    argv = ["verify", "worst", "poseidyn-lqmpc", *extra, "--budget", "20", "--out"]
    assert main([*argv, str(tmp_path / "v")]) == 2
    err = capsys.readouterr().err.strip()
    assert needle in err and len(err.splitlines()) == 1


def test_bad_budget_and_method_exit_before_compiling(tmp_path, capsys):
    """Each refuses in one line with status 2, and nothing is traced or compiled first (jax's
    own compile events, in this process). Importance sampling's dimension limit is the loop's
    dimension, so it is checked after the problem's set-up, whose eager parameter arithmetic
    is done here first: from then on nothing may compile."""
    import jax.monitoring

    from rvdjax.verify.evaluate import ProblemSpec, problem_for

    events = []
    listen = lambda name, *_, **__: events.append(name)  # noqa: E731
    cmds = [
        ["probability", "--method", "subset", "--budget", "50"],
        ["probability", "--method", "form", "--budget", "500"],
        [
            "probability",
            "--method",
            "is",
            "--budget",
            "500",
            "--disturbed",
            "--dispersion",
            "nav",
        ],  # fmt: skip
        ["worst", "--budget", "3", "--methods", "cma-es"],
        ["worst", "--budget", "30", "--methods", "psy"],
        ["worst", "--budget", "30", "--starts", "0"],
        ["worst", "--budget", "30", "--step", "0"],
    ]
    base = ["--requirement", "keep-out", "--dispersion", "paper003"]
    problem_for(ProblemSpec("thesis-vbar", "keep-out", "nav", disturbed=True))
    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        for cmd in cmds:
            t0 = time.perf_counter()
            argv = ["verify", cmd[0], "thesis-vbar", *base, *cmd[1:], "--out", str(tmp_path / "v")]
            assert main(argv) == 2, cmd
            err = capsys.readouterr().err.strip()
            assert len(err.splitlines()) == 1 and "--" in err, err
            assert time.perf_counter() - t0 < 10
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert not [e for e in events if "/jax/core/compile" in e], events
