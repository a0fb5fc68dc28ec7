"""The batch engine: slots fed by a queue of runs, results independent of how they were
batched (slots, refresh, blocks of the queue), runs kept in their lane, no NaN escaping a
batch, settings chosen for the device, a segment program that lowers for a GPU."""

from __future__ import annotations

import functools
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flights import stack

from rvdjax.bench import perturbed_states
from rvdjax.loop import RunStatus, fly
from rvdjax.loop import engine as E
from rvdjax.loop.engine import (
    Block,
    EngineConfig,
    accelerator_slots,
    arrays_source,
    auto_config,
    export_segment,
    fly_batch,
    run_batch,
    run_stream,
)
from rvdjax.loop.engine.slots import _strip_model, model_of, table_of
from rvdjax.loop.kernel import init, prepare
from rvdjax.scenarios import SCENARIOS
from rvdjax.solver.barrier import rows_of

SC = SCENARIOS["fastmpc-3d-free"]
PARAMS, X0 = SC.build()
LOOP = SC.loop(n_steps=25)  # short runs; about a third dock within the step budget
X0S = perturbed_states(X0, 12, rel=0.3).at[3].set(jnp.asarray(X0) * 0.002)  # run 3: close by
CHUNK = 4
SP = SC.solver_params()
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
    with pytest.raises(ValueError, match="refresh"):
        EngineConfig(refresh="sometimes")
    with pytest.raises(ValueError, match="Clarabel"):
        fly_batch(LOOP.replace(settings=SC.settings().__class__(backend="clarabel")), PARAMS, X0S)
    with pytest.raises(ValueError, match="params"):
        run_batch(LOOP, arrays_source(X0S), 3)


#: The accelerator's engine settings, small: one chunk, the compacted refresh, any slot.
ANY_SLOT = EngineConfig(slots=6, chunk=6, refresh="compacted", group=3, assign="any")


@pytest.fixture(scope="module")
def any_slot():
    return fly_batch(LOOP, PARAMS, X0S, config=ANY_SLOT)


@pytest.mark.parametrize(
    "config",
    [EngineConfig(slots=12, chunk=CHUNK, refresh="compacted"), ANY_SLOT],
    ids=["compacted-lanes", "compacted-any-slot"],
)
def test_the_compacted_refresh_flies_the_same_runs(reference, config, request):
    """Refreshing only the slots that need it (gathered into groups) flies the same runs: with
    lanes (each slot refreshed in its own lane) the same bits as the masked refresh, with runs
    in any slot the same steps and statuses and figures to rounding."""
    if config is ANY_SLOT:
        m = request.getfixturevalue("any_slot")
    else:
        m = fly_batch(LOOP, PARAMS, X0S, config=config)
    if config.assign == "lane":
        for a, b in zip(_bits(m), _bits(reference), strict=True):
            np.testing.assert_array_equal(a, b)
    else:
        np.testing.assert_array_equal(m.steps, reference.steps)
        np.testing.assert_array_equal(m.status_counts, reference.status_counts)
        np.testing.assert_allclose(m.delta_v_m_s, reference.delta_v_m_s, rtol=1e-9)


def test_a_refresh_group_is_written_back_to_its_slots_only():
    """The compacted refresh writes a group's rows back into the slots (``_put``: a select
    over every slot for small arrays, a scatter for large ones and for PRNG keys): each
    array, flags and keys included, gets the group's rows at the valid ids and keeps every
    other slot's, as NumPy's indexed assignment does; so too with the slots stored as the
    arrays' last axis."""
    from rvdjax.loop.engine.segment import SMALL_LEAF_BYTES, _put

    n, ids = 9, np.array([7, 2, 4, 0])
    valid = np.array([True, True, False, True])
    rng = np.random.default_rng(0)
    big = SMALL_LEAF_BYTES // 8 + 1  # float64 entries a slot past the small size
    tree = {
        "scalar": rng.normal(size=n),
        "flag": rng.random(n) > 0.5,
        "count": rng.integers(0, 9, (n, 4)).astype(np.int32),
        "big": rng.normal(size=(n, big)),
        "key": jax.random.split(jax.random.key(1), n),
    }
    new = {
        "scalar": rng.normal(size=4),
        "flag": rng.random(4) > 0.5,
        "count": rng.integers(10, 19, (4, 4)).astype(np.int32),
        "big": rng.normal(size=(4, big)),
        "key": jax.random.split(jax.random.key(2), 4),
    }
    got = jax.jit(_put)(tree, jnp.asarray(ids), jnp.asarray(valid), new)
    # the same with the slots as the arrays' last axis (an accelerator's tick loop)
    last = jax.tree.map(lambda a: jnp.moveaxis(a, 0, -1), tree)
    put_last = jax.jit(functools.partial(_put, last=True))
    got_last = put_last(last, jnp.asarray(ids), jnp.asarray(valid), new)
    got_last = jax.tree.map(lambda a: jnp.moveaxis(a, -1, 0), got_last)
    for name in tree:
        data = jax.random.key_data if name == "key" else np.asarray
        want = np.array(data(tree[name]))
        want[ids[valid]] = np.asarray(data(new[name]))[valid]
        np.testing.assert_array_equal(np.asarray(data(got[name])), want, name)
        np.testing.assert_array_equal(np.asarray(data(got_last[name])), want, name)


def test_a_queue_in_blocks_and_runs_in_their_lanes(reference):
    """A queue given in three blocks of inputs flies the same bits as one array; every slot's
    run is in the slot's lane (run r in lane r mod chunk: on a vectorising CPU a run's last
    bits depend on its lane, docs/history.md) while the blocks are swapped."""
    keys = jax.random.split(jax.random.key(0), len(X0S))
    blocks = [
        Block((X0S[lo : lo + 4], keys[lo : lo + 4], None, None), lo, lo + 4)
        for lo in range(0, len(X0S), 4)
    ]
    out = run_stream(
        LOOP,
        E.slots._pick_arrays,
        blocks,
        len(X0S),
        params=PARAMS,
        config=EngineConfig(slots=8, chunk=CHUNK, ticks_per_segment=5),
    )
    assert out["segments"] > 3 and 0 < out["device_busy_s"] <= out["seconds"]
    for a, b in zip(_bits(out["metrics"]), _bits(reference), strict=True):
        np.testing.assert_array_equal(a, b)
    # the lanes, segment by segment (the program of test_same_bits_whatever_the_batching)
    cfg = EngineConfig(slots=12, chunk=CHUNK, iterations=2, ticks_per_segment=7)
    source = arrays_source(X0S)
    eng = E.slots._initial_state(LOOP, cfg, source, PARAMS, SP)[0]
    seg = E.program._build(LOOP, cfg, source.fn)
    block = Block(None, 0, len(X0S))
    limit = jnp.asarray(E.segment._block_limit(cfg, block, [3, 3, 3, 3], len(X0S)))
    one, zero = jnp.int32(1), jnp.int32(0)
    seen = set()
    for _ in range(30):
        eng = seg(eng, source.data, zero, limit, jnp.asarray(False), PARAMS, SP, one, zero, one)
        run, live = np.asarray(eng.slots.run), np.asarray(eng.slots.live)
        slot = np.flatnonzero(live)
        assert np.all(run[slot] % CHUNK == slot % CHUNK)
        seen |= set(run[slot].tolist())
    assert seen == set(range(len(X0S)))


def test_a_deadline_stops_the_engine_between_segments():
    out = run_stream(
        LOOP,
        E.slots._pick_arrays,
        [Block(arrays_source(X0S).data, 0, len(X0S))],
        len(X0S),
        params=PARAMS,
        config=EngineConfig(slots=4, chunk=CHUNK, iterations=2, ticks_per_segment=8),
        deadline=0.0,
        keep=False,
    )
    assert out["segments"] == 1 and out["done"] < len(X0S) and "metrics" not in out


def test_engine_settings_are_chosen_for_the_device():
    """On the CPU the measured defaults and what the user set; an accelerator's slots from
    its memory and the slot state's size."""
    cfg = auto_config(platform="cpu")
    assert (cfg.slots, cfg.chunk, cfg.iterations, cfg.refresh, cfg.assign) == (
        256,
        32,
        3,
        "masked",
        "lane",
    )
    assert "CPU defaults" in cfg.chosen and "256 slots" in cfg.describe()
    two = auto_config(platform="cpu", devices=2, n_runs=100, iterations=4, slots=None)
    # 50 runs a device, in whole chunks of 32 (the lanes keep their width)
    assert (two.slots, two.iterations, two.devices, two.per_device.chunk_size) == (128, 4, 2, 32)
    assert auto_config(platform="cpu", slots=8).n_slots == 32
    assert "iterations=4" in two.chosen and "100 runs" in two.chosen
    # 80 GiB, 100 KiB a slot x 8 for temporaries: 52 428 fit, a power of two
    assert accelerator_slots(80 * 2**30, 100 * 2**10) == 32768
    assert accelerator_slots(2**30, 10 * 2**20) == 256  # never fewer than 256
    assert accelerator_slots(None, 1000) == 16384
    assert E.slot_bytes(LOOP, arrays_source(X0S), PARAMS) > 10_000
    with pytest.raises(ValueError, match="unknown engine setting"):
        auto_config(platform="cpu", slotz=3)


@pytest.mark.parametrize("name", ["fastmpc-3d", "poseidyn-lqmpc", "spot-2d-a", "thesis-vbar"])
def test_the_fields_a_family_rebuilds_are_its_ocps(name):
    """What the engine rebuilds instead of storing per slot (``model_of``: the model, and for
    these families the linear costs and the input rows, for the three-phase family also the
    state rows' mask and penalty, neutralised as the solver's start does, and the model's
    table with the slot's entry) is, bit for bit, the OCP the family builds at a run's first
    step; fields it rebuilds are stored as scalars."""
    sc = SCENARIOS[name]
    params, x0 = sc.build()
    loop = sc.loop(n_steps=2)

    @jax.jit
    def first(p, x):
        prep = prepare(loop, p, init(loop, p, x))
        fields = model_of(loop, p, prep.guidance)
        assert table_of(fields) is None  # a CPU-only process's programs carry no tables
        table = fields.pop("table", None)
        return prep.ocp, fields, None if table is None else table()

    ocp, fields, table = first(params, x0)
    assert (table is not None) == (name == "thesis-vbar")
    if table is not None:  # the slot's entries of the tables (the input rows not neutralised)
        at = int(table.index)
        np.testing.assert_array_equal(table.M[at], np.concatenate([ocp.B, ocp.A], axis=-1))
        np.testing.assert_array_equal(table.Fu[at], fields["Fu"])
        np.testing.assert_array_equal(table.x_mask[at], ocp.x_mask)
        np.testing.assert_array_equal(table.rho[at], rows_of(ocp).rho)
    state_rows = {"x_mask", "rho"} if name == "thesis-vbar" else set()
    assert set(fields) == {"A", "B", "c", "Q", "R", "Fu", "fu", "q", "r"} | state_rows
    for field, a in fields.items():
        want = rows_of(ocp).rho if field == "rho" else getattr(ocp, field)
        np.testing.assert_array_equal(np.asarray(a), np.asarray(want), field)
    stripped = _strip_model(ocp, fields)
    assert all(np.ndim(getattr(stripped, f)) == 0 for f in fields)
    assert np.ndim(stripped.Fx) == 3 and np.ndim(stripped.u_mask) == 2  # stored


def test_the_engine_state_is_built_as_one_program():
    """The engine's initial state (its empty slots, the ring, the counters) is one compiled
    program, not a program for each leaf's broadcast, and every leaf is strongly typed (the
    segment's outputs have its inputs' types, so every segment after the first reuses the
    first one's program)."""
    cfg = EngineConfig(slots=11, chunk=11)  # shapes no other test builds
    source = arrays_source(X0S)
    compiles = []

    def listen(event, *_, **kw):
        if event.endswith("backend_compile_duration"):
            compiles.append(kw.get("fun_name"))

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        eng = E.slots._initial_state(LOOP, cfg, source, PARAMS, SP)[0]
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert compiles == ["jit(build)"], compiles
    assert not [a for a in jax.tree.leaves(eng) if jax.typeof(a).weak_type]
    assert {a.shape[0] for a in jax.tree.leaves(eng.slots)} == {11}
    assert {a.shape[0] for a in jax.tree.leaves(eng.ring)} == {cfg.ring_size}


def test_the_segment_program_lowers_for_a_gpu():
    """jax.export lowers the engine's segment for CUDA on this CPU-only machine (a GPU
    lowering error would show here), with the accelerator settings (one chunk, compacted,
    the slots stored last), and the solver's default Newton step as Pallas (Triton) kernels
    there: the Newton blocks once a tick, then in each iteration the factorisation with the
    predictor's step, the row work between the solves, the corrector's step with its
    refinement, and its row work with the next iteration's Newton blocks; the blocks pass to
    the Riccati kernels as their lower triangles."""
    from rvdjax.loop.engine.segment import _slots_last

    exported = export_segment(LOOP, arrays_source(X0S), PARAMS)
    assert exported.platforms == ("cuda",)
    assert _slots_last(EngineConfig(slots=8, chunk=8, refresh="compacted", platform="cuda"))
    text = exported.mlir_module()
    assert "stablehlo.while" in text and "__gpu$xla.gpu.triton" in text
    assert "rvdjax_riccati_factor_solve" in text and "rvdjax_riccati_solve_refined" in text
    assert "rvdjax_pd_rows" in text and "rvdjax_pd_step_system" in text
    assert "rvdjax_pd_blocks" in text and "rvdjax_pd_step_rows" not in text
    assert "rvdjax_drift" not in text  # the starts are XLA's: the slots are stored batch first
    # the Hessian blocks Phi_u, Phi_x go from the blocks' kernel and the step's to the Riccati
    # kernels as their lower triangles (6 and 21 entries a stage; nu = 3, nx = 6), then g_x,
    # base_u, base_x, rp (the step's last output: alpha, the gap, the residual, the objective,
    # whether finite); the Riccati kernels take the right-hand sides g_u, g_x, rp after them
    assert _triton_entries(text, "rvdjax_pd_blocks", "out") == [6, 21, 6, 3, 6, 6]
    assert _triton_entries(text, "rvdjax_pd_step_system", "out")[-7:] == [6, 21, 6, 3, 6, 6, 5]
    for kernel in ("rvdjax_riccati_factor_solve", "rvdjax_riccati_solve_refined"):
        assert _triton_entries(text, kernel, "in")[-5:] == [6, 21, 3, 6, 6], kernel


def _triton_entries(text: str, kernel: str, side: str) -> list[int]:
    """The entries a stage of each [stage][entry][problem] operand (``side`` "in") or result
    ("out") of the Triton launch of ``kernel`` in a lowered program."""
    line = next(ln for ln in text.splitlines() if "gpu.triton" in ln and kernel in ln)
    ins, outs = line[line.rindex(" : (") :].split(") -> ", 1)
    types = ins if side == "in" else outs
    return [int(m.group(1)) for m in re.finditer(r"tensor<\d+x(\d+)x\d+xf64>", types)]


DEVICE_PROGRAMS_CHILD = """
import jax, jax.numpy as jnp, numpy as np
from jax import monitoring
import rvdjax  # float64, the package's XLA options
from rvdjax.loop.engine.device_programs import DevicePrograms
from rvdjax.loop.engine.stream import compile_side_by_side

compiles = []
monitoring.register_event_duration_secs_listener(
    lambda e, d, **_: compiles.append(d) if e.endswith("backend_compile_duration") else None)

def f(x, k):
    return jax.lax.fori_loop(0, k, lambda i, y: jnp.sin(y) @ y.T / 8 + x, x)

devices = jax.devices()
assert len(devices) == 3, devices
for threads in (1, 2):
    program = DevicePrograms(jax.jit(f))
    n = 7 + threads  # a program of its own shape
    per_device = [(jax.device_put(jnp.full((n, n), 0.1 * (d.id + 1)), d), jnp.int32(3))
                  for d in devices]
    before = len(compiles)
    assert compile_side_by_side(program, per_device, threads=threads) == threads
    ahead = len(compiles)
    out = [program(*a) for a in per_device]
    assert program.compiles == 1 and ahead == before + 1, (program.compiles, ahead - before)
    assert len(compiles) == ahead  # no compile at the calls
    for d, a, o in zip(devices, per_device, out):
        assert o.devices() == {d}, (o.devices(), d)
        np.testing.assert_array_equal(o, jax.jit(f)(*a))  # jit's own program for the device
    try:  # a device's program takes that device's buffers only
        program.compiled(*per_device[1])(*per_device[2])
    except ValueError:
        pass
    else:
        raise AssertionError("device 1's program ran on device 2's buffers")

# a program that loads but refuses the device's buffers at its first call (what a JAX whose
# deserialisation kept the first device's assignment would give): the device compiles its own
import rvdjax.loop.engine.device_programs as dp
dp.load_on = lambda compiled, device: compiled
program = DevicePrograms(jax.jit(f))
per_device = [(jax.device_put(jnp.full((5, 5), 0.1 * (d.id + 1)), d), jnp.int32(3))
              for d in devices]
out = [program(*a) for a in per_device]
assert program.compiles == 3, program.compiles
for d, a, o in zip(devices, per_device, out):
    assert o.devices() == {d}
    np.testing.assert_array_equal(o, jax.jit(f)(*a))
print("ok")
"""


def test_a_program_compiles_once_and_loads_onto_the_other_devices():
    """The engine's per-device programs (three host devices in a child process): compiled
    for the first device, loaded onto the others, one after another (this VM) or side by
    side; the later calls compile nothing, run on their own device, and give the bits of
    ``jax.jit``'s own program for that device. A loaded program that refuses its device's
    buffers at its first call is replaced by the device's own compile."""
    import os
    import subprocess
    import sys

    from rvdjax.loop.engine.stream import compile_threads

    assert compile_threads(4, cores=2) == 1  # the 2-core VM: one after another
    assert compile_threads(16, cores=16) == 8 and compile_threads(2, cores=16) == 2
    flags = os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=3"
    r = subprocess.run(
        [sys.executable, "-c", DEVICE_PROGRAMS_CHILD],
        env={**os.environ, "XLA_FLAGS": flags.strip()},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr[-3000:]


def test_slots_stored_last_fly_the_same_bits(monkeypatch, any_slot):
    """On an accelerator the loop over ticks keeps the slots as its arrays' last axis, the
    GPU kernels' layout (``segment._slots_last``). Forced on the CPU, with the accelerator's
    settings (one chunk, the compacted refresh, runs in any slot), it flies the same bits as
    the slots stored first."""
    from rvdjax.loop.engine import program, segment

    cfg = ANY_SLOT
    assert not segment._slots_last(cfg)  # the CPU keeps the slots first
    first = any_slot
    asked = []
    monkeypatch.setattr(segment, "_slots_last", lambda c: asked.append(c) or True)
    program._build_one.cache_clear()
    try:
        last = fly_batch(LOOP, PARAMS, X0S, config=cfg)
    finally:
        program._build_one.cache_clear()
    assert asked  # the program was built again, with the slots last
    assert len(set(np.asarray(first.steps).tolist())) > 1  # runs of different lengths
    for a, b in zip(_bits(last), _bits(first), strict=True):
        np.testing.assert_array_equal(a, b)
