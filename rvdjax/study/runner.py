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
import functools
import json
import math
import resource
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pyarrow as pa
from jax import lax

from rvdjax import provenance
from rvdjax.loop import RunStatus
from rvdjax.loop.engine import (
    Block,
    RunInputs,
    arrays_source,
    auto_config,
    run_stream,
    slot_bytes,
)
from rvdjax.loop.metrics import metrics_columns
from rvdjax.study import samplers
from rvdjax.study.spec import ParamRef, StudySpec, resolve, study_scenario
from rvdjax.study.table import PartWriter, done_runs, read_config, write_config

__all__ = ["run_study", "RunSet", "run_inputs", "replay", "effort_metric", "peak_rss_mb"]

_EFFORT_KEYS = ("delta_v_m_s", "effort_l1_N_s", "total_impulse_N_s")
ALIGN = 1024  # runs per call of the input samplers (module docstring)


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


@dataclasses.dataclass
class RunSet:
    """The inputs of a set of runs (host arrays; leading axis = run)."""

    run: np.ndarray
    point: np.ndarray
    ic: np.ndarray
    replicate: np.ndarray
    x0: np.ndarray  # (n, nx)
    keys: jax.Array  # (n,) PRNG keys of the closed loop
    drawn: dict  # vary name -> (n, ...) drawn physical / x0 values
    physical: list | None  # per-run physical overrides (None: the point's)


@functools.lru_cache(maxsize=8)
def _ic_sampler(kind: str, seed: int):
    if kind == "paper003":

        def one(ic, n):
            return samplers.paper003_initial_state(samplers.initial_key(seed, ic), n)

        return jax.jit(lambda ics, n: lax.map(lambda ic: one(ic, n), ics))
    raise ValueError(kind)


def _mean_motion(scenario, physical) -> float:
    from rvdjax.dynamics import mean_motion

    if "altitude_m" not in physical:
        raise ValueError(
            f"initial 'paper003' needs a CW mean motion; scenario {scenario.name!r} has no "
            "altitude_m"
        )
    return float(mean_motion(altitude_m=float(physical["altitude_m"])))


def _point_overrides(spec: StudySpec, scenario, point):
    """(static config overrides, physical overrides, x0 overrides {ParamRef: value})."""
    static, physical, x0 = {}, {}, {}
    for name, value in point.values.items():
        ref = resolve(scenario, name)
        if ref.kind == "static":
            nominal = {**scenario.config}.get(
                ref.base, getattr(scenario.guidance_family.config_type(**scenario.config), ref.base)
            )
            nominal = static.get(ref.base, nominal)
            static[ref.base] = ref.apply(
                tuple(nominal) if ref.index is not None else nominal, int(value)
            )
            if ref.index is not None:
                static[ref.base] = tuple(int(v) for v in static[ref.base])
        elif ref.kind == "physical":
            nominal = physical.get(ref.base, scenario.physical.get(ref.base))
            if nominal is None and ref.index is not None:
                raise ValueError(f"{name}: scenario {scenario.name!r} sets no {ref.base}")
            physical[ref.base] = ref.apply(nominal, float(value))
        else:
            x0[ref] = float(value)
    return static, physical, x0


def _flight(spec: StudySpec, scenario, static: dict | None = None, check: bool = False):
    """The study's nominal flight of a sweep point's static configuration (faults as
    physical overrides); a run's parameters are :meth:`Flight.build` of its values."""
    faults = spec.fault_overrides(scenario.thrusters.n) if spec.thrusters else {}
    return scenario.flight(spec.flight_options(scenario), config=static, check=check, **faults)


def _physical_nominal(scenario, base):
    if base in scenario.physical:
        return scenario.physical[base]
    from rvdjax.scenarios import THRUSTER_KEYS

    if base in THRUSTER_KEYS:
        return scenario.thruster_nominal(base)
    from rvdjax.schema import REQUIRED

    default = scenario.guidance_family.schema[base].default
    if default is REQUIRED or default is None:
        raise ValueError(f"--vary {base}: scenario {scenario.name!r} gives no value to vary")
    return default


@functools.lru_cache(maxsize=8)
def _vary_drawer(spec_vary: tuple, seed: int):
    dists = [samplers.parse_dist(d) for _, d in spec_vary]

    def one(ic, rep, nominals):
        base = samplers.vary_key(seed, ic, rep)
        return [
            samplers.draw(d, jax.random.fold_in(base, j), nom)
            for j, (d, nom) in enumerate(zip(dists, nominals, strict=True))
        ]

    return jax.jit(lambda ic, rep, nominals: lax.map(lambda a: one(*a), (ic, rep, nominals)))


def run_inputs(spec: StudySpec, scenario, runs) -> RunSet:
    """The exact inputs of ``runs`` (run indices): initial states, keys, drawn values.

    They are drawn for the whole ``ALIGN``-run ranges that hold ``runs``, each range one call
    of the same program (module docstring), then picked."""
    runs = np.asarray(runs, dtype=np.int64)
    if len(runs) and (runs.min() < 0 or runs.max() >= spec.n_runs):
        raise ValueError(f"run indices must be in [0, {spec.n_runs - 1}]")
    ranges = np.unique(runs // ALIGN)
    full = (ranges[:, None] * ALIGN + np.arange(ALIGN)).reshape(-1)
    # on the CPU whatever the engine's device: a loop of scalar steps is fast there (a GPU
    # would launch kernels per run), and the draws do not depend on the device
    with jax.default_device(jax.local_devices(backend="cpu")[0]):
        rs = _aligned_inputs(spec, scenario, np.minimum(full, spec.n_runs - 1))
    pick = np.searchsorted(ranges, runs // ALIGN) * ALIGN + runs % ALIGN
    return RunSet(
        runs,
        rs.point[pick],
        rs.ic[pick],
        rs.replicate[pick],
        rs.x0[pick],
        rs.keys[pick],
        {k: v[pick] for k, v in rs.drawn.items()},
        None if rs.physical is None else [rs.physical[i] for i in pick],
    )


def _by_range(fn, *args):
    """``fn`` over arrays with a leading axis of whole ``ALIGN`` ranges, one call per range."""
    n = len(args[0])
    out = [fn(*(a[lo : lo + ALIGN] for a in args)) for lo in range(0, n, ALIGN)]
    return jax.tree.map(lambda *a: np.concatenate([np.asarray(x) for x in a]), *out)


def _aligned_inputs(spec: StudySpec, scenario, runs) -> RunSet:
    runs = np.asarray(runs, dtype=np.int64)
    point, ic, rep = spec.decompose(runs)
    points = spec.points
    nx = scenario.guidance_family.layout.nx
    # initial states: sampler, then the point's x0 overrides
    if spec.initial == "nominal":
        x0 = np.broadcast_to(np.asarray(scenario.x0, float), (len(runs), nx)).copy()
    else:
        n = _mean_motion(scenario, scenario.physical)
        sampler = _ic_sampler(spec.initial, spec.seed)
        x0 = _by_range(lambda i: sampler(jnp.asarray(i), n), ic)
    point_phys = []
    for p in points:
        _, phys, x0_over = _point_overrides(spec, scenario, p)
        point_phys.append(phys)
        sel = point == p.index
        for ref, v in x0_over.items():
            x0[sel, ref.index] = v
    drawn = {}
    physical = None
    refs = [(resolve(scenario, n), n) for n, _ in spec.vary]
    if refs:
        nominals = []
        for ref, _ in refs:
            if ref.kind == "x0":
                nom = x0 if ref.index is None else x0[:, ref.index]
            else:
                base = np.stack(
                    [
                        np.asarray(
                            point_phys[p].get(ref.base, _physical_nominal(scenario, ref.base)),
                            float,
                        )
                        for p in point
                    ]
                )
                nom = base if ref.index is None else base.reshape(len(runs), -1)[:, ref.index]
            nominals.append(np.asarray(nom, float))
        drawer = _vary_drawer(spec.vary, spec.seed)
        values = _by_range(
            lambda i, j, *nom: drawer(jnp.asarray(i), jnp.asarray(j), list(nom)), ic, rep, *nominals
        )
        for (ref, name), v in zip(refs, values, strict=True):
            drawn[name] = v
            if ref.kind == "x0":
                if ref.index is None:
                    x0 = v.copy()
                else:
                    x0[:, ref.index] = v
        phys_refs = [
            (ref, v) for (ref, _), v in zip(refs, values, strict=True) if ref.kind == "physical"
        ]
        if phys_refs:
            physical = []
            for r in range(len(runs)):
                d = dict(point_phys[point[r]])
                for ref, v in phys_refs:
                    nominal = d.get(ref.base, _physical_nominal(scenario, ref.base))
                    d[ref.base] = _apply_value(ref, nominal, v[r])
                physical.append(d)
    keys = jax.vmap(samplers.disturbance_key, in_axes=(None, 0, 0))(
        spec.seed, jnp.asarray(ic), jnp.asarray(rep)
    )  # integer arithmetic: exact in any batch
    return RunSet(runs, point, ic, rep, x0, keys, drawn, physical)


def _apply_value(ref: ParamRef, nominal, value):
    value = np.asarray(value)
    if ref.index is not None:
        return ref.apply(nominal, float(value))
    if value.ndim == 0:
        return float(value)
    return value.reshape(np.shape(nominal)).tolist()


# ---------------------------------------------------------------------------------- rows


def _strings(n: int, value) -> pa.Array:
    return pa.array(np.full(n, value, dtype=object), pa.string())


def _table(spec, runs, point_values, point_ts, x0, drawn, m, effort) -> pa.Table:
    """One tidy row per run, as columns (no per-run Python object): ``runs`` (n,) run
    indices, ``x0`` (n, nx) and ``drawn`` {name: (n, ...)} their inputs, ``m`` their engine
    metrics; ``point_values`` {name: (points,)} the sweep values, ``point_ts`` (points, P) each
    point's per-phase sample times (None: not per phase)."""
    n = len(runs)
    point, ic, rep = spec.decompose(runs)
    cols: dict[str, Any] = {
        "study": _strings(n, spec.kind),
        "scenario": _strings(n, spec.scenario),
        "point": point.astype(np.int64),
        "run": runs.astype(np.int64),
        "ic": ic.astype(np.int64),
        "replicate": rep.astype(np.int64),
        "seed": np.full(n, spec.seed, np.int64),
    }
    for name, values in point_values.items():
        cols[name] = values[point].astype(np.float64)
    for name, v in drawn.items():
        v = np.asarray(v, np.float64).reshape(n, -1)
        if np.ndim(drawn[name]) == 1:
            cols[name] = v[:, 0]
        else:
            for j in range(v.shape[1]):
                cols[f"{name}[{j}]"] = v[:, j]
    for j in range(x0.shape[1]):
        cols[f"x0_{j}"] = np.asarray(x0[:, j], np.float64)
    status = np.asarray(m.status)
    for group in metrics_columns(m).values():
        cols.update(group)
    cols["status"] = pa.array(cols["status"], pa.string())
    cols["effort"] = cols[effort]
    if point_ts is not None:
        t = np.asarray(m.phase_time_s, np.float64)
        for ph in range(t.shape[1]):
            cols[f"phase{ph}_intervals"] = np.ceil(t[:, ph] / point_ts[point, ph] - 1e-9).astype(
                np.int64
            )
    cols["failure"] = pa.array(_failures(spec, status, cols), pa.string())
    return pa.table(cols)


def _failures(spec: StudySpec, status, cols) -> np.ndarray:
    """Why each run failed ("" for a success)."""
    out = np.full(len(status), "", dtype=object)
    violated = (status == RunStatus.DOCKED) & (cols["max_violation_m"] > 1e-6)
    out[violated] = "docked with a constraint violation"
    out[status == RunStatus.FAILED] = "non-finite truth state"
    timeout = np.flatnonzero(status == RunStatus.TIMEOUT)
    if spec.time_limit_s is not None:
        out[timeout] = f"not docked within {spec.time_limit_s:g} s"
    else:
        out[timeout] = [f"not docked within {k} steps" for k in cols["steps"][timeout]]
    return out


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
