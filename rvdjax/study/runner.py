"""Fly a study through the batch engine and write its table as it goes.

The runs of a study are grouped by their static configuration (a horizon is an array shape:
each distinct value compiles the closed loop once; everything else is traced). A group's runs
form one queue of the engine (:func:`rvdjax.loop.engine.run_stream`), whose inputs are
computed in blocks (the host keeps the inputs of the blocks still flying: its memory is set
by the block and the slots, not by the number of runs); the engine's results come back as
columns and are written to Parquet parts as they come (:mod:`rvdjax.study.table`), while the
device flies the next segment. ``resume=True`` flies only the runs not on disk.

A run's bits depend on its inputs and on the engine's lane it flies in (on a CPU; see
:mod:`rvdjax.loop.engine`). Both are functions of the run index alone. The inputs are drawn
on the CPU one run at a time (``lax.map``: scalar code, which XLA does not vectorise), in
calls of ``ALIGN`` runs aligned on the run index (run r is always entry r mod ``ALIGN`` of the
same program). With ``assign="lane"`` run r flies in lane r mod chunk. So a study's table has
the same bits whatever its slots, devices and processes, and however often it was killed and
resumed.
"""

from __future__ import annotations

import dataclasses
import json
import math
import resource
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pyarrow as pa

from rvdjax import provenance
from rvdjax.loop.engine import (
    Block,
    RunInputs,
    arrays_source,
    auto_config,
    run_stream,
    slot_bytes,
)
from rvdjax.study.inputs import (  # noqa: F401  (run_inputs, RunSet: re-exported)
    ALIGN,
    RunSet,
    _flight,
    _point_overrides,
    run_inputs,
)
from rvdjax.study.rows import _table
from rvdjax.study.spec import StudySpec, resolve, study_scenario
from rvdjax.study.table import PartWriter, done_runs, read_config, write_config

__all__ = ["run_study", "RunSet", "run_inputs", "replay", "effort_metric", "peak_rss_mb"]

_EFFORT_KEYS = ("delta_v_m_s", "effort_l1_N_s", "total_impulse_N_s")


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far [MB] (Linux: ru_maxrss is in kB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def effort_metric(scenario) -> str:
    """The scenario's headline effort: the first of delta-v, L1 impulse, L2 impulse that its
    paper publishes (delta-v when none is)."""
    for k in _EFFORT_KEYS:
        if k in scenario.published:
            return k
    return "delta_v_m_s"


# ---------------------------------------------------------------------------------- study


def _group_key(static: dict) -> tuple:
    return tuple(sorted((k, v if not isinstance(v, list) else tuple(v)) for k, v in static.items()))


def _stack(trees):
    return jax.tree.map(lambda *a: np.stack([np.asarray(x) for x in a]), *trees)


def _pick_run(data, i):
    """Queue entry i of a block: (x0s, keys, per-run parameters or None)."""
    x0s, keys, params = data
    return RunInputs(
        x0=x0s[i],
        key=keys[i],
        params=None if params is None else jax.tree.map(lambda a: a[i], params),
        solver=None,
    )


def _pick_point(data, i):
    """Queue entry i of a block whose runs share their sweep point's parameters: (x0s, keys,
    point index of each entry, the points' parameters stacked)."""
    x0s, keys, points, point_params = data
    return RunInputs(
        x0=x0s[i],
        key=keys[i],
        params=jax.tree.map(lambda a: a[points[i]], point_params),
        solver=None,
    )


class _BlockInfo(NamedTuple):
    runs: np.ndarray  # (block,) run index of each queue entry (-1: none)
    rs: RunSet  # the inputs of the block's runs
    index: np.ndarray  # (block,) entry -> position in rs


class _GroupQueue:
    """The engine's queue of one group of a study: which run sits at which queue position
    (with lanes, run r in lane r mod chunk), its inputs block by block, and the table rows of
    the results."""

    def __init__(self, spec, nominal, runs, cfg, point_ids, params_of_point, per_point):
        scenario = nominal.scenario
        self.nominal = nominal
        self.spec, self.scenario, self.cfg = spec, scenario, cfg
        self.point_ids = list(point_ids)
        self.params_of_point = params_of_point
        # per-run parameters (a physical value drawn per run), the point's (the group's points
        # differ in physical values) or shared
        self.per_run = any(resolve(scenario, n).kind == "physical" for n, _ in spec.vary)
        self.per_point = per_point and not self.per_run
        if cfg.assign == "lane":
            C = cfg.chunk_size
            lane = runs % C
            counts = np.bincount(lane, minlength=C)
            order = np.lexsort((runs, lane))
            first = np.concatenate([[0], np.cumsum(counts)[:-1]])
            rank = np.arange(len(runs)) - first[lane[order]]
            table = np.full((int(counts.max()), C), -1, np.int64)
            table[rank, lane[order]] = runs[order]
            self.positions = table.reshape(-1)
            self.lane_counts = counts
            unit = C
        else:
            self.positions = np.asarray(runs, np.int64)
            self.lane_counts = None
            unit = 1
        want = max(spec.block, 8 * cfg.per_device.n_slots * cfg.devices)
        self.block = unit * math.ceil(want / unit)
        self.info: dict[int, _BlockInfo] = {}
        self.remaining: dict[int, int] = {}

    def _inputs(self, start: int):
        """The engine's data for the block starting at queue position ``start``."""
        spec, scenario = self.spec, self.scenario
        ids = self.positions[start : start + self.block]
        ids = np.concatenate([ids, np.full(self.block - len(ids), -1, np.int64)])
        valid = ids >= 0
        rs = run_inputs(spec, scenario, ids[valid])
        index = np.where(valid, np.cumsum(valid) - 1, 0)
        self.info[start] = _BlockInfo(ids, rs, index)
        self.remaining[start] = int(valid.sum())
        x0 = jnp.asarray(rs.x0[index])
        keys = rs.keys[index]
        if rs.physical is not None:
            nominal = self.nominal
            built = _stack([nominal.build(**ph, x0=scenario.x0)[0] for ph in rs.physical])
            params = jax.tree.map(lambda a: jnp.asarray(a[index]), built)
            return (x0, keys, params)
        if self.per_point:
            local = {p: k for k, p in enumerate(self.point_ids)}
            points = jnp.asarray([local[int(p)] for p in rs.point[index]], jnp.int32)
            # device arrays: the engine indexes them with a traced point index
            stacked = jax.tree.map(
                jnp.asarray, _stack([self.params_of_point(p) for p in self.point_ids])
            )
            return (x0, keys, points, stacked)
        return (x0, keys, None)

    @property
    def source_fn(self):
        return _pick_point if self.per_point else _pick_run

    @property
    def shared(self):
        """The parameters every run shares (None: per run or per point)."""
        if self.per_run or self.per_point:
            return None
        return self.params_of_point(int(self.point_ids[0]))

    def blocks(self):
        for start in range(0, len(self.positions), self.block):
            yield Block(self._inputs(start), start, min(start + self.block, len(self.positions)))

    def table(self, positions, metrics, effort, point_values, point_ts) -> pa.Table:
        """The rows of the results at queue ``positions``."""
        starts = positions // self.block * self.block
        parts = []
        for start in np.unique(starts):
            sel = np.flatnonzero(starts == start)
            info = self.info[start]
            local = positions[sel] - start
            runs = info.runs[local]
            assert np.all(runs >= 0), "the engine flew a queue position that holds no run"
            k = info.index[local]
            m = jax.tree.map(lambda a, sel=sel: a[sel], metrics)
            drawn = {name: v[k] for name, v in info.rs.drawn.items()}
            parts.append(
                _table(self.spec, runs, point_values, point_ts, info.rs.x0[k], drawn, m, effort)
            )
            self.remaining[start] -= len(sel)
            if self.remaining[start] == 0:  # every run of the block is written
                del self.info[start], self.remaining[start]
        return pa.concat_tables(parts) if len(parts) > 1 else parts[0]


def _prefetch(items):
    """Iterate ``items`` computing the next one in a background thread (the next block's
    inputs are drawn while the engine flies the current one)."""
    it = iter(items)
    with ThreadPoolExecutor(max_workers=1) as pool:
        fut = pool.submit(next, it, None)
        while True:
            item = fut.result()
            if item is None:
                return
            fut = pool.submit(next, it, None)
            yield item


def _auto_flush(n_runs: int) -> int:
    """Rows per part file: 256, or 1/64 of the study for large ones (at most 65536)."""
    return int(min(65536, max(256, n_runs // 64)))


def prepare_out(
    spec: StudySpec, out: Path, resume: bool, allow_code_change: bool = False, scenario=None
) -> None:
    """Check ``out`` against the study (its spec, then its provenance: the same run
    definition and code version, :mod:`rvdjax.provenance`) and write its configuration.
    ``scenario``: the study's scenario record (None: read from the spec)."""
    out = Path(out)
    existing = read_config(out)
    config = {"spec": json.loads(spec.to_json()), "version": 1}
    if existing is not None:
        if not resume:
            raise ValueError(
                f"--out {out} already holds a study; pass --resume to continue it or choose "
                "another directory"
            )
        if existing.get("spec") != config["spec"]:
            diff = "; ".join(provenance.differences(existing.get("spec"), config["spec"]))
            raise ValueError(
                f"--out {out} holds a different study ({diff}); --resume continues only the "
                "same study"
            )
    elif out.exists() and any(out.iterdir()):
        raise ValueError(f"--out {out} exists and is not a study directory; choose another")
    sc = study_scenario(spec, out) if scenario is None else scenario
    config["provenance"] = provenance.stamp(  # provenance hook (rvdjax.provenance)
        None if existing is None else existing.get("provenance", {}),
        provenance.describe(
            spec=config["spec"],
            scenario=provenance.scenario_values(sc),
            params=_flight(spec, sc).params,
            solver=sc.solver_params(spec.mode),
        ),
        allow_code_change=allow_code_change,
        where=f"--out {out}",
    )
    write_config(out, config)


def run_study(
    spec: StudySpec,
    out,
    resume: bool = False,
    progress: bool | Callable = True,
    process_index: int = 0,
    process_count: int = 1,
    devices: int = 1,
    flush_rows: int | None = None,
    prepare: bool = True,
    max_seconds: float | None = None,
    engine: dict | None = None,
    allow_code_change: bool = False,
) -> dict:
    """Fly ``spec`` and write its table to ``out``; returns timing figures.

    Runs already in ``out`` are skipped when ``resume``; with ``process_count`` > 1 this
    process flies every ``process_count``-th remaining run and writes its own parts;
    ``devices`` shards the engine's slots over that many local devices; a part file is
    written every ``flush_rows`` finished runs (None: 256, or 1/64 of a large study) or 20 s.
    ``prepare``: process 0 checks ``out`` and writes the configuration first (False: the
    caller did, e.g. before a barrier of several processes). ``max_seconds``: stop starting
    engine segments after that long (the runs in flight are dropped, the table keeps every
    finished run: resume to complete it). ``engine``: further
    :class:`~rvdjax.loop.engine.EngineConfig` settings (e.g. ``platform``, ``refresh``); the
    spec's ``slots``, ``chunk`` and ``iterations`` (None: chosen for the device by
    :func:`~rvdjax.loop.engine.auto_config`) come first.

    The figures: runs flown and skipped, wall ``seconds``, ``runs_per_s``, peak memory, the
    device's busy time (``device_busy_s``), the compiles' (``compile_s``), the share of wall
    time the device was not busy (``outside_device_share``: input drawing, collection and
    writing not hidden behind the device's work, and compiles; ``..._flying``: without the
    compiles), and ``engine``: each group's engine settings. ``allow_code_change``: resume a
    study flown by another code version (its new rows are marked, :mod:`rvdjax.provenance`).
    """
    scenario = study_scenario(spec, out)
    spec.validate(dataclasses.replace(scenario, name=spec.scenario))
    out = Path(out)
    if prepare and process_index == 0:
        prepare_out(spec, out, resume, allow_code_change, scenario)
    marks = provenance.row_marks(read_config(out)["provenance"])  # provenance hook
    effort = effort_metric(scenario)
    all_runs = np.arange(spec.n_runs, dtype=np.int64)
    done = done_runs(out) if resume else np.zeros(0, np.int64)
    todo = np.setdiff1d(all_runs, done)
    todo = todo[process_index::process_count]
    flush_rows = _auto_flush(spec.n_runs) if flush_rows is None else flush_rows
    writer = PartWriter(out, process=process_index, flush_rows=flush_rows)
    # group the points by static configuration
    groups: dict[tuple, list] = {}
    point_cfg = {}
    for p in spec.points:
        static, phys, _ = _point_overrides(spec, scenario, p)
        point_cfg[p.index] = (static, phys)
        groups.setdefault(_group_key(static), []).append(p.index)
    point_values = {
        name: np.asarray([p.values[name] for p in spec.points], np.float64)
        for name in (spec.points[0].values if spec.points else {})
    }

    bar = None
    if progress is True:
        from tqdm.auto import tqdm

        bar = tqdm(
            total=len(todo),
            unit="run",
            desc=f"{spec.kind} {spec.scenario}",
            dynamic_ncols=True,
            smoothing=0.1,
        )
    t0 = time.perf_counter()
    deadline = None if max_seconds is None else t0 + max_seconds
    flown = 0
    busy = host = compile_s = 0.0
    engines = []
    nominal = _flight(spec, scenario, check=True)
    nominal_params = nominal.params
    for _, point_ids in groups.items():
        group_runs = todo[np.isin(spec.decompose(todo)[0], point_ids)]
        late = deadline is not None and time.perf_counter() > deadline
        if not len(group_runs) or (late and engines):  # (the first group flies a segment)
            continue
        static = point_cfg[point_ids[0]][0]
        loop = _flight(spec, scenario, static).loop
        sp = nominal.solver_params
        params_cache = {}

        def params_of_point(p, params_cache=params_cache):
            if p not in params_cache:
                phys = point_cfg[p][1]
                params_cache[p] = nominal.build(**phys)[0] if phys else nominal_params
            return params_cache[p]

        per_point = len({repr(sorted(point_cfg[p][1].items())) for p in point_ids}) > 1
        point_ts = _point_sample_times(spec, params_of_point)
        cfg = _engine_config(
            spec, scenario, loop, sp, group_runs, devices, engine, params_of_point(point_ids[0])
        )
        queue = _GroupQueue(spec, nominal, group_runs, cfg, point_ids, params_of_point, per_point)
        engines.append(cfg.describe())
        base = flown

        def on_results(positions, metrics, queue=queue, point_ts=point_ts):
            table = queue.table(positions, metrics, effort, point_values, point_ts)
            for name, value in marks.items():  # provenance hook (rvdjax.provenance)
                table = table.append_column(name, pa.array([value] * table.num_rows))
            writer.add(table)

        def on_progress(done_group, n, base=base):
            if bar is not None:
                bar.update(base + done_group - bar.n)
            elif callable(progress):
                progress(base + done_group, len(todo))

        res = run_stream(
            loop,
            queue.source_fn,
            _prefetch(queue.blocks()),
            len(group_runs),
            params=queue.shared,
            solver_params=sp,
            config=cfg,
            on_results=on_results,
            progress=on_progress,
            keep=False,
            deadline=deadline,
            lane_counts=queue.lane_counts,
        )
        flown += res["done"]
        busy += res["device_busy_s"]
        host += res["host_s"]
        compile_s += res["compile_s"]
    writer.close()
    if bar is not None:
        bar.close()
    wall = time.perf_counter() - t0
    return {
        "runs_flown": int(flown),
        "runs_skipped": int(len(done)),
        "runs_left": int(len(todo) - flown),
        "seconds": wall,
        "runs_per_s": flown / wall if wall > 0 else float("nan"),
        "peak_memory_mb": peak_rss_mb(),
        "device_busy_s": busy,
        "compile_s": compile_s,
        "host_s": host,
        "outside_device_share": 1.0 - busy / wall if wall > 0 else float("nan"),
        "outside_device_share_flying": (
            1.0 - busy / (wall - compile_s) if wall > compile_s else float("nan")
        ),
        "engine": engines,
    }


def _point_sample_times(spec, params_of_point):
    """(points, phases) per-phase sample times of every point, or None (not per phase)."""
    ts = [getattr(params_of_point(p.index), "ts", None) for p in spec.points]
    if all(t is not None and np.ndim(t) == 1 for t in ts):
        return np.stack([np.asarray(t, np.float64) for t in ts])
    return None


def _engine_config(spec, scenario, loop, sp, runs, devices, engine, params):
    """The engine's settings for a group of runs: the spec's and ``engine``'s, the rest
    chosen for the device (:func:`~rvdjax.loop.engine.auto_config`)."""
    overrides = dict(engine or {})
    overrides.update(slots=spec.slots, chunk=spec.chunk, iterations=spec.iterations)

    def size():
        probe = run_inputs(spec, scenario, runs[:1])
        return slot_bytes(loop, arrays_source(probe.x0, probe.keys), params, sp)

    return auto_config(devices=devices, n_runs=len(runs), slot_bytes=size, **overrides)


def replay(out, run: int):
    """(spec, flight) of run ``run`` of the study in ``out``: the
    :class:`~rvdjax.scenarios.flight.Flight` with that run's parameters, initial state and key
    (``flight.fly()`` to see that run again)."""

    config = read_config(Path(out))
    if config is None:
        raise ValueError(f"study {out}: no config.json (not a study directory)")
    spec = StudySpec.from_dict(config["spec"])
    if not 0 <= run < spec.n_runs:
        raise ValueError(f"run must be in [0, {spec.n_runs - 1}], got {run}")
    scenario = study_scenario(spec, out)
    rs = run_inputs(spec, scenario, [run])
    p = int(rs.point[0])
    static, phys, _ = _point_overrides(spec, scenario, spec.points[p])
    if rs.physical is not None:
        phys = rs.physical[0]
    flight = _flight(spec, scenario, static)
    return spec, flight.replace(params=flight.build(**phys)[0], x0=rs.x0[0], key=rs.keys[0])
