"""Scenario files (TOML): every built-in scenario round-trips to an equal record that builds
bit-identical arrays and flies bit-identical steps; bad files are one-line errors naming the
file and the key, before anything is compiled; the command line reads them everywhere."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import subprocess
import sys
import time

import jax
import numpy as np
import pytest

from rvdjax.actuators.thrusters import ThrusterSet
from rvdjax.cli import main
from rvdjax.loop import fly
from rvdjax.scenarios import SCENARIOS, get_scenario
from rvdjax.scenarios.files import (
    load_scenario_file,
    same_scenario,
    scenario_from_toml,
    scenario_to_toml,
)
from rvdjax.study import replay


def same(a, b) -> bool:
    """Equal values of the same types all the way down (tuples stay tuples, ints ints, -0.0)."""
    if type(a) is not type(b):
        return False
    if isinstance(a, dict):
        return list(a) == list(b) and all(same(a[k], b[k]) for k in a)
    if isinstance(a, tuple):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, float):
        if math.isnan(a):
            return math.isnan(b)
        return a == b and math.copysign(1.0, a) == math.copysign(1.0, b)
    if isinstance(a, ThrusterSet):
        return all(
            same(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(ThrusterSet)
        )
    return a == b


def assert_bit_identical(tree_a, tree_b, what: str) -> None:
    leaves_a, def_a = jax.tree_util.tree_flatten(tree_a)
    leaves_b, def_b = jax.tree_util.tree_flatten(tree_b)
    assert def_a == def_b, what
    for i, (a, b) in enumerate(zip(leaves_a, leaves_b, strict=True)):
        a, b = np.asarray(a), np.asarray(b)
        assert a.dtype == b.dtype and a.shape == b.shape, (what, i)
        assert a.tobytes() == b.tobytes(), (what, i)


def roundtrip(sc, tmp_path):
    path = tmp_path / f"{sc.name}.toml"
    path.write_text(scenario_to_toml(sc))
    return load_scenario_file(path)


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_every_scenario_round_trips(name, tmp_path):
    sc = SCENARIOS[name]
    back = roundtrip(sc, tmp_path)
    for f in dataclasses.fields(sc):
        assert same(getattr(sc, f.name), getattr(back, f.name)), (name, f.name)
    plants = (False, True) if sc.thrusters is not None else (False,)
    for thr in plants:
        assert_bit_identical(sc.build(thrusters=thr), back.build(thrusters=thr), (name, thr))
        assert sc.loop(thrusters=thr) == back.loop(thrusters=thr), (name, thr)
    assert sc.loop("paper") == back.loop("paper")
    assert_bit_identical(sc.solver_params("paper"), back.solver_params("paper"), name)
    assert scenario_to_toml(back) == scenario_to_toml(sc)  # written again: the same text


@pytest.mark.parametrize(
    "name, thrusters",
    [("poseidyn-lqmpc", True), ("fastmpc-3d", False)],
)
def test_a_file_flies_the_same_bits(name, thrusters, tmp_path):
    sc = SCENARIOS[name]
    back = roundtrip(sc, tmp_path)
    run = jax.jit(fly, static_argnums=0)  # equal loops share one compiled program
    flights = []
    for s in (sc, back):
        params, x0 = s.build(thrusters=thrusters)
        flights.append(run(s.loop(n_steps=3, thrusters=thrusters), params, x0))
    assert_bit_identical(flights[0], flights[1], name)
    assert int(flights[1][1].steps) == 3


def test_get_scenario_takes_a_path(tmp_path):
    path = tmp_path / "mine.toml"
    path.write_text(scenario_to_toml(SCENARIOS["poseidyn-lqmpc"]))
    sc = get_scenario(str(path))
    assert sc.name == os.path.normpath(str(path))  # named by its path: it resolves again
    assert load_scenario_file(path).name == "poseidyn-lqmpc"  # the file's own name
    minimal = tmp_path / "minimal.toml"  # the family's defaults do the rest
    minimal.write_text('family = "poseidyn"\nx0 = [3.0, 2.5, 0.0, 0.0]\nn_steps = 60\n')
    sc = load_scenario_file(minimal)
    assert sc.name == "minimal" and sc.thrusters is None and sc.physical == {}
    assert sc.x0 == (3.0, 2.5, 0.0, 0.0) and isinstance(sc.x0[0], float)


def test_a_latched_sense_is_read_from_a_file_and_printed(tmp_path):
    """[config] latch_turn = true reaches the family's configuration and adds its assumption
    to the printed notes; the built-in thesis-vbar (per-step reading) prints none of it."""
    text = scenario_to_toml(SCENARIOS["thesis-vbar"])
    assert "latch_turn" not in text  # off: not written
    path = tmp_path / "latched.toml"
    path.write_text(text.replace("N = [30, 15, 12]", "N = [30, 15, 12]\nlatch_turn = true"))
    sc = load_scenario_file(path)
    assert sc.loop().config.family_config.latch_turn is True
    added = set(sc.notes("accurate")) - set(SCENARIOS["thesis-vbar"].notes("accurate"))
    assert len(added) == 1 and "latch_turn" in added.pop()
    assert not any("latch_turn" in n for n in SCENARIOS["thesis-vbar"].notes("accurate"))


# ----------------------------------------------------------------------------------- errors

THESIS = scenario_to_toml(SCENARIOS["thesis-vbar"])


def edited(old: str, new: str, text: str = THESIS) -> str:
    assert text.count(old) == 1, old
    return text.replace(old, new)


@pytest.mark.parametrize(
    "text, key, words",
    [
        (edited("\nmass = 14.0", "\nmasss = 14.0"), "physical.masss", "allowed in [physical]"),
        (edited("\nmass = 14.0", '\nmass = "heavy"'), "physical.mass", "must be a number"),
        (edited("\nmass = 14.0", "\nmass = -1.0"), "physical.mass", "in (0, inf) kg"),
        (edited("\nmass = 14.0", ""), "physical.mass", "missing required key"),
        (edited("altitude_m = 500000.0", "altitude_m = [1.0, [2.0]]"), "altitude_m", "rectan"),
        (edited("altitude_m = 500000.0", 'altitude_m = [1.0, "2"]'), "physical.altitude_m[1]", ""),
        (edited('family = "three-phase"', ""), "family", "missing required key"),
        (edited('family = "three-phase"', 'family = "x"'), "family", "rendezvous"),
        (edited("x0 = [140.0, -1580.0, 60.0, -0.9, -0.32, 0.0]", "x0 = [1.0]"), "x0", "6 numbers"),
        (edited("\nn_steps = 300", ""), "n_steps", "missing required key"),
        (edited("\nn_steps = 300", "\nn_steps = 2.5"), "n_steps", "an integer"),
        (edited("N = [30, 15, 12]", "N = [30, 15.0, 12]"), "config.N[1]", "an integer"),
        (edited("N = [30, 15, 12]", "N = [30, 15]"), "config.N", "three ints"),
        (edited("thrust_N = 0.5", "thrust_N = [1.0, 1.0, -1.0, 1, 1, 1]"), "thrust_N[2]", ">"),
        (edited("thrust_N = 0.5", "thrust_N = [1.0, 1.0]"), "thrusters.thrust_N", "one per"),
        (edited('modulator = "pwm"', 'modulator = "x"'), "thrusters.modulator", "delta-sigma"),
        (edited("isp_s = 220.0", "isp_s = 0.0"), "thrusters.isp_s", "> 0 s"),
        (edited("[config]", "[config]\nfoo = 1"), "config.foo", "n_faces"),
        (edited("[config]", "[solver]\nmax_iter = 0\n\n[config]"), "solver.max_iter", ">= 1"),
        (edited("thesis = 13.28", 'thesis = "x"'), "published.delta_v_m_s.thesis", "a number"),
        ("name = 1\n" + THESIS.replace('name = "thesis-vbar"\n', ""), "name", "a string"),
        ("colour = 1\n" + THESIS, "colour", "allowed at the top level"),
    ],
)
def test_bad_files_name_the_file_and_the_key(text, key, words):
    with pytest.raises(ValueError) as err:
        scenario_from_toml(text, where="dir/my.toml")
    msg = str(err.value)
    assert msg.startswith("dir/my.toml: ") and "\n" not in msg, msg
    assert key in msg and words in msg, msg


def test_a_missing_or_broken_file(tmp_path):
    with pytest.raises(ValueError, match="nope.toml: no such scenario file"):
        get_scenario(str(tmp_path / "nope.toml"))
    bad = tmp_path / "bad.toml"
    bad.write_text("family = \n")
    with pytest.raises(ValueError, match=r"bad.toml: not valid TOML: .*line 1"):
        load_scenario_file(bad)


# ------------------------------------------------------------------------------ command line


def test_cli_bad_file_exits_2_with_one_line(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text(edited("\nmass = 14.0", "\nmass = -1.0"))
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "rvdjax.cli", "run", str(bad)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    seconds = time.perf_counter() - t0
    assert proc.returncode == 2 and proc.stdout == "", proc
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and f"{bad}: physical.mass must be" in lines[0], proc.stderr
    assert seconds < 30, seconds  # nothing compiled (the import of JAX is most of it)


def test_cli_scenario_show_round_trips(tmp_path, capsys):
    assert main(["scenario", "show", "spot-2d-a", "--toml"]) == 0
    text = capsys.readouterr().out
    assert text.startswith("# rvdjax scenario file, written by `rvdjax scenario show spot-2d-a")
    back = scenario_from_toml(text)
    sc = SCENARIOS["spot-2d-a"]
    assert all(same(getattr(sc, f.name), getattr(back, f.name)) for f in dataclasses.fields(sc))
    out = tmp_path / "my.toml"
    assert main(["scenario", "show", "spot-2d-a", "--out", str(out)]) == 0
    assert out.read_text() == text and "rvdjax run" in capsys.readouterr().out
    assert main(["scenario", "show", str(out)]) == 0  # a file's summary
    summary = capsys.readouterr().out
    assert summary.startswith(f"{out}: SPOT 2-D docking") and "thrusters: SPOT RED" in summary
    assert main(["scenario", "show", "spot-2d-a", "--out", str(tmp_path / "x.txt")]) == 2
    assert "--out" in capsys.readouterr().err


def test_study_with_a_file_resumes_and_replays(tmp_path, monkeypatch, capsys):
    """A file study flies the copy it keeps (DIR/scenario.toml): resume with the same file,
    refuse an edited one, replay a run from the original path or the copy."""
    monkeypatch.chdir(tmp_path)
    mine = tmp_path / "mine.toml"
    mine.write_text(scenario_to_toml(SCENARIOS["poseidyn-lqmpc"]))
    study = ["study", "montecarlo", "mine.toml", "--runs", "2", "--n-steps", "3"]
    study += ["--slots", "32", "--out", "st", "--quiet", "--json"]
    assert main(study) == 0
    s = json.loads(capsys.readouterr().out)
    copy = str(tmp_path / "st" / "scenario.toml")
    assert os.path.samefile(s["scenario"], copy) and s["runs"] == 2
    assert load_scenario_file(copy).name == "poseidyn-lqmpc"
    assert main([*study, "--resume"]) == 0  # nothing left to fly
    assert json.loads(capsys.readouterr().out)["runs_flown"] == 0
    mine.write_text(edited("n_steps = 60", "n_steps = 61", mine.read_text()))
    assert main([*study, "--resume"]) == 2
    assert "is not the scenario the study in st flies" in capsys.readouterr().err
    spec, flight = replay("st", 1)  # what `rvdjax run` replays
    sc, loop = flight.scenario, flight.loop
    assert sc.name == spec.scenario and loop.config.n_steps == 3
    assert same_scenario(copy, spec.scenario)  # `rvdjax run COPY --study st --run 1`
    assert main(["run", "mine.toml", "--study", "st", "--run", "1"]) == 2  # edited: refused
    assert "flies" in capsys.readouterr().err
