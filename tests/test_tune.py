"""Differentiable tuning (issue 9): parameter maps, the surrogate, the command and its files
(the gradient checks: tests/test_tune_gradients.py)."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

from rvdjax.cli import main
from rvdjax.scenarios import get_scenario
from rvdjax.tune import LossWeights, ParameterSpace, Tuner, TuneSpec, parse_loss
from rvdjax.tune.loss import run_terms

# family -> (scenario, tuned names); every family's full list of tunables
CASES = {
    "rendezvous": ("fastmpc-3d", ("Q", "R")),
    "planar-docking": ("spot-2d-a", ("Q", "R", "gamma", "gap")),
    "poseidyn": ("poseidyn-lqmpc", ("Q", "R", "terminal_scale", "ts")),
    "three-phase": ("thesis-vbar", ("Q", "R", "lam", "ts")),
}

# ------------------------------------------------------------------ maps and the surrogate


@pytest.mark.parametrize("family", list(CASES))
def test_hand_values_reproduce_the_scenario_parameters(family):
    """theta -> values -> params at the hand tuning gives back make_params' parameters,
    including the derived fields (DARE terminal weights, discrete models from Ts)."""
    name, names = CASES[family]
    sc = get_scenario(name)
    params, _ = sc.build()
    sp = sc.solver_params("accurate")
    space = ParameterSpace.of(sc, names, params, sp, "accurate")
    p, _ = space.apply(params, sp, space.values(space.theta()))
    for field in ("A", "B", "Q", "R", "Q_f"):
        np.testing.assert_allclose(
            np.asarray(getattr(p, field)), np.asarray(getattr(params, field)), rtol=1e-8, atol=1e-9
        )


def test_transforms_keep_values_valid():
    sc = get_scenario("spot-2d-a")
    params, _ = sc.build()
    sp = sc.solver_params("paper")
    space = ParameterSpace.of(sc, ("gamma", "R", "kappa"), params, sp, "paper")
    for big in (-50.0, 50.0):
        v = space.values({n: jnp.full(np.shape(a), big) for n, a in space.hand.items()})
        assert 0.0 <= float(v["gamma"]) <= 1.0
        assert np.all(np.asarray(v["R"]) >= 0) and float(v["kappa"]) >= 0
    back = space.values(space.theta())
    for n in space.names:
        np.testing.assert_allclose(np.asarray(back[n]), space.hand[n], rtol=1e-12)
    p, s = space.apply(params, sp, {**space.hand, "kappa": np.asarray(0.01)})
    assert float(s.kappa) == pytest.approx(0.01)


def test_surrogate_terms_of_a_full_maneuver():
    """E equals the exact headline effort (the smoothing is below 1e-8), T lies between 0
    and the time flown, M is 0 without violation."""
    spec = TuneSpec(scenario="poseidyn-lqmpc", params=("Q",), train=1, heldout=1, steps=0)
    tuner = Tuner(spec)
    sc = tuner.scenario
    from rvdjax.loop import fly

    infos, m = jax.jit(lambda x: fly(tuner.loop, tuner.params, x))(jnp.asarray(sc.x0))
    E, T, M = run_terms(tuner.loop, tuner.params, infos, tuner.effort_key)
    assert bool(m.docked) and float(m.max_violation_m) == 0.0
    np.testing.assert_allclose(float(E), float(getattr(m, tuner.effort_key)), rtol=1e-7)
    assert 0.0 < float(T) < float(m.time_to_dock_s)
    assert float(M) == 0.0


def test_parse_loss():
    assert parse_loss("time=2") == LossWeights(effort=1.0, time=2.0, margin=10.0)
    assert parse_loss(None) == LossWeights()
    for bad, word in (("time", "NAME=WEIGHT"), ("speed=1", "unknown"), ("time=-1", ">= 0")):
        with pytest.raises(ValueError, match=word):
            parse_loss(bad)
    with pytest.raises(ValueError, match="both"):
        LossWeights(effort=0.0, time=0.0)


# ------------------------------------------------------------------ the command and its files


@pytest.mark.slow  # 28 s; `pytest -m slow`
def test_tune_command_files_and_run_params(tmp_path, capsys):
    out = tmp_path / "tuned"
    argv = ["tune", "poseidyn-lqmpc", "--params", "Q,R,terminal_scale", "--train", "2"]
    argv += ["--heldout", "2", "--steps", "2", "--n-steps", "40", "--lr", "0.1"]
    assert main([*argv, "--out", str(out), "--json", "--quiet"]) == 0
    r = json.loads(capsys.readouterr().out)
    for label in ("hand", "tuned", "random_search"):
        m = r["heldout"][label]
        for key in ("effort", "time_to_dock_s", "docked_fraction", "max_violation_m", "loss"):
            assert key in m
    for key in ("grad_step_s", "forward_s", "peak_memory_mb"):
        assert r[key] > 0
    assert r["train_loss"]["tuned"] <= r["train_loss"]["hand"]
    hist = pd.read_parquet(out / "history.parquet")
    counts = hist.groupby("method")["evaluations"].max()
    assert counts["gradient"] == counts["random"] == 3  # the same budget
    ho = pd.read_parquet(out / "heldout.parquet")
    assert len(ho) == 3 * 2 and set(ho["tuning"]) == {"hand", "tuned", "random_search"}
    # the tuned file flies, and gives the held-out run's figures
    doc = json.loads((out / "tuned_params.json").read_text())
    assert set(doc["parameters"]) == {"Q", "R", "terminal_scale"}
    assert doc["provenance"]["definition_sha256"] == r["provenance"]["definition_sha256"]
    assert (
        main(["run", "poseidyn-lqmpc", "--params", str(out / "tuned_params.json"), "--json"]) == 0
    )
    run = json.loads(capsys.readouterr().out)
    assert run["tuned_params"] == str(out / "tuned_params.json")
    assert run["docked"]


def _error(argv, capsys) -> str:
    assert main(argv) == 2
    return capsys.readouterr().err


def test_bad_input_is_refused_before_any_work(tmp_path, capsys):
    assert "gamma" in _error(["tune", "poseidyn-lqmpc", "--params", "Q,gamma"], capsys)
    err = _error(["tune", "spot-2d-a", "--params", "kappa"], capsys)
    assert "paper mode" in err
    assert ">= 1" in _error(["tune", "poseidyn-lqmpc", "--train", "0"], capsys)
    assert ">= 0" in _error(["tune", "poseidyn-lqmpc", "--loss", "time=-2"], capsys)
    # a tuned file for another scenario, and values out of range
    f = tmp_path / "p.json"
    f.write_text(
        json.dumps(
            {
                "format": "rvdjax-tuned-params/1",
                "scenario": "spot-2d-a",
                "mode": "accurate",
                "parameters": {"gamma": 1.5},
            }
        )
    )
    assert "tuned for" in _error(["run", "poseidyn-lqmpc", "--params", str(f)], capsys)
    err = _error(["run", "spot-2d-a", "--params", str(f)], capsys)
    assert "gamma" in err and "(0, 1)" in err
    (tmp_path / "q.json").write_text("{}")
    assert "not an rvdjax" in _error(
        ["run", "spot-2d-a", "--params", str(tmp_path / "q.json")], capsys
    )
