"""Fly a study through the batch engine and write its table as it goes.

The runs of a study are grouped by their static configuration (a horizon is an array shape:
each distinct value compiles the closed loop once; everything else is traced), handed to the
engine in blocks of at most ``spec.block`` runs (the host memory of a study is set by the
block and the slots, not by the number of runs), and written to Parquet parts as the engine
finishes them (:mod:`rvdjax.study.table`). ``resume=True`` flies only the runs not on disk.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import resource
import time
from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from rvdjax import provenance
from rvdjax.loop import RunStatus
from rvdjax.loop.engine import EngineConfig, arrays_source, run_batch
from rvdjax.solver import Status
from rvdjax.study import samplers
from rvdjax.study.spec import ParamRef, StudySpec, resolve, study_scenario
from rvdjax.study.table import PartWriter, done_runs, read_config, write_config

__all__ = ["run_study", "RunSet", "run_inputs", "replay_inputs", "effort_metric", "peak_rss_mb"]

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

        return jax.jit(jax.vmap(one, in_axes=(0, None)))
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
                ref.base, getattr(scenario.family_.config_type(**scenario.config), ref.base)
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


def _build(spec: StudySpec, scenario, **physical):
    """scenario.build with the study's thrusters and faults."""
    if spec.thrusters:
        physical = {**spec.fault_overrides(scenario.thrusters.n), **physical}
    return scenario.build(thrusters=spec.thrusters, **physical)


def _physical_nominal(scenario, base):
    if base in scenario.physical:
        return scenario.physical[base]
    from rvdjax.scenarios import THRUSTER_KEYS

    if base in THRUSTER_KEYS:
        return scenario.thruster_nominal(base)
    import inspect

    default = inspect.signature(scenario.family_.make_params).parameters[base].default
    if default is inspect.Parameter.empty or default is None:
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

    return jax.jit(jax.vmap(one, in_axes=(0, 0, 0)))


def run_inputs(spec: StudySpec, scenario, runs) -> RunSet:
    """The exact inputs of ``runs`` (run indices): initial states, keys, drawn values."""
    runs = np.asarray(runs, dtype=np.int64)
    point, ic, rep = spec.decompose(runs)
    points = spec.points
    nx = scenario.family_.layout.nx
    # initial states: sampler, then the point's x0 overrides
    if spec.initial == "nominal":
        x0 = np.broadcast_to(np.asarray(scenario.x0, float), (len(runs), nx)).copy()
    else:
        n = _mean_motion(scenario, scenario.physical)
        x0 = np.asarray(_ic_sampler(spec.initial, spec.seed)(jnp.asarray(ic), n))
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
            nominals.append(jnp.asarray(nom, float))
        values = _vary_drawer(spec.vary, spec.seed)(jnp.asarray(ic), jnp.asarray(rep), nominals)
        values = [np.asarray(v) for v in values]
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
    )
    return RunSet(runs, point, ic, rep, x0, keys, drawn, physical)


def _apply_value(ref: ParamRef, nominal, value):
    value = np.asarray(value)
    if ref.index is not None:
        return ref.apply(nominal, float(value))
    if value.ndim == 0:
        return float(value)
    return value.reshape(np.shape(nominal)).tolist()


# ---------------------------------------------------------------------------------- rows


def _rows(spec, scenario, params_of_point, rs: RunSet, sel, metrics, effort) -> list[dict]:
    """One tidy row per run of ``sel`` (positions in ``rs``) from engine metrics."""
    m = metrics
    rows = []
    ts = None
    for k in range(len(sel)):
        i = sel[k]
        p = int(rs.point[i])
        point = spec.points[p]
        row = {
            "study": spec.kind,
            "scenario": spec.scenario,
            "point": p,
            "run": int(rs.run[i]),
            "ic": int(rs.ic[i]),
            "replicate": int(rs.replicate[i]),
            "seed": int(spec.seed),
        }
        for name, v in point.values.items():
            row[name] = float(v)
        for name, v in rs.drawn.items():
            v = np.asarray(v[i])
            if v.ndim == 0:
                row[name] = float(v)
            else:
                for j, e in enumerate(v.reshape(-1)):
                    row[f"{name}[{j}]"] = float(e)
        for j, e in enumerate(rs.x0[i]):
            row[f"x0_{j}"] = float(e)
        status = int(m.status[k])
        docked = bool(m.docked[k])
        row["status"] = RunStatus.name(status)
        row["docked"] = docked
        row["steps"] = int(m.steps[k])
        for f in (
            "time_to_dock_s",
            "total_impulse_N_s",
            "effort_l1_N_s",
            "delta_v_m_s",
            "delta_v_l1_m_s",
            "torque_l1_N_m_s",
            "max_violation_m",
            "mean_iterations",
            "thruster_impulse_N_s",
            "propellant_kg",
        ):
            row[f] = float(getattr(m, f)[k])
        row["valve_openings"] = int(m.valve_openings[k])
        row["pulses_dropped"] = int(m.pulses_dropped[k])
        row["effort"] = row[effort]
        params = params_of_point(p)
        ts = getattr(params, "ts", None)
        for ph, (dv, t) in enumerate(zip(m.phase_delta_v_m_s[k], m.phase_time_s[k], strict=True)):
            row[f"phase{ph}_delta_v_m_s"] = float(dv)
            row[f"phase{ph}_time_s"] = float(t)
            if ts is not None and np.ndim(ts) == 1:
                row[f"phase{ph}_intervals"] = int(np.ceil(float(t) / float(ts[ph]) - 1e-9))
        for name, v in m.margins_m.items():
            row[f"margin_{name}_m"] = float(v[k])
        for s, c in enumerate(m.status_counts[k]):
            row[f"solves_{Status.name(s)}"] = int(c)
        row["failure"] = _failure(status, row, spec)
        rows.append(row)
    return rows


def _failure(status: int, row: dict, spec: StudySpec) -> str:
    if status == RunStatus.DOCKED:
        return "" if row["max_violation_m"] <= 1e-6 else "docked with a constraint violation"
    if status == RunStatus.FAILED:
        return "non-finite truth state"
    limit = f"{spec.time_limit_s:g} s" if spec.time_limit_s is not None else f"{row['steps']} steps"
    return f"not docked within {limit}"


# ---------------------------------------------------------------------------------- study


def _group_key(static: dict) -> tuple:
    return tuple(sorted((k, v if not isinstance(v, list) else tuple(v)) for k, v in static.items()))


def _loop_for(spec: StudySpec, scenario, static: dict):
    loop = scenario.loop(
        spec.mode,
        truth=spec.truth,
        disturbed=spec.disturbed,
        n_steps=spec.n_steps,
        time_limit_s=spec.time_limit_s,
        nav_filter=spec.nav_filter,
        thrusters=(scenario.thrusters.replace(fdir=spec.fdir) if spec.thrusters else False),
        faults=spec.has_faults,
        **static,
    )
    return loop


def _pad(trees, n: int):
    """Pad every leading axis to ``n`` with copies of entry 0 (never flown: the queue's length
    is the number of real runs)."""

    def pad(a):
        if a is None or a.shape[0] == n:
            return a
        reps = jnp.repeat(a[:1], n - a.shape[0], axis=0)
        return jnp.concatenate([jnp.asarray(a), reps], axis=0)

    return jax.tree.map(pad, trees, is_leaf=lambda x: x is None)


def _stack(trees):
    return jax.tree.map(lambda *a: np.stack([np.asarray(x) for x in a]), *trees)


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
            params=_build(spec, sc)[0],
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
    flush_rows: int = 256,
    prepare: bool = True,
    allow_code_change: bool = False,
) -> dict:
    """Fly ``spec`` and write its table to ``out``; returns timing figures.

    Runs already in ``out`` are skipped when ``resume``; with ``process_count`` > 1 this
    process flies every ``process_count``-th remaining run and writes its own parts;
    ``devices`` shards the engine's slots over that many local devices; a part file is
    written every ``flush_rows`` finished runs (or 20 s). ``prepare``: process 0 checks
    ``out`` and writes the configuration first (False: the caller did, e.g. before a barrier
    of several processes). ``allow_code_change``: resume a study flown by another code
    version (its new rows are marked, :mod:`rvdjax.provenance`).
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
    writer = PartWriter(out, process=process_index, flush_rows=flush_rows)
    # group the points by static configuration
    groups: dict[tuple, list] = {}
    point_cfg = {}
    for p in spec.points:
        static, phys, _ = _point_overrides(spec, scenario, p)
        point_cfg[p.index] = (static, phys)
        groups.setdefault(_group_key(static), []).append(p.index)

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
    flown = 0
    nominal_params, _ = _build(spec, scenario)
    scenario.check(nominal_params, np.asarray(scenario.x0, float), _loop_for(spec, scenario, {}))
    for _, point_ids in groups.items():
        static = point_cfg[point_ids[0]][0]
        loop = _loop_for(spec, scenario, static)
        sp = scenario.solver_params(spec.mode)
        params_cache = {}

        def params_of_point(p, params_cache=params_cache):
            if p not in params_cache:
                phys = point_cfg[p][1]
                params_cache[p] = _build(spec, scenario, **phys)[0] if phys else nominal_params
            return params_cache[p]

        group_runs = todo[np.isin(spec.decompose(todo)[0], point_ids)]
        distinct_phys = len({repr(sorted(point_cfg[p][1].items())) for p in point_ids}) > 1
        # every block of the group has the same array shapes (the last one padded): the
        # engine's program depends on them, and a new shape would compile it again
        bucket = min(spec.block, 1 << max(0, int(len(group_runs) - 1).bit_length()))
        for lo in range(0, len(group_runs), spec.block):
            block = group_runs[lo : lo + spec.block]
            rs = run_inputs(spec, scenario, block)
            if rs.physical is not None:
                per_run = _stack(
                    [_build(spec, scenario, **phys, x0=scenario.x0)[0] for phys in rs.physical]
                )
                shared = None
            elif distinct_phys:
                per_run = _stack([params_of_point(int(p)) for p in rs.point])
                shared = None
            else:
                per_run = None
                shared = params_of_point(int(point_ids[0]))
            source = arrays_source(*_pad((jnp.asarray(rs.x0), rs.keys, per_run), bucket))
            unit = spec.chunk * devices
            slots = min(spec.slots, max(unit, int(np.ceil(len(block) / unit)) * unit))
            slots = max(slots, unit)
            cfg = EngineConfig(
                slots=slots, chunk=spec.chunk, iterations=spec.iterations, devices=devices
            )
            base = flown

            def on_results(idx, metrics, rs=rs):
                rows = _rows(spec, scenario, params_of_point, rs, idx, metrics, effort)
                writer.add([{**r, **marks} for r in rows])

            def on_progress(done_block, n, base=base):
                if bar is not None:
                    bar.update(base + done_block - bar.n)
                elif callable(progress):
                    progress(base + done_block, len(todo))

            run_batch(
                loop,
                source,
                len(block),
                params=shared,
                solver_params=sp,
                config=cfg,
                on_results=on_results,
                progress=on_progress,
            )
            flown += len(block)
    writer.close()
    if bar is not None:
        bar.close()
    wall = time.perf_counter() - t0
    return {
        "runs_flown": int(flown),
        "runs_skipped": int(len(done)),
        "seconds": wall,
        "runs_per_s": flown / wall if wall > 0 else float("nan"),
        "peak_memory_mb": peak_rss_mb(),
    }


def replay_inputs(out, run: int):
    """(scenario, loop, params, x0, key, solver params) of run ``run`` of the study in
    ``out``: fly them with :func:`rvdjax.loop.fly` to see that run again."""

    config = read_config(Path(out))
    if config is None:
        raise ValueError(f"--study {out}: no config.json (not a study directory)")
    spec = StudySpec.from_dict(config["spec"])
    if not 0 <= run < spec.n_runs:
        raise ValueError(f"--run must be in [0, {spec.n_runs - 1}], got {run}")
    scenario = study_scenario(spec, out)
    rs = run_inputs(spec, scenario, [run])
    p = int(rs.point[0])
    static, phys, _ = _point_overrides(spec, scenario, spec.points[p])
    if rs.physical is not None:
        phys = rs.physical[0]
    params = _build(spec, scenario, **phys)[0]
    loop = _loop_for(spec, scenario, static)
    return spec, scenario, loop, params, rs.x0[0], rs.keys[0], scenario.solver_params(spec.mode)
