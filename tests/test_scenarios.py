"""Scenarios as data: records per paper, one table of families, checks run once at build."""

from __future__ import annotations

import numpy as np
import pytest
from flights import first, flight

from rvdjax.families import FAMILIES, get_family
from rvdjax.scenarios import SCENARIOS, get_scenario, paper_kappa
from rvdjax.solver import SolverParams


def test_every_scenario_builds_with_its_family():
    for name, sc in SCENARIOS.items():
        assert sc.family in FAMILIES, name
        params, x0 = sc.build()
        fam = get_family(sc.family)
        assert x0.shape == (fam.layout.nx,), name
        loop = sc.loop()
        sc.check(params, x0, loop)
        assert loop.config.n_steps == sc.n_steps and loop.family is fam
        assert sc.description and sc.source and sc.assumptions, name
        for metric in sc.published:  # published figures name fields of the metrics
            assert metric in ("effort_l1_N_s", "delta_v_m_s", "time_to_dock_s"), (name, metric)


def test_one_family_per_paper_module_and_the_example():
    by_family = {}
    for sc in SCENARIOS.values():
        by_family.setdefault(sc.family, set()).add(sc.name)
    assert set(by_family) == set(FAMILIES)
    assert "vbar-400km-heavy-target" in by_family["three-phase"]


def test_unknown_names_are_clear_errors():
    with pytest.raises(ValueError, match="unknown scenario 'nope'.*fastmpc-3d"):
        get_scenario("nope")
    with pytest.raises(ValueError, match="unknown family 'nope'.*rendezvous"):
        get_family("nope")


def test_build_overrides_are_checked():
    sc = SCENARIOS["fastmpc-3d"]
    p, _ = sc.build(mass=5000.0)
    assert float(p.plant.mass) == 5000.0
    with pytest.raises(ValueError, match=r"mass must be finite and in \(0, inf\) kg"):
        sc.build(mass=-1.0)
    with pytest.raises(ValueError, match="x0 must have shape"):
        sc.build(x0=(1.0, 2.0))


def test_paper_kappa_and_solver_parameters():
    assert paper_kappa(10.0, 0.05) == pytest.approx(6.25e-3)
    assert paper_kappa(100.0, 0.05) == 0.05  # capped at paper 000's value
    sc = SCENARIOS["spot-2d-a"]
    sp = sc.solver_params("paper")
    assert isinstance(sp, SolverParams) and sp.kappa == pytest.approx(6.25e-3)
    assert sp.beta == 0.95 and sc.settings("paper").max_iter == 10
    assert any("kappa" in a for a in sc.notes("paper"))
    assert not any("kappa =" in a for a in sc.notes("accurate"))


def test_the_example_scenario_docks():
    """One record added a scenario no paper has (a V-bar approach to a heavier target in a
    lower orbit): it flies with the thesis' program and docks without violating a judged
    constraint."""
    sc = SCENARIOS["vbar-400km-heavy-target"]
    params, _ = sc.build()
    assert float(params.plant.drag.b_target) == pytest.approx(2.2 * 0.5 / 180.0)  # C_D A / m
    assert float(params.plant.drag.b_chaser) == pytest.approx(1.4 * 0.0366 / 14.0)
    _, _, infos, m = flight((sc.name,), n_steps=200)
    m = first(m)
    assert bool(m.docked) and float(m.max_violation_m) == 0.0
    assert np.all(np.asarray(m.phase_time_s) > 0)  # all three phases flown
