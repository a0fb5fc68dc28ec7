"""The one door from a scenario to a runnable set-up: FlightOptions, Scenario.flight and the
command line's shared flight options."""

import argparse
import pathlib

import jax
import numpy as np
import pytest

from rvdjax.cli import build_parser, main
from rvdjax.loop import fly
from rvdjax.scenarios import SCENARIOS, FlightOptions


@pytest.mark.parametrize(
    "values, words",
    [
        (dict(mode="fast"), "mode must be one of accurate, paper, barrier"),
        (dict(truth="kepler"), "truth must be one of linear"),
        (dict(nav_filter=True), "nav_filter needs disturbed"),
        (dict(faults=True), "faults needs thrusters"),
        (dict(n_steps=0), "n_steps must be >= 1"),
        (dict(time_limit_s=-1.0), "time_limit_s must be > 0"),
    ],
)
def test_bad_options_are_refused_naming_the_parameter(values, words):
    with pytest.raises(ValueError, match=words):
        FlightOptions(**values)


def test_a_scenario_without_thrusters_refuses_them_in_library_words():
    import dataclasses

    sc = dataclasses.replace(SCENARIOS["poseidyn-lqmpc"], thrusters=None)  # every record has one
    with pytest.raises(ValueError, match=r"^thrusters: scenario .* has no thruster set"):
        sc.flight(FlightOptions(thrusters=True))


def test_the_flight_flies_what_the_scenario_parts_fly():
    """The flight's parts are the scenario's build, loop and solver parameters, bit for bit,
    with the overrides applied to the parameters and the configuration."""
    sc = SCENARIOS["poseidyn-lqmpc"]
    opts = FlightOptions(mode="paper", n_steps=4, disturbed=True, seed=3)
    flight = sc.flight(opts, mass=1.1 * sc.physical["mass"])
    params, x0 = sc.build(mass=1.1 * sc.physical["mass"])
    loop = sc.loop("paper", n_steps=4, disturbed=True)
    assert flight.loop == loop
    assert flight.options is opts and flight.physical == {"mass": 1.1 * sc.physical["mass"]}
    for a, b in zip(jax.tree.leaves(flight.params), jax.tree.leaves(params), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    _, m = flight.fly()
    _, ref = jax.jit(lambda p, x, k, s: fly(loop, p, x, k, s))(
        params, x0, jax.random.key(3), sc.solver_params("paper")
    )
    for a, b in zip(jax.tree.leaves(m), jax.tree.leaves(ref), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # a run dispersed around the flight keeps its overrides and thrusters
    p2, _ = flight.build(x0=np.asarray(x0) + 1.0)
    np.testing.assert_array_equal(np.asarray(p2.plant.mass), np.asarray(params.plant.mass))


def _leaves(parser: argparse.ArgumentParser):
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield parser
    for action in subs:
        for child in action.choices.values():
            yield from _leaves(child)


FLIGHT_FLAGS = {
    "--mode",
    "--truth",
    "--disturbed",
    "--nav-filter",
    "--thrusters",
    "--n-steps",
    "--time-limit-s",
    "--seed",
}


@pytest.mark.parametrize(
    "path", ["run", "tune", "compare", "bench", "study montecarlo", "study sweep", "verify worst"]
)
def test_every_flying_command_takes_the_same_flight_options(path):
    parser = build_parser()
    for word in path.split():
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        parser = sub.choices[word]
    flags = {s for a in parser._actions for s in a.option_strings}
    expected = FLIGHT_FLAGS - ({"--mode"} if path == "compare" else set())
    assert expected <= flags
    helps = {a.option_strings[0]: a for a in parser._actions if a.option_strings}
    assert helps["--n-steps"].type is int and helps["--truth"].default == "linear"


def test_bad_flight_options_name_the_flag(capsys):
    assert main(["run", "poseidyn-lqmpc", "--n-steps", "0"]) == 2
    assert "--n-steps must be >= 1" in capsys.readouterr().err
    assert main(["tune", "poseidyn-lqmpc", "--thrusters"]) == 2
    assert "--judge-thrusters" in capsys.readouterr().err


def test_no_private_jax_imports():
    root = pathlib.Path(__file__).parents[1] / "rvdjax"
    offenders = [p for p in root.rglob("*.py") if "jax._src" in p.read_text()]
    assert offenders == []


def test_a_flight_builds_its_truth_blocks_for_their_names_once_per_shapes():
    """The names and kinds of a family's truth blocks (what a flight's empty accumulator and
    its metrics need) come from one abstract trace per hook, family configuration and
    argument shapes (rvdjax.loop.metrics.truth_kinds): tracing a flight builds the blocks
    twice, for their names and in the step; tracing it again with the same shapes per run,
    batched this time, builds them once, in the step (three times each without the shared
    trace). The kinds still judge the hard blocks, and the batched flight's figures are the
    single one's (to rounding)."""
    import dataclasses

    sc = SCENARIOS["poseidyn-lqmpc"]
    loop = sc.loop("paper", n_steps=3)
    calls, hook = [], loop.family.truth_blocks

    def counted(*args):
        calls.append(1)
        return hook(*args)

    # a hook of its own: nothing cached by another test
    law = dataclasses.replace(loop.family.law, truth_blocks=counted)
    loop = dataclasses.replace(loop, family=dataclasses.replace(loop.family, law=law))
    params, x0 = sc.build()
    sp = sc.solver_params("paper")

    def one(x, k):
        return fly(loop, params, x, k, sp)[1]

    single = jax.jit(one).trace(x0, jax.random.key(0))
    assert len(calls) == 2
    xs, keys = np.stack([x0, x0]), jax.random.split(jax.random.key(0), 2)
    batched = jax.jit(jax.vmap(one)).trace(xs, keys)
    assert len(calls) == 3
    m1 = single.lower().compile()(x0, jax.random.key(0))
    m2 = batched.lower().compile()(xs, keys)
    fc = loop.config.family_config
    blocks = counted(params, fc, loop.family.init(params, fc, x0), x0, 0.0)  # eagerly
    kinds = {b.name: b.kind for b in blocks}
    assert set(m1.margins_m) == set(kinds) and "monitor" in kinds.values()
    hard = min(float(m1.margins_m[n]) for n, kind in kinds.items() if kind == "hard")
    assert float(m1.max_violation_m) == max(0.0, -hard)
    for a, b in zip(jax.tree.leaves(m1), jax.tree.leaves(m2), strict=True):
        # (a batched program rounds some sums in another order: 1 ulp here and there)
        np.testing.assert_allclose(np.asarray(b)[0], np.asarray(a), rtol=1e-12, atol=0)
