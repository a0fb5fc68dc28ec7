"""Study benchmark: the batch engine against the same maneuvers flown one by one from a Python
loop with Clarabel, PIQP, DAQP (sparse and condensed) or HPIPM (where its library is
installed: rvdjax.peers_hpipm) solving every MPC step; and the memory of a study against its
number of runs.

    python sweeps/study_benchmark.py throughput [--scenario thesis-vbar] [--batch-runs 256]
        [--slots 64] [--single-runs 8] [--peers clarabel,piqp,...] [--json FILE]
    python sweeps/study_benchmark.py memory [--runs 1000,100000] [--json FILE]
    python sweeps/study_benchmark.py refresh [--scenarios thesis-vbar,poseidyn-lqmpc,fastmpc-3d]
        [--slots 64] [--batch-runs 128] [--repeats 2] [--json FILE]

Throughput: the same initial conditions (paper 003 Sec. 4.1 for three-phase scenarios, the
scenario's x0 perturbed otherwise), one core (XLA single threaded), compile excluded. The
engine flies a queue of ``--batch-runs`` runs through ``--slots`` slots, as a study does (a
queue longer than the slots keeps the batch full; with as many slots as runs the wall time is
the longest run's). The Python loop calls the jitted MPC step once per step (the host solver
inside it through a callback: QP assembly in SciPy included), as a user without rvdjax's
engine would, on ``--single-runs`` runs spread evenly over the queue (its step compiled
first, by one untimed run). Maneuvers differ in length (0.15-2.5 km), so the ratio is given
per maneuver and per MPC step flown. The Python loop's rows also give its milliseconds per
step and, on the first step's QP of the same runs, the assembly and the host solve alone:
the solve alone bounds what any engine speed can make of the ratio.
Memory: `rvdjax study montecarlo` in a fresh process per size (peak RSS of that process, the
rate, and the share of wall time the device was not busy).
Refresh: the engine's two refreshes of the slots whose solve finished, the masked one (by
chunk, the other slots masked) and the compacted one (only those slots, gathered by lane),
on the same runs, alternated ``--repeats`` times in one process (one core, compile excluded).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

import rvdjax  # noqa: F401  (its XLA options, before JAX starts)
from rvdjax.xla_options import one_thread

one_thread()

import numpy as np  # noqa: E402

from rvdjax.peers_hpipm import hpipm_unavailable  # noqa: E402

DEFAULT_PEERS = ("clarabel", "piqp", "daqp", "daqp-condensed")


def throughput(args) -> list[dict]:
    import jax

    from rvdjax.loop.engine import EngineConfig, arrays_source, run_batch
    from rvdjax.loop.reference import reference_loop
    from rvdjax.scenarios import FlightOptions, get_scenario
    from rvdjax.study import StudySpec
    from rvdjax.study.runner import run_inputs

    sc = get_scenario(args.scenario)
    flight = sc.flight(FlightOptions(time_limit_s=args.time_limit_s, n_steps=args.n_steps))
    params, loop = flight.params, flight.loop
    initial = "paper003" if sc.family == "three-phase" else "nominal"
    vary = () if initial == "paper003" else (("x0", "*normal(1,0.02)"),)
    spec = StudySpec(
        kind="montecarlo", scenario=sc.name, n_initial=args.batch_runs, initial=initial, vary=vary
    )
    rs = run_inputs(spec, sc, np.arange(args.batch_runs))
    rows = []
    cfg = EngineConfig(slots=min(args.slots, args.batch_runs), chunk=32)
    src = arrays_source(rs.x0, rs.keys)
    # compile with the timed queue's shapes (a queue of another length compiles again)
    run_batch(loop, src, 2, params=params, config=cfg)
    t0 = time.perf_counter()
    out = run_batch(loop, src, args.batch_runs, params=params, config=cfg)
    wall = time.perf_counter() - t0
    m = out["metrics"]
    engine_rate = args.batch_runs / wall
    engine_steps = float(np.sum(m.steps)) / wall
    rows.append(
        {
            "method": f"rvdjax batch engine, {args.batch_runs} runs in {cfg.slots} slots",
            "runs": args.batch_runs,
            "maneuvers_per_s": engine_rate,
            "steps_per_s": engine_steps,
            "docked_fraction": float(np.mean(m.docked)),
            "ratio": 1.0,
            "ratio_per_step": 1.0,
        }
    )
    subset = np.unique(np.linspace(0, args.batch_runs - 1, args.single_runs).round().astype(int))
    peers = args.peers or ",".join(DEFAULT_PEERS + (() if hpipm_unavailable() else ("hpipm",)))
    for backend in peers.split(","):
        # compile the step (the loop itself: its step length is static, a shorter loop would
        # compile another step) by flying the first run once untimed, then time whole maneuvers
        reference_loop(loop, params, rs.x0[subset[0]], rs.keys[subset[0]], backend=backend)
        secs, steps, agree = 0.0, 0, []
        for i in subset:
            _, mi, s = reference_loop(loop, params, rs.x0[i], rs.keys[i], backend=backend)
            secs += s
            steps += int(mi.steps)
            agree.append(
                (bool(mi.docked) == bool(m.docked[i]))
                and abs(float(mi.delta_v_m_s) - float(m.delta_v_m_s[i]))
                <= 1e-3 * max(1.0, float(m.delta_v_m_s[i]))
            )
        rate = len(subset) / secs
        assembly_ms, solve_ms = _host_parts(loop, params, rs, subset, backend)
        rows.append(
            {
                "method": f"Python loop, {backend} per step",
                "runs": len(subset),
                "maneuvers_per_s": rate,
                "steps_per_s": steps / secs,
                "ratio": engine_rate / rate,
                "ratio_per_step": engine_steps / (steps / secs),
                "same_outcome_as_engine": f"{sum(agree)}/{len(agree)}",
                "ms_per_step": 1e3 * secs / steps,
                "qp_assembly_ms": assembly_ms,
                "host_solve_ms": solve_ms,
            }
        )
        print(rows[-1], file=sys.stderr)
    del jax
    return rows


def _host_parts(loop, params, rs, subset, backend: str, repeats: int = 5):
    """Milliseconds of the Python loop's two host parts on the first MPC step's QP of the
    timed runs: the SciPy assembly (rvdjax.qp.to_qp) and the host solver alone."""
    import jax

    from rvdjax.loop.kernel import init, prepare
    from rvdjax.qp import to_qp
    from rvdjax.solver.clarabel import _host_solve  # the loop's own dispatch to the peers

    def solve(qp):
        return _host_solve(backend, qp)

    build, solved = [], []
    for i in subset:
        st = init(loop, params, rs.x0[i], rs.keys[i])
        ocp = jax.tree.map(np.asarray, prepare(loop, params, st).ocp)
        qp = to_qp(ocp, soft=True)
        solve(qp)
        t0 = time.perf_counter()
        for _ in range(repeats):
            to_qp(ocp, soft=True)
        t1 = time.perf_counter()
        for _ in range(repeats):
            solve(qp)
        t2 = time.perf_counter()
        build.append((t1 - t0) / repeats)
        solved.append((t2 - t1) / repeats)
    return 1e3 * float(np.mean(build)), 1e3 * float(np.mean(solved))


def memory(args) -> list[dict]:
    rows = []
    for n in args.runs:
        out = f"/tmp/rvdjax-memory-study-{n}"
        subprocess.run(["rm", "-rf", out], check=True)
        initial = ["--initial", args.initial] if args.initial != "nominal" else []
        vary = ["--vary", "x0=*normal(1,0.02)"] if args.initial == "nominal" else []
        cmd = [
            sys.executable, "-m", "rvdjax.cli", "study", "montecarlo", args.mem_scenario,
            "--runs", str(n), "--n-steps", str(args.mem_steps), *vary, *initial,
            "--out", out, "--json", "--quiet",
        ]  # fmt: skip
        r = subprocess.run(cmd, capture_output=True, text=True, check=True)
        s = json.loads(r.stdout)
        rows.append(
            {
                "runs": n,
                "scenario": args.mem_scenario,
                "n_steps": args.mem_steps,
                "seconds": s["seconds"],
                "runs_per_s": s["runs_per_s"],
                "outside_device_share": s["outside_device_share"],
                "compile_s": s["compile_s"],
                "outside_device_share_flying": s["outside_device_share_flying"],
                "peak_memory_mb": s["peak_memory_mb"],
                "engine": s["engine"][0],
            }
        )
        print(rows[-1], file=sys.stderr)
    return rows


def refresh(args) -> list[dict]:
    from rvdjax.bench import perturbed_states
    from rvdjax.loop.engine import EngineConfig, arrays_source, compile_engine, run_batch
    from rvdjax.scenarios import FlightOptions, get_scenario

    rows = []
    for name in args.scenarios.split(","):
        sc = get_scenario(name)
        flight = sc.flight(FlightOptions())
        params, x0, loop = flight.params, flight.x0, flight.loop
        sp = sc.solver_params()
        source = arrays_source(perturbed_states(x0, args.batch_runs))
        configs = {
            mode: EngineConfig(slots=args.slots, chunk=32, refresh=mode)
            for mode in ("masked", "compacted")
        }
        for cfg in configs.values():
            compile_engine(loop, source, params, sp, cfg)
        rates = {mode: [] for mode in configs}
        bits = None
        for _ in range(args.repeats):
            for mode, cfg in configs.items():
                out = run_batch(loop, source, args.batch_runs, params, sp, cfg)
                rates[mode].append(args.batch_runs / out["seconds"])
                dv = np.asarray(out["metrics"].delta_v_m_s)
                bits = dv if bits is None else bits
                assert np.array_equal(dv, bits), "the refreshes flew different bits"
        for mode, r in rates.items():
            rows.append(
                {
                    "scenario": name,
                    "refresh": mode,
                    "slots": args.slots,
                    "runs": args.batch_runs,
                    "maneuvers_per_s": float(np.median(r)),
                    "all": " / ".join(f"{v:.1f}" for v in r),
                    "vs_masked": float(np.median(r) / np.median(rates["masked"])),
                }
            )
            print(rows[-1], file=sys.stderr)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("what", choices=("throughput", "memory", "refresh"))
    ap.add_argument("--scenarios", default="thesis-vbar,poseidyn-lqmpc,fastmpc-3d")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--initial", default="nominal", choices=("nominal", "paper003"))
    ap.add_argument("--scenario", default="thesis-vbar")
    ap.add_argument("--batch-runs", type=int, default=256)
    ap.add_argument("--slots", type=int, default=64)
    ap.add_argument("--single-runs", type=int, default=8)
    ap.add_argument(
        "--peers", default=None, help=f"default: {','.join(DEFAULT_PEERS)}, and hpipm if installed"
    )
    ap.add_argument("--time-limit-s", type=float, default=12000.0)
    ap.add_argument("--n-steps", type=int, default=2600)
    ap.add_argument("--runs", type=lambda t: [int(v) for v in t.split(",")], default=[1000, 100000])
    ap.add_argument("--mem-scenario", default="poseidyn-lqmpc")
    ap.add_argument("--mem-steps", type=int, default=5)
    ap.add_argument("--json", metavar="FILE")
    args = ap.parse_args()
    rows = {"throughput": throughput, "memory": memory, "refresh": refresh}[args.what](args)
    keys = list(dict.fromkeys(k for r in rows for k in r))
    print(" | ".join(keys))
    for r in rows:
        print(" | ".join(f"{r.get(k):.4g}" if isinstance(r.get(k), float) else str(r.get(k))
                         for k in keys))  # fmt: skip
    if args.json:
        from rvdjax.provenance import benchmark_block

        with open(args.json, "w") as f:
            prov = benchmark_block("sweeps/study_benchmark.py", vars(args))
            json.dump({"provenance": prov, "rows": rows}, f, indent=2)


if __name__ == "__main__":
    main()
