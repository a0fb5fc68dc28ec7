"""A study's runs and their inputs: run r's sweep point, initial state, drawn values and PRNG
key, computed in calls of ``ALIGN`` runs aligned on the run index, so that a run's inputs
(and bits) do not depend on which runs are drawn with it (:mod:`rvdjax.study.runner`)."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from rvdjax.study import samplers
from rvdjax.study.spec import ParamRef, StudySpec, resolve

__all__ = ["RunSet", "run_inputs", "ALIGN"]

ALIGN = 1024  # runs per call of the input samplers (module docstring)


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
