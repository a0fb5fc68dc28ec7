"""The batch engine: slots fed by a queue of runs, results independent of how they were
batched, no NaN escaping a batch."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flights import stack

from rvdjax.bench import perturbed_states
from rvdjax.loop import RunStatus, fly
from rvdjax.loop.engine import EngineConfig, arrays_source, fly_batch, run_batch
from rvdjax.scenarios import SCENARIOS

SC = SCENARIOS["fastmpc-3d-free"]
PARAMS, X0 = SC.build()
LOOP = SC.loop(n_steps=25)  # short runs; about a third dock within the step budget
X0S = perturbed_states(X0, 12, rel=0.3).at[3].set(jnp.asarray(X0) * 0.002)  # run 3: close by
CHUNK = 4
FLY = jax.jit(lambda p, x: fly(LOOP, p, x)[1])  # one single-maneuver program for the file


def _bits(m):
    return [np.asarray(a) for a in jax.tree.leaves(m)]


@pytest.fixture(scope="module")
def reference():
    """12 runs through 4 slots (one chunk), 2 iterations per tick."""
    return fly_batch(LOOP, PARAMS, X0S, config=EngineConfig(slots=4, chunk=CHUNK, iterations=2))


@pytest.mark.parametrize(
    "slots, iterations, ticks",
    [(12, 2, 7), (4, 3, 256)],
    ids=["B12-short-segments", "K3"],
)
def test_same_bits_whatever_the_batching(reference, slots, iterations, ticks):
    """The same run gives the same bits whatever the number of slots, the iterations per tick
    (the grouping of solver iterations) and the segment length (for one chunk size)."""
    cfg = EngineConfig(slots=slots, chunk=CHUNK, iterations=iterations, ticks_per_segment=ticks)
    m = fly_batch(LOOP, PARAMS, X0S, config=cfg)
    for a, b in zip(_bits(m), _bits(reference), strict=True):
        np.testing.assert_array_equal(a, b)


def test_same_bits_whatever_the_order(reference):
    """Runs fed in reverse order (so they finish in another order and share slots with other
    runs) give the same bits per run."""
    rev = fly_batch(LOOP, PARAMS, X0S[::-1], config=EngineConfig(slots=4, chunk=CHUNK))
    for a, b in zip(_bits(rev), _bits(reference), strict=True):
        np.testing.assert_array_equal(a[::-1], b)


def test_engine_equals_single_flights(reference):
    """Each run equals the jitted single maneuver (another program: agreement to rounding)."""
    docked = 0
    for i in range(len(X0S)):
        m = FLY(PARAMS, X0S[i])
        docked += bool(m.docked)
        assert bool(m.docked) == bool(reference.docked[i])
        assert int(m.steps) == int(reference.steps[i])
        np.testing.assert_array_equal(np.asarray(m.status_counts), reference.status_counts[i])
        for field in ("effort_l1_N_s", "delta_v_m_s", "time_to_dock_s"):
            np.testing.assert_allclose(
                float(getattr(reference, field)[i]), float(getattr(m, field)), rtol=1e-9
            )
    assert 0 < docked < len(X0S)  # both endings (docked, out of steps) are exercised
    assert set(reference.status.tolist()) == {RunStatus.DOCKED, RunStatus.TIMEOUT}


def test_per_run_parameters_and_a_small_ring():
    """A queue that varies the family's parameters per run (chaser mass and thrust limit)
    through fewer slots than runs and a ring as small as the slots (collections stall the
    engine, results are unchanged); each run equals its own single flight."""
    changes = [dict(mass=5000.0, u_max=15.0), dict(), dict(mass=8000.0), dict(u_max=30.0)]
    built = [SC.build(**c, obstacles_on=False) for c in changes]
    params = stack([b[0] for b in built])
    x0s = X0S[:4]
    out = run_batch(
        LOOP,
        arrays_source(x0s, params=params),
        4,
        config=EngineConfig(slots=2, chunk=2, ring=2, ticks_per_segment=1000),
    )
    assert np.array_equal(out["run"], [0, 1, 2, 3])
    efforts = out["metrics"].effort_l1_N_s
    assert len(set(np.round(efforts, 6))) == 4  # the parameters made a difference
    for i, (p, _) in enumerate(built):
        m = FLY(p, x0s[i])
        assert bool(out["metrics"].docked[i]) == bool(m.docked)
        np.testing.assert_allclose(efforts[i], float(m.effort_l1_N_s), rtol=1e-9)


def test_no_nan_escapes_a_batch(reference):
    """A run with a non-finite initial state fails with finite (or inf) figures; the other
    runs of the batch are unaffected, bit for bit."""
    bad = X0S.at[5].set(jnp.full(6, jnp.nan))
    m = fly_batch(LOOP, PARAMS, bad, config=EngineConfig(slots=4, chunk=CHUNK))
    assert int(m.status[5]) == RunStatus.FAILED and not bool(m.docked[5])
    for leaf in _bits(m):
        if np.issubdtype(leaf.dtype, np.floating):
            assert not np.any(np.isnan(leaf))
    keep = np.arange(len(X0S)) != 5
    for a, b in zip(_bits(m), _bits(reference), strict=True):
        np.testing.assert_array_equal(a[keep], b[keep])


def test_engine_rejects_bad_use():
    with pytest.raises(ValueError, match="slots"):
        EngineConfig(slots=0)
    with pytest.raises(ValueError, match="Clarabel"):
        fly_batch(LOOP.replace(settings=SC.settings().__class__(backend="clarabel")), PARAMS, X0S)
    with pytest.raises(ValueError, match="params"):
        run_batch(LOOP, arrays_source(X0S), 3)
