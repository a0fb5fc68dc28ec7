"""Where a device's time goes: its kernels in a ``jax.profiler`` trace, summed by name and
by source line.

    PYTHONPATH=. python sweeps/gpu_profile.py qp [--batch 65536] [--mode accurate]
        [--kernel auto] [--shared-model] [--top 25] [--hlo] [--out results/gpu-profile]
    PYTHONPATH=. python sweeps/gpu_profile.py engine [--scenario fastmpc-3d] [--slots 32768]
        [--seconds 3] [--kernel auto] [--top 25] [--out results/gpu-profile]
    taskset -c 0 python sweeps/gpu_profile.py engine --scenario thesis-vbar --seconds 4  # a CPU

``qp``: one ``jit(vmap(solve))`` call on the fastmpc-3d first-step QPs (as
``sweeps/gpu_benchmark.py``), compiled and run once before the traced call. ``--shared-model``: one
(A, B) for the whole batch, as the engine's slots of most scenarios share it. ``engine``: the
batch engine (``rvdjax bench --closed-loop``'s initial states, the device's engine settings;
32 768 slots on a GPU, 64 on a CPU unless ``--slots``) compiled, then flown for ``--seconds``
under the trace. On an H100 (jax 0.11.2, 2026-11-27)
the engine's first segment failed under the trace with ``CUDA_ERROR_LAUNCH_FAILED`` (XLA's
loops and the kernels alike; without the profiler it flies): JAX's CUPTI tracing is known to
leave the CUDA context broken on H100s (jax-ml/jax issue 40260).

Each device kernel of the trace (the planes ``/device:*``; on a CPU-only machine the host's
XLA thunks instead, whose nested time a ``while``, ``conditional`` or ``call`` thunk leaves
to the thunks it runs) is summed by name: calls, own and mean time, share of the kernels'
total. A kernel is matched to the HLO instruction of the compiled
program with the same name (XLA names a GPU kernel after its fusion), whose ``op_name``
(the jax function that made it) and source line (from the metadata, or from its stack frame
in the tables XLA prints after the module) are printed, so a fusion's time points at
the code; a second table sums the kernels' time by that line. Triton kernels (the solver's
Pallas kernels) are named after their ``pallas_call``.
The rows go to ``OUT/gpu_profile.jsonl`` and the trace stays in ``OUT/trace`` (TensorBoard
or Perfetto can open it); ``--hlo`` also writes the compiled program. One call; the whole
run takes under two minutes on one H100. On the CPU, a run of ``--seconds`` s traced is
slower than without the trace (some 10-20 % on the engine: each of its tens of thousands of
thunk calls a second is recorded), most for the smallest thunks.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import re
import shutil
import sys
import time

import jax
import numpy as np

import rvdjax  # noqa: F401  (float64)

_INSTR = re.compile(r"^\s*(?:ROOT\s+)?%?([\w.\-]+)\s*=.*?metadata=\{([^}]*)\}")
_META = re.compile(r'(op_name|source_file|source_line|stack_frame_id)=("[^"]*"|\d+)')


_TABLE_ROW = re.compile(r"^(\d+) (?:\"(.*)\"|\{(.*)\})\s*$")
_FIELD = re.compile(r"(\w+)=(\d+)")
_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _frame_tables(hlo: str) -> dict:
    """The tables XLA prints after a module (FileNames, FileLocations, StackFrames): jax 0.10
    puts a ``stack_frame_id`` in an instruction's metadata instead of its source file and line.
    Returns {table: {id: value}} (a file's name; a location's and a frame's fields)."""
    tables: dict = {}
    current = None
    for line in hlo.splitlines():
        s = line.strip()
        if s in ("FileNames", "FunctionNames", "FileLocations", "StackFrames"):
            current = tables.setdefault(s, {})
            continue
        m = _TABLE_ROW.match(s) if current is not None else None
        if not m:
            current = None if s else current
            continue
        current[int(m.group(1))] = (
            m.group(2) if m.group(2) is not None else dict(_FIELD.findall(m.group(3)))
        )
    return tables


def _frame_source(tables: dict, frame: int) -> str:
    """file:line of the innermost frame of ``frame``'s stack outside jax's own code (the
    repository's path where the file is in it); "" where the tables do not have it."""
    files, locs, frames = (tables.get(k, {}) for k in ("FileNames", "FileLocations", "StackFrames"))
    seen = set()
    while frame in frames and frame not in seen:
        seen.add(frame)
        loc = locs.get(int(frames[frame].get("file_location_id", 0)), {})
        path = files.get(int(loc.get("file_name_id", 0)), "")
        if path and "site-packages" not in path and f"{os.sep}jax{os.sep}" not in path:
            if path.startswith(_ROOT + os.sep):
                path = os.path.relpath(path, _ROOT)
            return f"{path}:{loc.get('line', '?')}"
        frame = int(frames[frame].get("parent_frame_id", frame))  # a root is its own parent
    return ""


def hlo_sources(hlo: str) -> dict:
    """Instruction name -> "op_name (file:line)" from a compiled program's HLO text (the line
    from the metadata's source file and line, or from its stack frame: :func:`_frame_source`);
    names also under the forms GPU kernels take ('.' and '-' as '_')."""
    out = {}
    tables = _frame_tables(hlo)
    for line in hlo.splitlines():
        m = _INSTR.match(line)
        if not m:
            continue
        meta = {k: v.strip('"') for k, v in _META.findall(m.group(2))}
        if "op_name" not in meta:
            continue
        where = os.path.basename(meta.get("source_file", ""))
        where = f"{where}:{meta['source_line']}" if where else ""
        if not where and "stack_frame_id" in meta:
            where = _frame_source(tables, int(meta["stack_frame_id"]))
        src = meta["op_name"] + (f" ({where})" if where else "")
        name = m.group(1)
        out[name] = src
        out.setdefault(re.sub(r"[.\-]", "_", name), src)
    return out


def source_line(source: str | None) -> str:
    """The "file:line" of a :func:`hlo_sources` value ("?" where it has none)."""
    m = re.search(r"\(([^()]+:\d+)\)$", source or "")
    return m.group(1) if m else "?"


def kernel_times(trace_dir: str) -> tuple[list[dict], str]:
    """Device kernels summed by name from the newest ``*.xplane.pb`` under ``trace_dir``:
    [{name, calls, total_ms, self_ms, mean_us}], largest ``self_ms`` first, and the planes
    read. On a CPU-only machine the kernels are the host's XLA thunks, which nest (a ``while``,
    a ``conditional`` or a ``call`` runs the thunks of its body): ``self_ms`` leaves out the
    time of the thunks an event contains, so the rows add up to the time traced; on a GPU it
    is ``total_ms``."""
    from jax.profiler import ProfileData

    paths = sorted(glob.glob(os.path.join(trace_dir, "**", "*.xplane.pb"), recursive=True))
    if not paths:
        raise FileNotFoundError(f"no .xplane.pb under {trace_dir}")
    data = ProfileData.from_file(paths[-1])
    planes = [p for p in data.planes if p.name.startswith("/device:")]
    host_only = not planes
    if host_only:  # a CPU-only machine: the XLA thunks on the host's executor threads
        planes = [p for p in data.planes if p.name == "/host:CPU"]
    sums: dict[str, list] = {}
    for plane in planes:
        lines = list(plane.lines)
        if host_only:
            lines = [ln for ln in lines if ln.name.startswith("tf_XLA")]
        elif any(ln.name.startswith("Stream") for ln in lines):
            # the kernels themselves; "XLA Ops"/"XLA Modules" lines repeat them by HLO name
            lines = [ln for ln in lines if ln.name.startswith("Stream")]
        for line in lines:
            events = sorted(
                (
                    (ev.name, ev.start_ns, ev.duration_ns)
                    for ev in line.events
                    if not ev.name.endswith("(wait for completion)")  # a caller waiting
                ),
                key=lambda e: (e[1], -e[2]),
            )
            stack: list = []  # the open events containing the current one: [name, end]
            for name, start, dur in events:
                while stack and stack[-1][1] <= start:
                    stack.pop()
                s = sums.setdefault(name, [0, 0.0, 0.0])
                s[0] += 1
                s[1] += dur
                s[2] += dur
                if host_only and stack:
                    sums[stack[-1][0]][2] -= dur
                if host_only:
                    stack.append([name, start + dur])
    rows = [
        dict(name=k, calls=c, total_ms=ns / 1e6, self_ms=own / 1e6, mean_us=ns / 1e3 / c)
        for k, (c, ns, own) in sums.items()
    ]
    rows.sort(key=lambda r: -r["self_ms"])
    return rows, ", ".join(p.name for p in planes)


def by_line(rows: list[dict]) -> list[dict]:
    """The rows' ``self_ms`` summed by the source line of their ``source`` (set by
    :func:`main`): [{line, self_ms, kernels}], largest first."""
    out: dict[str, list] = {}
    for r in rows:
        s = out.setdefault(source_line(r.get("source")), [0.0, 0])
        s[0] += r["self_ms"]
        s[1] += 1
    lines = [dict(line=k, self_ms=v[0], kernels=v[1]) for k, v in out.items()]
    return sorted(lines, key=lambda r: -r["self_ms"])


def _kind(name: str) -> str:
    if name.startswith("ThunkExecutor"):  # the host's own time between a program's thunks
        return "dispatch"
    low = name.lower()
    if "triton" in low or "pallas" in low or "riccati" in low:
        return "triton"
    for k in ("fusion", "copy", "transpose", "dynamic", "reduce", "scatter", "gather", "memset"):
        if k in low:
            return k
    return "other"


def _qp(args):
    from rvdjax.problems import fastmpc3d_first_step_batch, perturbed_x0
    from rvdjax.solver import SolverSettings, solve

    settings = (SolverSettings.paper if args.mode == "paper" else SolverSettings)(
        kernel=args.kernel
    )
    ocps = jax.device_put(fastmpc3d_first_step_batch(perturbed_x0(0, args.batch)))
    axes = 0
    if args.shared_model:  # one (A, B) for the batch, as the engine's slots share it
        ocps = ocps._replace(A=ocps.A[0], B=ocps.B[0])
        axes = type(ocps)(*(None if f in ("A", "B") else 0 for f in ocps._fields))
    compiled = jax.jit(jax.vmap(lambda o: solve(o, settings), in_axes=(axes,)))
    compiled = compiled.lower(ocps).compile()
    sol = jax.block_until_ready(compiled(ocps))

    def traced():
        jax.block_until_ready(compiled(ocps))

    info = dict(
        target="qp",
        batch=args.batch,
        mode=args.mode,
        kernel=args.kernel,
        shared_model=args.shared_model,
        iterations=float(np.mean(np.asarray(sol.iterations))),
        status=np.bincount(np.asarray(sol.status).ravel()).tolist(),
        objective_finite=bool(np.all(np.isfinite(np.asarray(sol.objective)))),
    )
    return traced, compiled.as_text(), info


def _engine(args):
    from gpu_study_benchmark import _run_until  # this folder's engine driver

    from rvdjax.bench import perturbed_states
    from rvdjax.loop.engine import arrays_source, auto_config
    from rvdjax.loop.engine.stream import _compile_segment
    from rvdjax.scenarios import FlightOptions, get_scenario

    sc = get_scenario(args.scenario)
    options = FlightOptions(n_steps=40 if args.smoke else None)
    flight = sc.flight(options, settings=sc.settings(options.mode, kernel=args.kernel))
    params, x0, loop = flight.params, flight.x0, flight.loop
    sp = sc.solver_params()
    n = 3 * args.slots
    source = arrays_source(perturbed_states(x0, n))
    cfg = auto_config(slots=args.slots)
    # compiled once: the program the flight below reuses, and its HLO for the kernels' sources
    hlo = _compile_segment(loop, source, params, sp, cfg).as_text()
    done = {}

    def traced():
        deadline = time.perf_counter() + args.seconds
        done.update(_run_until(loop, source, n, params, sp, cfg, deadline, []))

    info = dict(target="engine", scenario=args.scenario, slots=cfg.n_slots, kernel=args.kernel)
    info["engine"] = cfg.describe()
    return traced, hlo, info, done


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("target", choices=("qp", "engine"))
    ap.add_argument("--batch", type=int, default=65536, help="QPs in the batch (qp)")
    ap.add_argument("--shared-model", action="store_true", help="qp: one (A, B) for all")
    ap.add_argument("--mode", choices=("accurate", "paper"), default="accurate")
    ap.add_argument("--kernel", default="auto", help="the Newton step's form (SolverSettings)")
    ap.add_argument("--scenario", default="fastmpc-3d", help="engine: the scenario")
    ap.add_argument(
        "--slots", type=int, default=None, help="engine: slots (32768 on a GPU, 64 on a CPU)"
    )
    ap.add_argument("--seconds", type=float, default=3.0, help="engine: seconds flown traced")
    ap.add_argument("--top", type=int, default=25, help="kernels printed")
    ap.add_argument("--out", default="results/gpu-profile", help="directory for the rows")
    ap.add_argument("--hlo", action="store_true", help="also write the compiled program's HLO")
    ap.add_argument("--smoke", action="store_true", help="tiny sizes: test the script")
    args = ap.parse_args(argv)
    from rvdjax.solver.riccati import KERNELS

    if args.kernel not in KERNELS:
        print(f"--kernel: must be one of {', '.join(KERNELS)}, got {args.kernel!r}")
        return 2
    if args.slots is None:
        args.slots = 64 if jax.default_backend() == "cpu" else 32768
    for name, v, lo in (
        ("--batch", args.batch, 1),
        ("--slots", args.slots, 1),
        ("--top", args.top, 1),
    ):
        if v < lo:
            print(f"{name}: must be an integer >= {lo}, got {v}")
            return 2
    if not args.seconds > 0:
        print(f"--seconds: must be > 0, got {args.seconds}")
        return 2
    from rvdjax.outputs import check_dir

    check_dir(args.out, "--out")
    os.makedirs(args.out, exist_ok=True)
    if args.smoke:
        args.batch, args.slots, args.seconds = min(args.batch, 64), min(args.slots, 32), 2.0
    done = {}
    if args.target == "qp":
        traced, hlo, info = _qp(args)
    else:
        traced, hlo, info, done = _engine(args)
    trace_dir = os.path.join(args.out, "trace")
    shutil.rmtree(trace_dir, ignore_errors=True)
    t0 = time.perf_counter()
    with jax.profiler.trace(trace_dir):
        traced()
    wall_ms = 1e3 * (time.perf_counter() - t0)
    rows, planes = kernel_times(trace_dir)
    sources = hlo_sources(hlo)
    total = sum(r["self_ms"] for r in rows) or float("nan")
    info.update(
        device=str(jax.devices()[0].device_kind),
        planes=planes,
        wall_ms=wall_ms,
        kernels_ms=total,
        launches=sum(r["calls"] for r in rows),
        runs_done=done.get("done"),
        ticks=done.get("ticks"),
        by_kind={},
    )
    if info["ticks"]:
        info["launches_per_tick"] = info["launches"] / info["ticks"]
    for r in rows:
        r["share"] = r["self_ms"] / total
        r["kind"] = _kind(r["name"])
        r["source"] = sources.get(r["name"]) or sources.get(re.sub(r"[.\-]", "_", r["name"]))
        info["by_kind"][r["kind"]] = info["by_kind"].get(r["kind"], 0.0) + r["self_ms"]
    if args.hlo:
        tag = args.scenario if args.target == "engine" else args.mode
        path = os.path.join(args.out, f"{args.target}-{tag}-{args.kernel}.hlo.txt")
        with open(path, "w", encoding="utf-8") as f:
            f.write(hlo)
    with open(os.path.join(args.out, "gpu_profile.jsonl"), "a", encoding="utf-8") as f:
        from rvdjax.provenance import benchmark_block

        prov = benchmark_block("sweeps/gpu_profile.py", vars(args))
        lines = by_line(rows)
        f.write(
            json.dumps(dict(info, top=rows[: args.top], lines=lines[: args.top], provenance=prov))
            + "\n"
        )
    print(
        f"{info['target']} on {info['device']} ({planes}): {info['launches']} kernel calls, "
        f"{total:.1f} ms in kernels, {wall_ms:.1f} ms wall traced"
    )
    if info["ticks"]:
        print(f"{info['ticks']} ticks, {info['launches_per_tick']:.0f} kernel calls a tick")
    if args.target == "qp":
        print(
            f"iterations {info['iterations']:.3f}, statuses {info['status']}, "
            f"objectives finite {info['objective_finite']}"
        )
    print("by kind: " + ", ".join(f"{k} {v:.1f} ms" for k, v in info["by_kind"].items()))
    print("| kernel | kind | calls | own ms | share | with nested ms | mean µs | source |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in rows[: args.top]:
        print(
            f"| {r['name'][:60]} | {r['kind']} | {r['calls']} | {r['self_ms']:.2f} | "
            f"{100 * r['share']:.1f} % | {r['total_ms']:.2f} | {r['mean_us']:.1f} | "
            f"{(r['source'] or '')[:90]} |"
        )
    print("| source line | own ms | share | kernels |")
    print("| --- | --- | --- | --- |")
    for r in lines[: args.top]:
        print(
            f"| {r['line']} | {r['self_ms']:.2f} | {100 * r['self_ms'] / total:.1f} % | "
            f"{r['kernels']} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
