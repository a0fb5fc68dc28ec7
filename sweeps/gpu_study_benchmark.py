"""GPU study benchmark: the batch engine and the studies at accelerator scale, against the same
machine's CPU cores, in one run of at most ``--budget-s`` seconds (290), compile included.

    PYTHONPATH=. python sweeps/gpu_study_benchmark.py [--out DIR] [--budget-s 290]
        [--parts throughput,ch5,study,cpu,bits|settings] [--kernel K] [--settings S]
        [--scenarios A,B] [--slots 4096,32768] [--block 128 --warps 4] [--smoke]

From the repository root on a machine whose jax has GPU support; nothing to install. Parts,
each with its own time budget (a share of ``--budget-s``; a part that runs out stops and
reports what it measured), each a function that ``sweeps/gpu_benchmark.py`` also calls:

* ``throughput``: maneuvers/s of ``thesis-vbar``, ``fastmpc-3d`` and ``poseidyn-lqmpc`` at
  4 096 and 32 768 slots (``rvdjax bench --closed-loop``'s initial states: x0 perturbed by
  2 %), the engine's other settings chosen for the device
  (:func:`rvdjax.loop.engine.auto_config`); compile time apart; the rate over the runs
  finished while the queue kept every slot busy when the budget cut the queue short;
  ``--block``/``--warps`` set the Pallas kernels' tile (``rvdjax.solver.lanes.KernelConfig``);
* ``refresh``: ``thesis-vbar`` at 32 768 slots with the other refresh than the device's
  choice (masked on a GPU), against its ``throughput`` row;
* ``ch5``: paper 003 Ch. 5 (``rvdjax study robustness thesis-vbar --initial-conditions 100
  --realisations 60 --initial paper003 --nav-filter --time-limit-s 12000 --n-steps 2600``):
  its flying time (compiled beforehand by a first segment), successes and docked runs;
* ``study``: ``rvdjax study montecarlo thesis-vbar --runs 1000000 --initial paper003``, as
  much of it as fits in its budget: runs written, their rate once compiled, the projected
  wall time of the 10^6 runs (compile included), the share of the flying time the device was
  busy, and the table's checks (no NaN, every MPC step's solve status counted);
* ``cpu``: the same study on this machine's CPU cores (one XLA host device per core, the CPU
  defaults), for the baseline and the ratio;
* ``bits``: 256 ``thesis-vbar`` runs at two slot counts on the GPU: do they give the same
  bits (checked on the CPU by the tests; on a GPU not yet)?
* ``settings`` (only when named in ``--parts``): ``thesis-vbar``'s maneuvers/s under the
  accelerator's engine settings changed one at a time (``SETTINGS``, or ``--settings
  "slots=4096/slots=4096,iterations=8"``): slots, solver iterations per tick, ticks per
  segment, refresh.

Rows go to ``OUT/gpu_study_benchmark.jsonl`` as they are measured; the table is printed at
the end. ``--smoke`` runs tiny sizes on whatever device there is (the CPU here): the script's
own test.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time

# One XLA host device per core for the CPU baseline: set before JAX starts.
if "xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "")
        + f" --xla_force_host_platform_device_count={os.cpu_count() or 1}"
    ).strip()

import jax  # noqa: E402
import numpy as np  # noqa: E402
from gpu_benchmark import Recorder  # noqa: E402  (rows to JSON lines as they come)

import rvdjax  # noqa: E402, F401  (float64, XLA options)

SCENARIOS = ("thesis-vbar", "fastmpc-3d", "poseidyn-lqmpc")
SLOTS = (4096, 32768)
STUDY_RUNS = 1_000_000
# shares of the budget (the parts run in this order; time a part leaves goes to the next)
SHARES = {
    "throughput": 0.38,
    "refresh": 0.08,
    "ch5": 0.14,
    "study": 0.18,
    "cpu": 0.14,
    "bits": 0.08,
    "settings": 0.5,  # only when asked for (--parts settings): not in DEFAULT_PARTS
}
DEFAULT_PARTS = tuple(p for p in SHARES if p != "settings")

SMOKE = dict(slots=(32,), n_steps=40, ch5=(4, 3), study_runs=1_000_000)
# The accelerator's engine settings one at a time (part "settings", thesis-vbar): the
# device's choices at 4 096 slots first, then each with one setting changed; a variant's
# budget is its weight's share of the part's.
SETTINGS = (
    ({"slots": 4096}, 1.0),
    ({"slots": 4096, "iterations": 8}, 1.0),
    ({"slots": 4096, "ticks_per_segment": 512}, 0.6),  # the same program: no compile
    ({"slots": 4096, "refresh": "masked"}, 1.0),
    ({"slots": 16384}, 1.8),  # a wave of runs takes longer: more of the budget
    ({"slots": 4096, "iterations": 2}, 1.0),
)


def _platform(smoke: bool) -> str:
    """The accelerator's platform ("gpu"), or the CPU when there is none (smoke runs)."""
    backend = jax.default_backend()
    if backend == "cpu" and not smoke:
        print("no GPU: JAX's default backend is the CPU (use --smoke to test the script)")
    return backend


# ------------------------------------------------------------------------------ throughput


def throughput(
    scenario: str,
    slots: int,
    budget_s: float,
    smoke: bool = False,
    refresh: str | None = None,
    kernel: str | None = None,
    part: str | None = None,
    **engine,
) -> dict:
    """Maneuvers/s of ``scenario`` through ``slots`` slots on the default device: a queue of
    3 x slots runs (x0 perturbed by 2 %), cut at ``budget_s`` (compile included); ``refresh``
    and ``engine`` (other :class:`EngineConfig` fields) override the engine's choices,
    ``kernel`` the Newton step's form (SolverSettings)."""
    from rvdjax.bench import perturbed_states
    from rvdjax.loop.engine import arrays_source, auto_config, compile_engine

    t_start = time.perf_counter()
    sc = _scenario(scenario)
    from rvdjax.scenarios import FlightOptions

    options = FlightOptions(n_steps=SMOKE["n_steps"] if smoke else None)
    settings = sc.settings(options.mode, kernel=kernel) if kernel else None
    flight = sc.flight(options, settings=settings)
    params, x0, loop = flight.params, flight.x0, flight.loop
    sp = sc.solver_params()
    n = 3 * slots
    source = arrays_source(perturbed_states(x0, n))
    cfg = auto_config(slots=slots, refresh=refresh, **engine)
    t0 = time.perf_counter()
    compile_engine(loop, source, params, sp, cfg)
    compile_s = time.perf_counter() - t0
    marks = []
    deadline = t_start + budget_s
    out = _run_until(loop, source, n, params, sp, cfg, deadline, marks)
    rate_all = out["done"] / out["seconds"] if out["seconds"] > 0 else float("nan")
    return dict(
        part=part or ("throughput" if refresh is None else "refresh"),
        scenario=scenario,
        slots=cfg.n_slots,
        device=str(jax.devices(cfg.platform)[0].device_kind),
        runs=int(out["done"]),
        queued=n,
        seconds=out["seconds"],
        maneuvers_per_s=rate_all if out["done"] >= n else _steady_rate(marks),
        complete=bool(out["done"] >= n),
        compile_s=compile_s,
        device_busy_share=out["device_busy_s"] / out["seconds"] if out["seconds"] else None,
        engine=cfg.describe(),
        kernel=flight.loop.config.settings.kernel,
    )


def _run_until(loop, source, n, params, sp, cfg, deadline, marks):
    from rvdjax.loop.engine import Block, run_stream

    t0 = time.perf_counter()

    def progress(done, total):
        marks.append((time.perf_counter() - t0, done))

    return run_stream(
        loop,
        source.fn,
        [Block(source.data, 0, n)],
        n,
        params=params,
        solver_params=sp,
        config=cfg,
        progress=progress,
        keep=False,
        deadline=deadline,
    )


def _steady_rate(marks) -> float:
    """Runs per second over the second half of a cut-short run (the slots full, the first
    runs' fill-up behind)."""
    if len(marks) < 2:
        return marks[-1][1] / marks[-1][0] if marks and marks[-1][0] > 0 else float("nan")
    t = np.asarray([m[0] for m in marks])
    d = np.asarray([m[1] for m in marks], float)
    half = np.searchsorted(t, t[-1] / 2)
    half = min(half, len(t) - 2)
    dt = t[-1] - t[half]
    return float((d[-1] - d[half]) / dt) if dt > 0 else float("nan")


def _scenario(name: str):
    from rvdjax.scenarios import get_scenario

    return get_scenario(name)


# ------------------------------------------------------------------------------------ ch5


def ch5(budget_s: float, smoke: bool = False, platform: str | None = None, devices: int = 1):
    """Paper 003 Ch. 5 robustness: its flying time on ``platform`` (compiled first)."""
    from rvdjax.study import StudySpec, run_study, summarize

    n_ic, reps = SMOKE["ch5"] if smoke else (100, 60)
    spec = StudySpec(
        kind="robustness",
        scenario="thesis-vbar",
        n_initial=n_ic,
        replicates=reps,
        initial="paper003",
        disturbed=True,
        nav_filter=True,
        time_limit_s=12000.0,
        n_steps=SMOKE["n_steps"] if smoke else 2600,
    )
    engine = {"platform": platform} if platform else None
    t_start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        # the same program for the timed run: one segment compiles it
        run_study(spec, os.path.join(tmp, "warm"), progress=False, max_seconds=0.0,
                  engine=engine, devices=devices)  # fmt: skip
        compile_s = time.perf_counter() - t_start
        left = budget_s - (time.perf_counter() - t_start)
        out = os.path.join(tmp, "ch5")
        timing = run_study(spec, out, progress=False, max_seconds=max(1.0, left),
                           engine=engine, devices=devices)  # fmt: skip
        s = summarize(out)
    return dict(
        part="ch5",
        runs=timing["runs_flown"],
        of=spec.n_runs,
        flying_s=timing["seconds"],
        complete=timing["runs_left"] == 0,
        successes=s["successes"],
        docked=s["docked"],
        compile_s=compile_s,
        device_busy_share=1 - timing["outside_device_share"],
        engine=timing["engine"][0] if timing["engine"] else "",
    )


# ---------------------------------------------------------------------------------- study


def study(
    budget_s: float,
    smoke: bool = False,
    platform: str | None = None,
    devices: int = 1,
    part: str = "study",
):
    """``rvdjax study montecarlo thesis-vbar --runs 1000000 --initial paper003`` for at most
    ``budget_s`` (compile included): runs written, their rate once compiled, the projected
    time of all 10^6 runs (compile included), the table's checks."""
    from rvdjax.study import StudySpec, read_table, run_study

    spec = StudySpec(
        kind="montecarlo",
        scenario="thesis-vbar",
        n_initial=SMOKE["study_runs"] if smoke else STUDY_RUNS,
        initial="paper003",
        n_steps=SMOKE["n_steps"] if smoke else None,
    )
    engine = {"platform": platform} if platform else None
    tmp = tempfile.mkdtemp(prefix="rvdjax-gpu-study-")
    try:
        t0 = time.perf_counter()
        timing = run_study(spec, tmp, progress=False, max_seconds=budget_s, engine=engine,
                           devices=devices)  # fmt: skip
        wall = time.perf_counter() - t0
        df = read_table(tmp) if timing["runs_flown"] else None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    checks = _table_checks(df)
    flying = wall - timing["compile_s"]
    rate = timing["runs_flown"] / flying if flying > 0 else float("nan")
    return dict(
        part=part,
        runs=timing["runs_flown"],
        of=spec.n_runs,
        seconds=wall,
        compile_s=timing["compile_s"],
        runs_per_s=rate,
        projected_s=timing["compile_s"] + spec.n_runs / rate if rate > 0 else float("inf"),
        device_busy_share=1 - timing["outside_device_share_flying"],
        peak_memory_mb=timing["peak_memory_mb"],
        devices=devices,
        engine=timing["engine"][0] if timing["engine"] else "",
        **checks,
    )


def _table_checks(df) -> dict:
    """No NaN in the table; every MPC step's solve status counted (the solve counts of a row
    sum to its steps)."""
    if df is None:
        return dict(nan_values=None, statuses_counted=None)
    numeric = df.select_dtypes("number")
    solves = df[[c for c in df.columns if c.startswith("solves_")]].sum(axis=1)
    return dict(
        nan_values=int(numeric.isna().sum().sum()),
        statuses_counted=bool((solves == df["steps"]).all()),
        docked_share=float(df["docked"].mean()),
    )


# ------------------------------------------------------------------------------- settings


def parse_settings(text: str | None) -> list[tuple[dict, float]]:
    """``"slots=4096/slots=4096,iterations=8"`` -> [({"slots": 4096}, 1.0), ...]: engine
    settings (:class:`EngineConfig` fields; integers where they parse) a variant, equal
    weights; None: ``SETTINGS``."""
    if not text:
        return list(SETTINGS)
    out = []
    for variant in (v for v in text.split("/") if v):
        values = {}
        for pair in variant.split(","):
            key, _, value = pair.partition("=")
            values[key.strip()] = int(value) if value.strip().isdigit() else value.strip()
        out.append((values, 1.0))
    return out


def engine_settings(budget_s: float, smoke: bool = False, text: str | None = None) -> list[dict]:
    """thesis-vbar's maneuvers/s under each engine-settings variant (``parse_settings``),
    each within its share of ``budget_s`` (compile included)."""
    variants = parse_settings(text)
    total = sum(w for _, w in variants)
    rows = []
    for values, weight in variants:
        values = dict(values)
        if smoke:
            values["slots"] = SMOKE["slots"][0]
        slots = values.pop("slots", SLOTS[0])
        try:
            row = throughput("thesis-vbar", slots, weight / total * budget_s, smoke,
                             part="settings", **values)  # fmt: skip
            rows.append(dict(row, variant=", ".join(f"{k}={v}" for k, v in values.items())))
        except Exception as err:  # one variant's failure is reported; the next still run
            rows.append(dict(part="settings", variant=str(values), error=f"{err}"[:300]))
    return rows


# ----------------------------------------------------------------------------------- bits


def bits(budget_s: float, smoke: bool = False) -> dict:
    """256 thesis-vbar runs through two slot counts on the default device: equal bits?"""
    from rvdjax.bench import perturbed_states
    from rvdjax.loop.engine import auto_config, fly_batch

    sc = _scenario("thesis-vbar")
    from rvdjax.scenarios import FlightOptions

    flight = sc.flight(FlightOptions(n_steps=SMOKE["n_steps"] if smoke else 400))
    params, x0, loop = flight.params, flight.x0, flight.loop
    n = 64 if smoke else 256
    x0s = perturbed_states(x0, n, rel=0.05)
    t0 = time.perf_counter()
    out = [fly_batch(loop, params, x0s, config=auto_config(slots=s)) for s in (n // 4, n)]
    a, b = (np.asarray(m.delta_v_m_s) for m in out)
    return dict(
        part="bits",
        runs=n,
        slots=f"{n // 4} vs {n}",
        runs_differing=int(np.sum(a != b)),
        largest_difference_m_s=float(np.max(np.abs(a - b))),
        seconds=time.perf_counter() - t0,
        within_budget=bool(time.perf_counter() - t0 <= budget_s),
    )


# ---------------------------------------------------------------------------------- table


def format_table(rows: list[dict]) -> str:
    out = []
    cpu = next((r for r in rows if r.get("part") == "cpu"), None)
    gpu = next((r for r in rows if r.get("part") == "study"), None)
    for r in rows:
        p = r.get("part")
        if p in ("throughput", "refresh", "settings") and "error" not in r:
            cut = "" if r["complete"] else f" (cut at {r['runs']} of {r['queued']})"
            how = r["engine"].split(", ")[3] if p == "refresh" else ""
            how = f"[{r.get('variant') or 'as chosen'}]" if p == "settings" else how
            out.append(
                f"{r['scenario']:<16} {r['slots']:>6} slots: {r['maneuvers_per_s']:>9.0f} "
                f"maneuvers/s{cut}, compile {r['compile_s']:.1f} s {how}".rstrip()
            )
        elif p == "ch5":
            done = "" if r["complete"] else f" (cut: {r['runs']} of {r['of']} runs)"
            out.append(
                f"Ch. 5 ({r['of']} runs): flown in {r['flying_s']:.1f} s{done}, "
                f"{r['successes']} successes, {r['docked']} docked, compile {r['compile_s']:.1f} s"
            )
        elif p in ("study", "cpu"):
            where = "GPU" if p == "study" else f"CPU, {r['devices']} cores"
            out.append(
                f"10^6-run thesis-vbar study on the {where}: {r['runs']} runs in "
                f"{r['seconds']:.0f} s (compile {r['compile_s']:.0f} s, then "
                f"{r['runs_per_s']:.0f} runs/s; all 10^6 in {r['projected_s']:.0f} s), device "
                f"busy {r['device_busy_share']:.0%} once compiled, NaN {r['nan_values']}, "
                f"statuses counted {r['statuses_counted']}"
            )
        elif p == "bits":
            out.append(
                f"bits at {r['slots']} slots: {r['runs_differing']} of {r['runs']} runs differ "
                f"(largest {r['largest_difference_m_s']:.3g} m/s)"
            )
        if "error" in r:
            out.append(f"{p}: error: {r['error']}")
    if cpu and gpu and cpu["runs_per_s"] > 0:
        ratio = gpu["runs_per_s"] / cpu["runs_per_s"]
        out.append(f"study rate, GPU over the CPU cores: {ratio:.1f}x")
    return "\n".join(out)


# ----------------------------------------------------------------------------------- main


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="results/gpu", help="directory for the JSON lines")
    ap.add_argument("--budget-s", type=float, default=None, help="seconds in all (290)")
    ap.add_argument("--parts", default=",".join(DEFAULT_PARTS), help="comma-separated parts")
    ap.add_argument("--smoke", action="store_true", help="tiny sizes: test the script")
    ap.add_argument("--kernel", default=None, help="the Newton step's form for throughput rows")
    ap.add_argument("--scenarios", default=",".join(SCENARIOS), help="throughput's scenarios")
    ap.add_argument("--slots", default=None, help="throughput's slot counts (4096,32768)")
    ap.add_argument("--block", type=int, default=None, help="the kernels' problems a program")
    ap.add_argument("--warps", type=int, default=None, help="the kernels' warps a program")
    ap.add_argument(
        "--settings",
        default=None,
        help="the settings part's variants: NAME=VALUE pairs joined by ',', variants by '/'"
        " (default: SETTINGS)",
    )
    args = ap.parse_args(argv)
    tile = {k: v for k, v in (("block", args.block), ("num_warps", args.warps)) if v}
    for name, v in tile.items():
        if v < 1 or v & (v - 1):
            print(f"--{'warps' if name == 'num_warps' else name}: must be a power of two, got {v}")
            return 2
    scenarios = [s for s in args.scenarios.split(",") if s]
    parts = [p for p in args.parts.split(",") if p]
    unknown = set(parts) - set(SHARES)
    if unknown:
        print(f"--parts: unknown {', '.join(sorted(unknown))}; choose from {', '.join(SHARES)}")
        return 2
    budget = args.budget_s or (240.0 if args.smoke else 290.0)
    os.makedirs(args.out, exist_ok=True)
    rec = Recorder(os.path.join(args.out, "gpu_study_benchmark.jsonl"))
    from rvdjax.bench import machine_info
    from rvdjax.solver import lanes

    platform = _platform(args.smoke)
    from rvdjax.provenance import benchmark_block

    rec.add(
        part="machine",
        machine=machine_info(),
        devices=[str(d) for d in jax.devices()],
        provenance=benchmark_block("sweeps/gpu_study_benchmark.py", vars(args)),
    )
    t_start = time.perf_counter()
    total_share = sum(SHARES[p] for p in parts)
    carried = 0.0

    def part_budget(name: str) -> float:
        return SHARES[name] / total_share * budget + carried

    for name in parts:
        t0 = time.perf_counter()
        allowed = min(part_budget(name), budget - (t0 - t_start))
        try:
            if name == "throughput":
                sizes = SMOKE["slots"] if args.smoke else SLOTS
                if args.slots:
                    sizes = tuple(int(v) for v in args.slots.split(","))
                each = allowed / (len(scenarios) * len(sizes))
                for scenario in scenarios:
                    for slots in sizes:
                        with lanes.configured(**tile):
                            row = throughput(scenario, slots, each, args.smoke, kernel=args.kernel)
                        rec.add(**row, **tile)
            elif name == "refresh":  # the other refresh than the device's choice
                slots = (SMOKE["slots"] if args.smoke else SLOTS)[-1]
                other = "masked" if platform != "cpu" else "compacted"
                rec.add(**throughput("thesis-vbar", slots, allowed, args.smoke, other))
            elif name == "ch5":
                rec.add(**ch5(allowed, args.smoke, platform))
            elif name == "study":
                rec.add(**study(allowed, args.smoke, platform))
            elif name == "cpu":
                cores = len(jax.devices("cpu"))
                rec.add(**study(allowed, args.smoke, "cpu", devices=cores, part="cpu"))
            elif name == "bits":
                rec.add(**bits(allowed, args.smoke))
            elif name == "settings":
                for row in engine_settings(allowed, args.smoke, args.settings):
                    rec.add(**row)
        except Exception as err:  # a part's failure is reported, the next parts still run
            rec.add(part=name, error=f"{type(err).__name__}: {err}")
        carried = max(0.0, allowed - (time.perf_counter() - t0))
    print(format_table(rec.rows))
    print(f"total {time.perf_counter() - t_start:.0f} s; rows: {rec.path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
