"""Paper mode (paper 000 Algorithm 1: fixed kappa, <= 10 Newton steps) flies every registered
scenario: it docks, the truth trajectory violates no keep-out / cone / overshoot constraint, and
every solve ends converged or at the iteration cap (issue 3, "Must show").

Scenarios whose closed loops are one program (same loop, static configuration and kappa) are
flown as one vmapped batch, so each family compiles once.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest

from rvdjax.scenarios import SCENARIOS
from rvdjax.solver import Status

# fastmpc-3d in paper mode is covered by tests/test_sim.py
SKIP = {"fastmpc-3d"}


def _families():
    groups: dict = {}
    for name, sc in SCENARIOS.items():
        if name in SKIP:
            continue
        config = dataclasses.replace(sc.config, settings=sc.settings("paper"))
        groups.setdefault((sc.fly, config), []).append(name)
    return [(names, config, fly) for (fly, config), names in groups.items()]


FAMILIES = _families()


def test_every_scenario_is_in_a_family():
    flown = {n for names, _, _ in FAMILIES for n in names}
    assert flown | SKIP == set(SCENARIOS)


@pytest.mark.parametrize("family", FAMILIES, ids=lambda f: "+".join(f[0]))
def test_paper_mode_docks_cleanly(family):
    names, config, fly = family
    built = [SCENARIOS[n].build() for n in names]
    for n, (params, x0) in zip(names, built, strict=True):
        SCENARIOS[n].validate(params, x0, config)
    params = jax.tree.map(lambda *a: np.stack(a), *[b[0] for b in built])
    x0 = np.stack([b[1] for b in built])
    _, m = jax.jit(jax.vmap(lambda p, x: fly(p, x, config)))(params, x0)
    m = jax.tree.map(np.asarray, m)
    for i, n in enumerate(names):
        counts = m.status_counts[i]
        assert m.docked[i], f"{n}: did not dock in paper mode"
        assert m.max_violation_m[i] <= 1e-9, f"{n}: violation {m.max_violation_m[i]:.3g} m"
        assert counts[Status.INFEASIBLE] == 0 and counts[Status.NONFINITE] == 0, (n, counts)
        assert counts[Status.CONVERGED] > 0, (n, counts)
        assert np.isfinite(m.effort_l1_N_s[i]) and np.isfinite(m.time_to_dock_s[i])
