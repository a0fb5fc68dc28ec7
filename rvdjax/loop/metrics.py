"""A run's figures of merit: the running :class:`Accumulator`, the :class:`Metrics` reduced
from it, and :data:`FIELDS`, the one table of the Metrics fields (dtype, unit, label).

Everything that lists the Metrics fields is generated from :data:`FIELDS`: the published
figures a scenario file may name (:data:`FIGURES`), a run's JSON row (:func:`metrics_row`)
and a study's columns (:func:`metrics_columns`); ``tests/test_metrics.py`` checks that they
agree with ``Metrics._fields``.

The Accumulator carries, under the Metrics names, every figure that is a running sum or
minimum (:data:`CARRIED`); its other fields (``time_s``, ``dv_l2``, ``iterations``) are the
sums the derived figures are computed from (time to dock, delta-v, mean iterations).
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from rvdjax.actuators.thrusters import G0
from rvdjax.batching import shapes_of
from rvdjax.solver import Status

if TYPE_CHECKING:
    from rvdjax.loop.kernel import Loop, LoopState, StepInfo

__all__ = [
    "HIST_BINS",
    "RunStatus",
    "Accumulator",
    "Metrics",
    "MetricField",
    "FIELDS",
    "FIGURES",
    "CARRIED",
    "empty_accumulator",
    "accumulate",
    "metrics",
    "metrics_row",
    "metrics_columns",
]

HIST_BINS = 32  # per-step solver iteration histogram: bins 0 .. 30 and >= 31


class RunStatus:
    """How a run ended (``Metrics.status``)."""

    DOCKED = 0
    TIMEOUT = 1  # out of MPC steps (or past LoopConfig.time_limit_s) without docking
    FAILED = 2  # the truth became non-finite (the run stops; its figures stay finite)

    names = ("docked", "timeout", "failed")

    @classmethod
    def name(cls, code: int) -> str:
        return cls.names[int(code)]


class Accumulator(NamedTuple):
    """Running figures of a run (reduced by :func:`metrics`); the fields named as in
    :class:`Metrics` are that figure so far."""

    steps: jnp.ndarray  # () MPC steps flown
    time_s: jnp.ndarray  # () time flown [s]
    total_impulse_N_s: jnp.ndarray  # () sum ||impulse||_2 [N s] (force axes)
    effort_l1_N_s: jnp.ndarray  # () sum ||impulse||_1 [N s]
    dv_l2: jnp.ndarray  # () sum ||dv||_2 [m/s] (delta_v_m_s of delta-v inputs)
    delta_v_l1_m_s: jnp.ndarray  # () sum ||dv||_1 [m/s]
    torque_l1_N_m_s: jnp.ndarray  # () sum |torque| dt [N m s]
    phase_delta_v_m_s: jnp.ndarray  # (P,) L2 delta-v per phase [m/s]
    phase_time_s: jnp.ndarray  # (P,) time per phase [s]
    phase_effort_l1_N_s: jnp.ndarray  # (P,) sum ||impulse||_1 per phase [N s]
    phase_thruster_impulse_N_s: jnp.ndarray  # (P,) thruster impulse per phase [N s]
    margins_m: dict  # name -> () smallest truth margin so far [m]
    status_counts: jnp.ndarray  # (4,) solver statuses
    iterations: jnp.ndarray  # () solver iterations
    iteration_histogram: jnp.ndarray  # (HIST_BINS,) MPC steps per iteration count
    thruster_impulse_N_s: jnp.ndarray  # () sum over thrusters of thrust x on-time [N s]
    valve_openings: jnp.ndarray  # () valve openings
    pulses_dropped: jnp.ndarray  # () pulses dropped by the minimum on-time


class Metrics(NamedTuple):
    """Per-run figures of merit (DESIGN §4), one definition for every family; units and
    shapes in :data:`FIELDS`.

    Impulses count the translational axes (``Layout.force``): a force F acting dt gives F dt,
    a delta-v dv gives m dv; delta-v is impulse / m.
    """

    status: jnp.ndarray  # RunStatus code
    docked: jnp.ndarray
    steps: jnp.ndarray  # MPC steps flown
    time_to_dock_s: jnp.ndarray  # time flown until docking [s] (inf if not docked)
    total_impulse_N_s: jnp.ndarray  # sum_k ||impulse_k||_2
    effort_l1_N_s: jnp.ndarray  # sum_k ||impulse_k||_1 (paper 001 Eq. 14)
    delta_v_m_s: jnp.ndarray  # sum_k ||dv_k||_2
    delta_v_l1_m_s: jnp.ndarray  # sum_k ||dv_k||_1
    torque_l1_N_m_s: jnp.ndarray  # sum_k |torque_k| dt (planar 3-DOF)
    phase_delta_v_m_s: jnp.ndarray  # (P,) L2 delta-v per phase
    phase_time_s: jnp.ndarray  # (P,) time per phase [s]
    phase_effort_l1_N_s: jnp.ndarray  # (P,) effort_l1_N_s per phase
    phase_thruster_impulse_N_s: jnp.ndarray  # (P,) thruster_impulse_N_s per phase
    max_violation_m: jnp.ndarray  # largest violation of a hard constraint by the truth
    margins_m: dict  # name -> smallest truth margin of that block over the run
    status_counts: jnp.ndarray  # (4,) solver statuses over the steps flown
    mean_iterations: jnp.ndarray
    iteration_histogram: jnp.ndarray  # (HIST_BINS,) steps per solver iteration count
    thruster_impulse_N_s: jnp.ndarray  # sum_i F_i t_on,i over every thruster (paper 002 Eq. 11)
    propellant_kg: jnp.ndarray  # thruster impulse / (Isp g0)
    valve_openings: jnp.ndarray  # number of pulses fired
    pulses_dropped: jnp.ndarray  # pulses under the minimum on-time not fired
    contact_speed_m_s: jnp.ndarray  # translational speed of the truth at docking (inf if not)


class MetricField(NamedTuple):
    """One row of :data:`FIELDS`.

    Attributes:
        name: the :class:`Metrics` field.
        dtype: "status" (a :class:`RunStatus` code), "bool", "int" or "float" for one value
            per run; "float[phase]" one per guidance phase, "float[block]" one per truth
            constraint block (a dict), "int[status]" one per solver :class:`Status`,
            "int[bin]" one per histogram bin (:data:`HIST_BINS`).
        unit: SI unit ("" for counts and flags).
        label: what it is, for tables and plots.
        key: its key in :func:`metrics_row` when not ``name`` (the JSON's spelling).
        in_table: a study table has its columns (:func:`metrics_columns`).
    """

    name: str
    dtype: str
    unit: str
    label: str
    key: str | None = None
    in_table: bool = True

    @property
    def row_key(self) -> str:
        return self.name if self.key is None else self.key


F = MetricField
FIELDS: tuple[MetricField, ...] = (
    F("status", "status", "", "how the run ended"),
    F("docked", "bool", "", "docked"),
    F("steps", "int", "", "MPC steps flown"),
    F("time_to_dock_s", "float", "s", "time to dock"),
    F("total_impulse_N_s", "float", "N s", "total impulse, L2 (vector norm)"),
    F("effort_l1_N_s", "float", "N s", "total impulse, L1 (per-axis sum)"),
    F("delta_v_m_s", "float", "m/s", "delta-v (L2)"),
    F("delta_v_l1_m_s", "float", "m/s", "delta-v, L1 (per-axis sum)"),
    F("torque_l1_N_m_s", "float", "N m s", "torque impulse |tau| dt"),
    F("phase_delta_v_m_s", "float[phase]", "m/s", "delta-v (L2) per phase"),
    F("phase_time_s", "float[phase]", "s", "time per phase"),
    F("phase_effort_l1_N_s", "float[phase]", "N s", "total impulse, L1 per phase"),
    F("phase_thruster_impulse_N_s", "float[phase]", "N s", "thruster impulse per phase"),
    F("max_violation_m", "float", "m", "largest constraint violation (truth)"),
    F("margins_m", "float[block]", "m", "smallest truth margin per constraint block"),
    F("status_counts", "int[status]", "", "solver statuses", key="solver_status_counts"),
    F("mean_iterations", "float", "", "mean solver iterations / step"),
    # not in study tables: 32 columns a run (256 MB of a 10^6-run table), which no summary
    # reads; a run's histogram is in `rvdjax run --json` and the benchmarks
    F(
        "iteration_histogram",
        "int[bin]",
        "",
        "MPC steps per solver iteration count",
        in_table=False,
    ),
    F("thruster_impulse_N_s", "float", "N s", "thruster impulse, all thrusters"),
    F("propellant_kg", "float", "kg", "propellant"),
    F("valve_openings", "int", "", "valve openings"),
    F("pulses_dropped", "int", "", "pulses dropped (minimum on-time)"),
    F("contact_speed_m_s", "float", "m/s", "translational speed at docking"),
)
del F

#: The figures with one number per run (what a scenario file's [published] may name).
FIGURES = tuple(f.name for f in FIELDS if f.dtype in ("int", "float"))

#: The Metrics fields the Accumulator carries as they are.
CARRIED = tuple(n for n in Accumulator._fields if n in Metrics._fields)


# ---------------------------------------------------------------------------- in the loop


def truth_kinds(loop: Loop, params, g, x, t) -> dict:
    """{name: kind} of the family's truth blocks: static, so read from one abstract trace of
    ``truth_blocks`` per hook, configuration and argument shapes (a flight asks twice, for
    its empty accumulator and its metrics, and every later trace of the same loop asks again;
    building the blocks only for their names made 7 % of the Python calls of tracing a
    vmapped thesis-vbar flight)."""
    avals, tree = jax.tree.flatten(shapes_of((params, g, x, t)))
    fc = loop.config.family_config
    return dict(_truth_kinds(loop.family.truth_blocks, fc, tree, tuple(avals)))


@functools.lru_cache(maxsize=256)
def _truth_kinds(truth_blocks, family_config, tree, avals) -> tuple[tuple[str, str], ...]:
    # keyed by the hook itself: families compare by name
    kinds = []

    def blocks(params, g, x, t):
        kinds[:] = [(b.name, b.kind) for b in truth_blocks(params, family_config, g, x, t)]
        return ()

    jax.eval_shape(blocks, *jax.tree.unflatten(tree, avals))
    return tuple(kinds)


def empty_accumulator(loop: Loop, params, x0, g, dtype) -> Accumulator:
    """The accumulator of a run that has not flown (``g``: its initial guidance state)."""
    P = loop.family.n_phases
    zero = jnp.zeros((), dtype)
    names = truth_kinds(loop, params, g, x0, zero)
    return Accumulator(
        steps=jnp.zeros((), jnp.int32),
        time_s=zero,
        total_impulse_N_s=zero,
        effort_l1_N_s=zero,
        dv_l2=zero,
        delta_v_l1_m_s=zero,
        torque_l1_N_m_s=zero,
        phase_delta_v_m_s=jnp.zeros(P, dtype),
        phase_time_s=jnp.zeros(P, dtype),
        phase_effort_l1_N_s=jnp.zeros(P, dtype),
        phase_thruster_impulse_N_s=jnp.zeros(P, dtype),
        margins_m={n: jnp.asarray(jnp.inf, dtype) for n in names},
        status_counts=jnp.zeros(4, jnp.int32),
        iterations=jnp.zeros((), jnp.int32),
        iteration_histogram=jnp.zeros(HIST_BINS, jnp.int32),
        thruster_impulse_N_s=zero,
        valve_openings=jnp.zeros((), jnp.int32),
        pulses_dropped=jnp.zeros((), jnp.int32),
    )


def accumulate(loop: Loop, params, acc: Accumulator, info: StepInfo, fired=None) -> Accumulator:
    """``acc`` after the step ``info`` (``fired``: the thrusters' firing of the step, or None
    for ideal forces)."""
    lay = loop.family.layout
    act = info.active
    idx = jnp.asarray(lay.force, int)
    dv = info.u[idx] * (info.dt / params.plant.mass if lay.input == "force" else 1.0)
    imp = dv * params.plant.mass if lay.input == "delta-v" else info.u[idx] * info.dt
    dv2 = jnp.linalg.norm(dv)
    tq = jnp.asarray(lay.torque, int)
    torque = jnp.sum(jnp.abs(info.u[tq])) * info.dt if lay.torque else 0.0
    P = loop.family.n_phases
    in_phase = (info.phase == jnp.arange(P)) & act
    hist_bin = jnp.minimum(info.iterations, HIST_BINS - 1)
    imp_l1 = jnp.sum(jnp.abs(imp))
    thrust_imp = 0.0 if fired is None else fired.thrust_impulse
    return Accumulator(
        steps=acc.steps + act.astype(jnp.int32),
        time_s=acc.time_s + info.dt,
        total_impulse_N_s=acc.total_impulse_N_s + jnp.where(act, jnp.linalg.norm(imp), 0.0),
        effort_l1_N_s=acc.effort_l1_N_s + jnp.where(act, imp_l1, 0.0),
        dv_l2=acc.dv_l2 + jnp.where(act, dv2, 0.0),
        delta_v_l1_m_s=acc.delta_v_l1_m_s + jnp.where(act, jnp.sum(jnp.abs(dv)), 0.0),
        torque_l1_N_m_s=acc.torque_l1_N_m_s + jnp.where(act, torque, 0.0),
        phase_delta_v_m_s=acc.phase_delta_v_m_s + jnp.where(in_phase, dv2, 0.0),
        phase_time_s=acc.phase_time_s + jnp.where(in_phase, info.dt, 0.0),
        phase_effort_l1_N_s=acc.phase_effort_l1_N_s + jnp.where(in_phase, imp_l1, 0.0),
        phase_thruster_impulse_N_s=acc.phase_thruster_impulse_N_s
        + jnp.where(in_phase, thrust_imp, 0.0),
        margins_m={
            n: jnp.minimum(low, jnp.where(act, jnp.min(info.margins[n]), jnp.inf))
            for n, low in acc.margins_m.items()
        },
        status_counts=acc.status_counts + Status.counts(info.status, act).astype(jnp.int32),
        iterations=acc.iterations + jnp.where(act, info.iterations, 0).astype(jnp.int32),
        iteration_histogram=acc.iteration_histogram.at[hist_bin].add(act.astype(jnp.int32)),
        thruster_impulse_N_s=acc.thruster_impulse_N_s + jnp.where(act, thrust_imp, 0.0),
        valve_openings=acc.valve_openings
        + (0 if fired is None else jnp.where(act, fired.openings, 0).astype(jnp.int32)),
        pulses_dropped=acc.pulses_dropped
        + (0 if fired is None else jnp.where(act, fired.dropped, 0).astype(jnp.int32)),
    )


def metrics(loop: Loop, params, state: LoopState) -> Metrics:
    """The run's :class:`Metrics` from its final state (the one reduction for every family)."""
    acc = state.acc
    kinds = truth_kinds(loop, params, state.guidance, state.x, state.t)
    judged = [acc.margins_m[n] for n, kind in kinds.items() if kind == "hard"]
    worst = jnp.min(jnp.stack([*judged, jnp.asarray(jnp.inf, state.x.dtype)]))
    docked = state.docked
    # a NaN anywhere in the figures (a non-finite truth) fails the run; no NaN is returned
    nan = jnp.any(jnp.stack([jnp.any(jnp.isnan(a)) for a in jax.tree.leaves(acc)]))
    failed = state.failed | nan
    status = jnp.where(
        docked & ~failed,
        RunStatus.DOCKED,
        jnp.where(failed, RunStatus.FAILED, RunStatus.TIMEOUT),
    )
    mass = params.plant.mass

    def clean(a):  # NaN -> +inf ("unknown"), never NaN in a batch's results
        return jnp.where(jnp.isnan(a), jnp.inf, a)

    force = loop.family.layout.input == "force"
    out = Metrics(
        **{name: getattr(acc, name) for name in CARRIED},
        status=status.astype(jnp.int32),
        docked=docked & ~failed,
        time_to_dock_s=jnp.where(docked & ~failed, acc.time_s, jnp.inf),
        delta_v_m_s=acc.total_impulse_N_s / mass if force else acc.dv_l2,
        max_violation_m=jnp.maximum(0.0, -worst),
        mean_iterations=acc.iterations / jnp.maximum(acc.steps, 1),
        propellant_kg=acc.thruster_impulse_N_s / (_isp(params) * G0),
        contact_speed_m_s=jnp.where(docked & ~failed, _speed(loop, state.x), jnp.inf),
    )
    return jax.tree.map(lambda a: clean(a) if jnp.issubdtype(a.dtype, jnp.floating) else a, out)


def _speed(loop: Loop, x):
    """Translational speed of state ``x`` [m/s] (the velocities of the position axes)."""
    lay = loop.family.layout
    v = x[jnp.asarray(lay.vel[: len(lay.pos)], int)]
    return jnp.sqrt(jnp.sum(v * v))


def _isp(params):
    """Specific impulse [s] of the thrusters (1 without thrusters: no propellant is used)."""
    thr = params.plant.thrusters
    return jnp.asarray(1.0) if thr is None else thr.isp_s


# -------------------------------------------------------------------------- outside the loop


def _json(v):
    v = float(v)
    return v if np.isfinite(v) else None


def metrics_row(m: Metrics) -> dict:
    """One run's metrics as plain JSON values (inf as None), keyed by
    :attr:`MetricField.row_key`: status by name, solver statuses as {status name: count},
    per-phase figures and the histogram as lists, margins as {block: value}."""
    out = {}
    for f in FIELDS:
        v = getattr(m, f.name)
        if f.dtype == "status":
            v = RunStatus.name(int(v))
        elif f.dtype == "bool":
            v = bool(v)
        elif f.dtype == "int":
            v = int(v)
        elif f.dtype == "float":
            v = _json(v)
        elif f.dtype == "float[phase]":
            v = [_json(e) for e in np.asarray(v)]
        elif f.dtype == "float[block]":
            v = {k: _json(e) for k, e in v.items()}
        elif f.dtype == "int[status]":
            v = {Status.name(i): int(c) for i, c in enumerate(np.asarray(v))}
        elif f.dtype == "int[bin]":
            v = [int(c) for c in np.asarray(v)]
        else:
            raise ValueError(f"no row form for dtype {f.dtype!r} ({f.name})")
        out[f.row_key] = v
    return out


def metrics_columns(m: Metrics) -> dict[str, dict[str, np.ndarray]]:
    """Metrics of n runs (leading axis n on every field) as table columns, per field:
    {field: {column: (n,) array}}. A status is its name (object array); one column per
    phase (``phase0_time_s``), per truth block (``margin_keep_out_m``), per solver status
    (``solves_converged``); the fields marked ``in_table`` only."""
    out = {}
    for f in (f for f in FIELDS if f.in_table):
        v = getattr(m, f.name)
        if f.dtype == "status":
            cols = {f.name: np.asarray(RunStatus.names, dtype=object)[np.asarray(v)]}
        elif f.dtype == "bool":
            cols = {f.name: np.asarray(v, bool)}
        elif f.dtype == "int":
            cols = {f.name: np.asarray(v, np.int64)}
        elif f.dtype == "float":
            cols = {f.name: np.asarray(v, np.float64)}
        elif f.dtype == "float[phase]":
            v = np.asarray(v, np.float64)
            rest = f.name.removeprefix("phase_")
            cols = {f"phase{p}_{rest}": v[:, p] for p in range(v.shape[1])}
        elif f.dtype == "float[block]":
            cols = {f"margin_{k}_{f.unit}": np.asarray(e, np.float64) for k, e in v.items()}
        elif f.dtype == "int[status]":
            v = np.asarray(v, np.int64)
            cols = {f"solves_{Status.name(k)}": v[:, k] for k in range(v.shape[1])}
        elif f.dtype == "int[bin]":
            v = np.asarray(v, np.int64)
            cols = {f"{f.name}_{k}": v[:, k] for k in range(v.shape[1])}
        else:
            raise ValueError(f"no column form for dtype {f.dtype!r} ({f.name})")
        out[f.name] = cols
    return out
