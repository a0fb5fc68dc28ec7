"""Batch studies: statistics, samplers, reproducibility from (seed, run index), the tidy
table, resuming a killed study bit for bit, and the same table from 4 devices or 2 processes."""

from __future__ import annotations

import json
import math
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest
from scipy import stats as st

from rvdjax.dynamics import mean_motion
from rvdjax.scenarios import get_scenario
from rvdjax.study import StudySpec, read_table, replay, run_study, summarize
from rvdjax.study import stats as sstats
from rvdjax.study.runner import run_inputs
from rvdjax.study.samplers import paper003_initial_state, parse_dist

# --------------------------------------------------------------------------------- statistics


@pytest.mark.parametrize("k, n", [(1, 10), (45, 50), (99, 100), (500, 500)])
def test_clopper_pearson_lower_bound_meets_its_definition(k, n):
    """P(X >= k | p_L) = 1 - confidence for the binomial (the exact one-sided bound)."""
    pl = sstats.clopper_pearson_lower(k, n, 0.9)
    assert st.binom.sf(k - 1, n, pl) == pytest.approx(0.1, rel=1e-8)
    assert pl < k / n


def test_zero_failure_rule_gives_852_runs_for_3_sigma_at_90_percent():
    assert sstats.zero_failure_runs(0.9973, 0.9) == 852
    # n zero-failure runs demonstrate (1 - C)^(1/n): the Clopper-Pearson bound with k = n
    assert sstats.demonstrated_reliability(852, 0.9) >= 0.9973
    assert sstats.demonstrated_reliability(851, 0.9) < 0.9973
    assert sstats.demonstrated_reliability(852, 0.9) == pytest.approx(
        sstats.clopper_pearson_lower(852, 852, 0.9), rel=1e-9
    )


def test_percentiles_ignore_non_finite_values():
    v = np.r_[np.arange(101.0), np.inf, np.nan]
    p = sstats.percentiles(v)
    assert p["p50"] == 50.0 and p["p95"] == 95.0
    assert p["p99.73"] == pytest.approx(np.percentile(np.arange(101.0), 99.73))
    assert sstats.percentiles([np.inf])["p50"] is None


@pytest.mark.parametrize("bad", [(11, 10), (-1, 10)])
def test_statistics_reject_bad_counts(bad):
    with pytest.raises(ValueError, match="successes"):
        sstats.clopper_pearson_lower(*bad)
    with pytest.raises(ValueError, match="confidence"):
        sstats.zero_failure_runs(0.99, 1.0)


# --------------------------------------------------------------------------------- samplers


def test_distributions_parse_and_reject_bad_text():
    assert parse_dist("uniform(1, 2)").args == (1.0, 2.0)
    assert parse_dist("+normal(0,10)").op == "+"
    assert parse_dist("3.5").kind == "const"
    for bad, msg in [
        ("uniform(2,1)", "low < high"),
        ("normal(0)", "takes 2"),
        ("gamma(1,2)", "unknown distribution"),
        ("normal(0,-1)", "sigma >= 0"),
        ("xyz", "cannot read"),
    ]:
        with pytest.raises(ValueError, match=msg):
            parse_dist(bad)


def test_paper003_initial_states_follow_section_4():
    """Range U(150, 2500) m in the orbital plane; velocity = no-drift + N(0, 0.5 m/s)."""
    n = float(mean_motion(altitude_m=500e3))
    keys = jax.random.split(jax.random.key(3), 4000)
    x = np.asarray(jax.vmap(lambda k: paper003_initial_state(k, n))(keys))
    r = np.linalg.norm(x[:, :3], axis=1)
    assert r.min() >= 150.0 and r.max() <= 2500.0
    assert st.kstest((r - 150.0) / 2350.0, "uniform").pvalue > 1e-3
    assert np.all(x[:, 2] == 0.0)
    dv = x[:, 3:] - np.stack([0 * r, -2 * n * x[:, 0], 0 * r], axis=1)
    assert np.all(np.abs(dv.mean(axis=0)) < 4 * 0.5 / math.sqrt(len(x)))
    np.testing.assert_allclose(dv.std(axis=0), 0.5, rtol=0.05)


SC = get_scenario("fastmpc-3d-free")
BASE = dict(
    kind="montecarlo",
    scenario=SC.name,
    n_steps=25,
    slots=4,
    chunk=4,
    vary=(("x0", "*normal(1,0.2)"),),
)


def test_a_run_is_reproducible_from_seed_and_index():
    spec = StudySpec(n_initial=10, replicates=2, **BASE)
    all_runs = run_inputs(spec, SC, np.arange(20))
    one = run_inputs(spec, SC, [13])
    np.testing.assert_array_equal(one.x0[0], all_runs.x0[13])
    assert jnp.array_equal(jax.random.key_data(one.keys[0]), jax.random.key_data(all_runs.keys[13]))
    # replicates of one initial condition share the initial state, not the noise key
    assert (one.ic[0], one.replicate[0]) == (6, 1)
    other = run_inputs(StudySpec(n_initial=10, replicates=2, **{**BASE, "seed": 1}), SC, [13])
    assert not np.array_equal(other.x0[0], one.x0[0])


def test_study_specs_are_checked_before_anything_runs():
    with pytest.raises(ValueError, match="unknown parameter 'nope'"):
        StudySpec(n_initial=2, **{**BASE, "vary": (("nope", "normal(0,1)"),)}).validate(SC)
    with pytest.raises(ValueError, match="use --grid"):
        spec = StudySpec(n_initial=2, **{**BASE, "vary": (("N", "choice(10,20)"),)})
        spec.validate(SC)
    with pytest.raises(ValueError, match="nav_filter needs disturbed"):
        StudySpec(n_initial=2, nav_filter=True, **BASE)
    with pytest.raises(ValueError, match="n_initial"):
        StudySpec(n_initial=0, **BASE)


def test_a_horizon_grid_compiles_once_per_value():
    spec = StudySpec(n_initial=2, **{**BASE, "kind": "sweep", "grid": (("N", (10, 15)),)})
    spec.validate(SC)
    assert [p.values for p in spec.points] == [{"N": 10.0}, {"N": 15.0}]
    assert spec.n_runs == 4


def test_two_parameter_sweeps_draw_one_panel_per_horizon():
    from rvdjax.study.figures import _panels

    grid = (("Ts", (20.0, 30.0, 40.0)), ("N", (10.0, 15.0)))
    spec = StudySpec(n_initial=2, **{**BASE, "kind": "sweep", "grid": grid})
    panels = _panels(spec)
    assert [name for name, _ in panels] == ["N = 10", "N = 15"]
    for (_, series), n in zip(panels, (10.0, 15.0), strict=True):
        # each panel holds the three sample times at its horizon, by point index
        assert [spec.points[i].values for i, _ in series] == [
            {"Ts": ts, "N": n} for ts in (20.0, 30.0, 40.0)
        ]
        assert [label for _, label in series] == ["Ts=20", "Ts=30", "Ts=40"]
    one = StudySpec(n_initial=2, **{**BASE, "kind": "sweep", "grid": (("N", (10, 15)),)})
    assert _panels(one) == [("", [(0, "N=10"), (1, "N=15")])]


# --------------------------------------------------------------------------------- a study


def test_a_study_writes_a_tidy_table_and_replays_a_run(tmp_path):
    spec = StudySpec(n_initial=6, **BASE)
    out = tmp_path / "mc"
    timing = run_study(spec, out, progress=False, flush_rows=2)
    df = read_table(out)
    assert timing["runs_flown"] == 6 and list((out / "runs").glob("part-*.parquet"))
    assert df["run"].tolist() == list(range(6))
    numeric = df.select_dtypes("number")
    assert not numeric.isna().any().any()
    assert set(df["status"]) <= {"docked", "timeout", "failed"}
    assert (df["failure"] == "").sum() <= df["docked"].sum()
    s = summarize(out)
    assert s["runs"] == 6 and s["docked"] == int(df["docked"].sum())
    assert 0.0 <= s["success_lower_bound"] <= s["success_fraction"]
    # the replay flies exactly that run's inputs
    from rvdjax.loop import fly

    _, flight = replay(out, 4)
    loop, params, x0, key, sp = (
        flight.loop,
        flight.params,
        flight.x0,
        flight.key,
        flight.solver_params,
    )
    _, m = jax.jit(lambda p, x, k: fly(loop, p, x, k, sp))(params, x0, key)
    row = df.iloc[4]
    assert bool(m.docked) == bool(row["docked"]) and int(m.steps) == int(row["steps"])
    np.testing.assert_allclose(float(m.effort_l1_N_s), row["effort_l1_N_s"], rtol=1e-9)
    np.testing.assert_allclose(np.asarray(x0), row[[f"x0_{j}" for j in range(6)]].to_numpy(float))
    with pytest.raises(ValueError, match="--resume"):
        run_study(spec, out, progress=False)
    with pytest.raises(ValueError, match="different study"):
        run_study(StudySpec(n_initial=7, **BASE), out, resume=True, progress=False)


# ------------------------------------------------------------------ kill, resume, scale out

CLI = [sys.executable, "-m", "rvdjax.cli", "study", "montecarlo", SC.name]
# runs of 12 steps: what these tests check (the table's bits, parts, resumption, devices) does
# not need whole maneuvers, and each child process flies the 48 runs at the tests' XLA
# optimisation level 0 (25 steps: about 14 s of a child's 32 s on a 2-core VM)
ARGS = ["--n-steps", "12", "--slots", "4", "--chunk", "4", "--vary", "x0=*normal(1,0.2)"]
ARGS += ["--quiet", "--flush-rows", "2"]
RUNS = 48  # two waves of the distributed test's 24 slots; flying them dominates these tests


def _env(cache: Path, **extra) -> dict:
    env = dict(os.environ)
    env.update(
        JAX_COMPILATION_CACHE_DIR=str(cache),
        JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0.2",
        JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="0",
        **extra,
    )
    return env


def _cli(args, env, **kw):
    return subprocess.run(CLI + args, env=env, capture_output=True, text=True, **kw)


@pytest.fixture(scope="module")
def study_env(tmp_path_factory):
    root = tmp_path_factory.mktemp("study")
    env = _env(root / "cache")
    ref = root / "reference"
    r = _cli(["--runs", str(RUNS), "--out", str(ref), *ARGS], env, timeout=600)
    assert r.returncode == 0, r.stderr
    return root, env, read_table(ref)


def _frames_equal(a: pd.DataFrame, b: pd.DataFrame) -> None:
    pd.testing.assert_frame_equal(a, b, check_exact=True)


def test_a_killed_study_resumes_to_the_same_table_bit_for_bit(study_env):
    root, env, reference = study_env
    out = root / "killed"
    proc = subprocess.Popen(
        CLI + ["--runs", str(RUNS), "--out", str(out), *ARGS],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    parts = out / "runs"
    t0 = time.monotonic()
    while time.monotonic() - t0 < 300 and proc.poll() is None:
        if parts.exists() and len(list(parts.glob("part-*.parquet"))) >= 2:
            break
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    partial = read_table(out)
    assert 0 < len(partial) < RUNS, "the study finished before it could be killed"
    r = _cli(
        ["--runs", str(RUNS), "--out", str(out), "--resume", "--json", *ARGS], env, timeout=600
    )
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)  # nothing lost, nothing flown twice
    assert (summary["runs_skipped"], summary["runs_flown"]) == (len(partial), RUNS - len(partial))
    _frames_equal(read_table(out), reference)


def _slurm_job() -> tuple[int, int]:
    """A Slurm job id whose coordinator port (JAX: 61440 + id mod 4096) is free here."""
    for _ in range(50):
        job = int.from_bytes(os.urandom(3), "little")
        port = job % 4096 + 61440
        with socket.socket() as s:
            try:
                s.bind(("localhost", port))
            except OSError:
                continue
        return job, port
    raise RuntimeError("no free port in 61440-65535")


def test_two_processes_of_two_devices_give_the_same_table(study_env):
    """Two processes as Slurm's srun would start them on two nodes (its environment
    simulated; the second reads it with --coordinator auto, the first is given the same
    coordinator explicitly), each with two devices (``--devices 2``) and 12 slots instead of
    4: the slots split over four devices in two processes, and the same table, bit for bit.
    (One test for devices and processes: each spawns interpreters that compile the study,
    about 20 s of the suite's time apiece.)"""
    root, env, reference = study_env
    out = root / "distributed"
    job, port = _slurm_job()
    args = [a if a != "4" or ARGS[i - 1] != "--slots" else "12" for i, a in enumerate(ARGS)]
    args += ["--devices", "2"]
    # (the optimisation level of the tests' XLA_FLAGS kept: the reference is flown at it)
    flags = env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2"
    env = {**env, "XLA_FLAGS": flags.strip()}
    slurm = dict(
        SLURM_JOB_ID=str(job), SLURM_STEP_NODELIST="localhost", SLURM_NTASKS="2",
        SLURM_PROCID="1", SLURM_LOCALID="0",
    )  # fmt: skip
    explicit = ["--coordinator", f"localhost:{port}", "--num-processes", "2", "--process-id", "0"]
    runs = [(explicit, env), (["--coordinator", "auto"], {**env, **slurm})]
    procs = [
        subprocess.Popen(
            CLI + ["--runs", str(RUNS), "--out", str(out), *args, *extra],
            env=e,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for extra, e in runs
    ]
    for p in procs:
        _, err = p.communicate(timeout=600)
        assert p.returncode == 0, err
    files = {f.name.split("-")[1] for f in (out / "runs").glob("part-*.parquet")}
    assert files == {"P000", "P001"}  # each process wrote its own parts
    config = json.loads((out / "config.json").read_text())
    envs = config["provenance"]["environments"].values()
    assert [e["device_count"] for e in envs] == [4]  # two processes of two devices each
    _frames_equal(read_table(out), reference)


# ------------------------------------------------------------------------- command line


@pytest.mark.parametrize(
    "argv, message",
    [
        (["study", "sweep", "poseidyn-lqmpc"], "needs at least one --grid"),
        (["study", "montecarlo", "poseidyn-lqmpc", "--vary", "nope=normal(0,1)"], "nope"),
        (["study", "montecarlo", "poseidyn-lqmpc", "--vary", "mass=gamma(1)"], "gamma"),
        (["study", "montecarlo", "poseidyn-lqmpc", "--runs", "0"], "--runs must be >= 1"),
        (["study", "sweep", "poseidyn-lqmpc", "--grid", "N=10.5"], "integers"),
        (["study", "montecarlo", "nope"], "unknown scenario"),
        (["run", "poseidyn-lqmpc", "--study", "x"], "--study DIR and --run R"),
        (["run", "poseidyn-lqmpc", "--nav-filter"], "--nav-filter needs --disturbed"),
    ],
)
def test_study_command_line_rejects_bad_input_before_flying(argv, message, tmp_path, capsys):
    from rvdjax.cli import main

    if argv[0] == "study":
        argv = [*argv, "--out", str(tmp_path / "s"), "--quiet"]
    assert main(argv) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "s" / "runs").exists()
