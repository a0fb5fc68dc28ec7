"""GPU benchmark: QPs per second and maneuvers per second on one GPU against the same
machine's CPU cores, in one run of at most 5 minutes per part, compile included.

Parts (``python sweeps/gpu_benchmark.py [qp|study|all]``, from the repository root with
``PYTHONPATH=.`` on a machine whose jax has GPU support; nothing to install):

* ``qp``: the fastmpc-3d first-step QPs (paper 000 Table 1, x0 perturbed, N = 30):
  ``jit(vmap(solve))`` per QP at B = 1, 16 384 and 65 536 (``--sizes``) in accurate and paper
  modes on the GPU, for each form of the Newton step in ``--kernels`` (default ``xla,pallas``:
  XLA's loops at every size, then the Pallas kernels at the largest, with block loads and
  stores first since they compile in seconds, then entry by entry, a compile of over a
  minute; ``pallas-block-io`` alone runs the block-I/O kernels at every size, as a fast
  form); the same QPs on the machine's CPU cores (one XLA host device per core, the batch
  split over them, chunks of 32 per core; ``--no-cpu`` leaves them out); one fastmpc-3d
  maneuver per MPC step on the GPU and on one CPU core; float32 paper mode (NONFINITE count
  and objective error against float64); compile times, XLA's planned memory per program, the
  GPU's peak memory, the kernels per solver iteration counted in the compiled GPU program,
  and each form's objective error against the first's. ``--padded-blocks`` adds each form at
  the largest batch with the block kernels' arrays padded to a power of two of entries (the
  layout until 2026-11-28), for a before/after in one run. ``--shared-model`` adds each form
  at the largest batch with one copy of the model (A, B, c, Q, R) for the whole batch, as the
  batch engine solves a Monte Carlo's MPC steps, instead of one per problem.
* ``study``: the batch engine at GPU scale (``sweeps/gpu_study_benchmark.py``).

Every row is appended to ``OUT/gpu_benchmark.jsonl`` as it is measured (so a run cut short
keeps what it measured) and the table is printed at the end. ``--smoke`` runs tiny sizes on
whatever device there is (the CPU here): the script's own test.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
import time

# One XLA host device per core for the CPU rows: set before JAX starts.
if "xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "")
        + f" --xla_force_host_platform_device_count={os.cpu_count() or 1}"
    ).strip()

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import rvdjax  # noqa: E402, F401  (float64)
from rvdjax import devices  # noqa: E402
from rvdjax.problems import fastmpc3d_first_step_batch, perturbed_x0  # noqa: E402
from rvdjax.solver import (  # noqa: E402
    SolverParams,
    SolverSettings,
    Status,
    driver,
    lanes,
    solve,
    unrolled,
)

SIZES = (1, 16384, 65536)
SMOKE_SIZES = (1, 64, 256)


class Recorder:
    """Rows appended to a JSON-lines file as they come, and kept for the table."""

    def __init__(self, path):
        self.path, self.rows = path, []

    def add(self, **row) -> dict:
        row = {k: (float(v) if isinstance(v, np.floating) else v) for k, v in row.items()}
        self.rows.append(row)
        with open(self.path, "a", encoding="utf-8") as f:
            f.write(json.dumps(row, default=str) + "\n")
        shown = {k: v for k, v in row.items() if v is not None and k != "provenance"}
        print("  " + ", ".join(f"{k}={_fmt(v)}" for k, v in shown.items()), flush=True)
        if "provenance" in row:
            from rvdjax.provenance import format_provenance

            print("  provenance: " + "; ".join(format_provenance(row["provenance"])), flush=True)
        return row


def _fmt(v):
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def _time(fn, *args, repeats=3):
    """(seconds of the fastest of ``repeats`` calls, the result)."""
    best, out = np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - t0)
    return best, out


def _planned_mb(compiled) -> float:
    try:
        m = compiled.memory_analysis()
        return (m.argument_size_in_bytes + m.output_size_in_bytes + m.temp_size_in_bytes) / 2**20
    except Exception:  # backend dependent
        return float("nan")


def _peak_mb(device) -> float:
    try:
        return device.memory_stats()["peak_bytes_in_use"] / 2**20
    except Exception:  # the CPU has no memory stats
        return float("nan")


_WHILE = re.compile(r"\swhile\(.*?condition=%?([\w.\-]+),\s*body=%?([\w.\-]+)")
_TRIP = re.compile(r'"known_trip_count":\{"n":"(\d+)"\}')
_LAUNCH = re.compile(r"\s(fusion|custom-call|copy|transpose|dynamic-update-slice)\(")
_CALLS = re.compile(
    r"(?:calls|to_apply|true_computation|false_computation)=%?([\w.\-]+)"
    r"|branch_computations=\{([^}]*)\}"
)


def _computations(hlo: str) -> tuple[dict, str]:
    comps, name, entry = {}, None, None
    for line in hlo.splitlines():
        if line and not line[0].isspace() and line.rstrip().endswith("{"):
            name = line.split()[1 if line.startswith("ENTRY") else 0].lstrip("%")
            comps[name] = []
            if line.startswith("ENTRY"):
                entry = name
        elif name is not None and line.startswith(" "):
            comps[name].append(line)
    return comps, entry


def _called(line: str) -> list[str]:
    out = []
    for one, many in _CALLS.findall(line):
        out += [one] if one else [c.strip().lstrip("%") for c in many.split(",")]
    return [c for c in out if c]


def kernels_per_iteration(hlo: str) -> dict:
    """Kernel launches per solver iteration in a compiled program's HLO text: the body of the
    largest top-level while loop (the solve loop), nested loops counted times their trip
    count where XLA knows it (else once). A launch is a fusion, a custom call (a Pallas
    kernel), or a copy, transpose or in-place update left unfused. Approximate (both
    branches of a conditional count), for comparing programs."""
    comps, entry = _computations(hlo)

    def count(comp, seen=()):
        if comp in seen or comp not in comps:
            return 0, 0
        launches = loops = 0
        for line in comps[comp]:
            w = _WHILE.search(line)
            if w:
                trip = _TRIP.search(line)
                n = int(trip.group(1)) if trip else 1
                inner, inner_loops = count(w.group(2), (*seen, comp))
                launches += n * inner + 1  # + the loop condition's check
                loops += 1 + inner_loops
                continue
            if _LAUNCH.search(line):
                launches += 1
            for c in _called(line):
                if " fusion(" not in line:  # a fusion is one launch, whatever it calls
                    a, b = count(c, (*seen, comp))
                    launches, loops = launches + a, loops + b
        return launches, loops

    def top_level(comp, seen=()):
        if comp in seen or comp not in comps:
            return []
        found = []
        for line in comps[comp]:
            w = _WHILE.search(line)
            if w:
                found.append(w.group(2))
            elif " fusion(" not in line:
                for c in _called(line):
                    found += top_level(c, (*seen, comp))
        return found

    bodies = top_level(entry) if entry else []
    if not bodies:
        return {"launches": None, "inner_loops": None}
    launches, loops = max(count(b) for b in bodies)
    return {"launches": launches, "inner_loops": loops}


def _ocps(n: int, dtype=jnp.float64):
    x0s = perturbed_x0(0, n)
    ocps = fastmpc3d_first_step_batch(x0s)
    return jax.tree.map(lambda a: a.astype(dtype) if a.dtype == jnp.float64 else a, ocps)


def _settings(mode: str, kernel: str) -> SolverSettings:
    return SolverSettings.paper(kernel=kernel) if mode == "paper" else SolverSettings(kernel=kernel)


def _solve_shared(ocp, settings: SolverSettings):
    """:func:`rvdjax.solver.solve`'s loop with the model fields (A, B, c, Q, R) passed through
    as they are (``trusted_model``), so that under ``vmap(in_axes=...)`` one model serves every
    problem unbatched, as in the batch engine."""
    params = SolverParams.for_settings(settings)
    sol, o, _ = driver._forward_state(ocp, params, None, settings, trusted_model=True)
    return driver.with_objective(o, sol)


def _shared(ocps_host):
    """(the batch with one copy of the model, vmap's in_axes for it): the fastmpc-3d QPs
    differ only in x0 and the keep-out rows linearised about it; A, B, c, Q, R are one."""
    axes = type(ocps_host)(*(None if f in driver.MODEL_FIELDS else 0 for f in ocps_host._fields))
    fields = zip(ocps_host._fields, ocps_host, strict=True)
    one = type(ocps_host)(*(a[0] if f in driver.MODEL_FIELDS else a for f, a in fields))
    return one, axes


def _gpu_row(
    rec,
    device,
    mode,
    kernel,
    n,
    ocps_host,
    dtype="float64",
    ref=None,
    label=None,
    hlo_dir=None,
    shared=False,
):
    """One jit(vmap(solve)) row on ``device``; returns the solutions (host). With ``hlo_dir``
    the compiled program's HLO text is written there; with ``shared`` one model serves the
    batch (:func:`_solve_shared`)."""
    settings = _settings(mode, kernel)
    if shared:
        ocps_host, axes = _shared(ocps_host)
        fn = jax.jit(jax.vmap(lambda o: _solve_shared(o, settings), in_axes=(axes,)))
    else:
        fn = jax.jit(jax.vmap(lambda o: solve(o, settings)))
    ocps = jax.device_put(ocps_host, device)
    t0 = time.perf_counter()
    compiled = fn.lower(ocps).compile()
    compile_s = time.perf_counter() - t0
    sec, sol = _time(compiled, ocps)
    status = np.asarray(sol.status)
    row = dict(
        part="qp",
        device=devices.describe(device),
        kernel=label or kernel,
        mode=mode,
        dtype=dtype,
        batch=n,
        us_per_qp=1e6 * sec / n,
        qps_per_s=n / sec,
        iterations=float(np.mean(np.asarray(sol.iterations))),
        nonfinite=int(np.sum(status == Status.NONFINITE)),
        converged=int(np.sum(status == Status.CONVERGED)),
        compile_s=compile_s,
        planned_mb=_planned_mb(compiled),
        peak_mb=_peak_mb(device),
    )
    if device.platform != "cpu" or hlo_dir:
        text = compiled.as_text()
        row.update(kernels_per_iteration(text))
        if hlo_dir:
            name = re.sub(r"[^\w.-]+", "_", f"hlo_{label or kernel}_{mode}_{n}.txt")
            with open(os.path.join(hlo_dir, name), "w", encoding="utf-8") as f:
                f.write(text)
    if ref is not None:
        J, J_ref = np.asarray(sol.objective, float), np.asarray(ref.objective, float)
        ok = np.isfinite(J) & np.isfinite(J_ref)
        row["max_rel_objective_error"] = float(
            np.max(np.abs(J[ok] - J_ref[ok]) / np.abs(J_ref[ok]), initial=0.0)
        )
    rec.add(**row)
    return jax.device_get(sol)


def _cpu_row(rec, mode, n, ocps_host, chunk=32):
    """The same QPs on every CPU core: the batch split over the host devices (shard_map),
    each solving chunks of ``chunk`` (the CPU's fast path, rvdjax.solver.solve_batch)."""
    from jax.sharding import Mesh, NamedSharding
    from jax.sharding import PartitionSpec as P

    from rvdjax.solver import solve_batch

    cpus = jax.devices("cpu")
    D = max(d for d in range(1, len(cpus) + 1) if n % d == 0)
    mesh = Mesh(np.asarray(cpus[:D]), ("b",))
    settings = _settings(mode, "xla")

    def local(ocps):
        return solve_batch(ocps, settings, chunk=min(chunk, n // D))

    fn = jax.jit(
        jax.shard_map(local, mesh=mesh, in_specs=P("b"), out_specs=P("b"), check_vma=False)
    )
    ocps = jax.device_put(ocps_host, NamedSharding(mesh, P("b")))
    t0 = time.perf_counter()
    compiled = fn.lower(ocps).compile()
    compile_s = time.perf_counter() - t0
    sec, sol = _time(compiled, ocps)
    rec.add(
        part="qp",
        device=f"cpu x {D} cores",
        kernel="xla",
        mode=mode,
        dtype="float64",
        batch=n,
        us_per_qp=1e6 * sec / n,
        qps_per_s=n / sec,
        iterations=float(np.mean(np.asarray(sol.iterations))),
        nonfinite=int(np.sum(np.asarray(sol.status) == Status.NONFINITE)),
        converged=int(np.sum(np.asarray(sol.status) == Status.CONVERGED)),
        compile_s=compile_s,
        planned_mb=_planned_mb(compiled),
        peak_mb=float("nan"),
    )


def _maneuver_row(rec, device, kernel="auto"):
    """One fastmpc-3d maneuver (rvdjax run's closed loop) per MPC step on ``device``."""
    from rvdjax.loop import fly
    from rvdjax.scenarios import FlightOptions, get_scenario

    sc = get_scenario("fastmpc-3d")
    flight = sc.flight(FlightOptions(), settings=sc.settings("accurate", kernel=kernel))
    params, x0, loop = flight.params, flight.x0, flight.loop
    with jax.default_device(device):
        f = jax.jit(lambda p, x: fly(loop, p, x)[1])
        t0 = time.perf_counter()
        m = jax.block_until_ready(f(params, x0))
        compile_s = time.perf_counter() - t0
        sec, m = _time(f, params, x0, repeats=2)
    steps = int(m.steps)
    rec.add(
        part="maneuver",
        device=devices.describe(device),
        kernel=kernel,
        mode="accurate",
        scenario="fastmpc-3d",
        ms_per_step=1e3 * sec / steps,
        steps=steps,
        effort_l1_N_s=float(m.effort_l1_N_s),
        compile_s=compile_s,
    )


def qp_part(
    rec,
    budget_s: float,
    smoke: bool,
    kernels=("xla", "pallas"),
    sizes=None,
    unrolls=(),
    cpu=True,
    hlo_dir=None,
    padded=False,
    shared=False,
    modes=("accurate", "paper"),
) -> None:
    t_start = time.perf_counter()
    sizes = sizes or (SMOKE_SIZES if smoke else SIZES)
    accel = [d for d in jax.devices() if d.platform != "cpu"]
    gpu = accel[0] if accel else jax.devices("cpu")[0]
    if not accel:
        print("no GPU: the 'gpu' rows run on the CPU (a smoke test of the script)", flush=True)
    host = {n: jax.device_get(_ocps(n)) for n in sizes}

    def left():
        return budget_s - (time.perf_counter() - t_start)

    # In priority order: each kernel at the largest batch first. The Pallas kernels only when
    # asked for, last: on an H100 their Triton compile did not finish in 165 s (2026-11-26),
    # a compile no budget bounds.
    fast = [k for k in kernels if k != "pallas"]
    plan = [("gpu", m, k, n) for m in modes for n in reversed(sizes) for k in fast]
    plan += [("unroll", u, sizes[-1]) for u in unrolls]
    if padded:  # the block kernels' arrays padded to a power of two of entries, as until 11-28
        plan += [("padded", m, k, sizes[-1]) for m in modes for k in fast]
    if shared:  # one model for the batch (the engine's case): model reads leave the traffic
        plan += [("shared", m, k, sizes[-1]) for m in modes for k in fast]
    if cpu:
        plan += [("cpu", m, "xla", n) for m in modes for n in sizes[1:]]
    if "pallas" in kernels:  # accurate mode first: the default; block I/O first (compiles fast)
        plan += [("blockio", m, sizes[-1]) for m in modes]
        plan += [("gpu", m, "pallas", sizes[-1]) for m in modes]
    plan += [("maneuver", gpu, k) for k in fast]
    if cpu:
        plan += [("maneuver", "cpu", "auto")]
    plan += [("f32", "paper", k, sizes[-1]) for k in fast[:1] if "paper" in modes]
    if "pallas" in kernels:
        # the kernels' launch configuration (rvdjax.solver.lanes.KernelConfig), with block
        # I/O: compiles of seconds
        plan += [("tile", b, w, sizes[-1]) for b, w in ((64, 2), (256, 8), (128, 2))]
    refs = {}
    for item in plan:
        if left() < 20:
            print(f"time budget reached: skipped {item}", flush=True)
            continue
        try:
            if item[0] == "gpu":
                _, mode, kernel, n = item
                dump = hlo_dir if (mode, n) == ("accurate", sizes[-1]) else None
                ref = refs.get((mode, n))
                sol = _gpu_row(rec, gpu, mode, kernel, n, host[n], ref=ref, hlo_dir=dump)
                refs.setdefault((mode, n), sol)
            elif item[0] == "blockio":
                _, mode, n = item
                ref = refs.get((mode, n))
                _gpu_row(rec, gpu, mode, "pallas-block-io", n, host[n], ref=ref)
            elif item[0] == "unroll":
                _, u, n = item
                with unrolled.configured(unroll=u):
                    label = f"unrolled, {u} stages a trip"
                    _gpu_row(rec, gpu, "accurate", "unrolled", n, host[n], label=label)
            elif item[0] == "padded":
                _, mode, kernel, n = item
                with lanes.configured(padded_blocks=True):
                    label = f"{kernel}, padded blocks"
                    _gpu_row(
                        rec, gpu, mode, kernel, n, host[n], ref=refs.get((mode, n)), label=label
                    )
            elif item[0] == "shared":
                _, mode, kernel, n = item
                label = f"{kernel}, shared model"
                ref = refs.get((mode, n))
                _gpu_row(rec, gpu, mode, kernel, n, host[n], ref=ref, label=label, shared=True)
            elif item[0] == "cpu":
                _cpu_row(rec, item[1], item[3], host[item[3]])
            elif item[0] == "tile":
                _, block, warps, n = item
                with lanes.configured(block=block, num_warps=warps):
                    label = f"pallas-block-io, {block} problems, {warps} warps"
                    _gpu_row(rec, gpu, "accurate", "pallas-block-io", n, host[n], label=label)
            elif item[0] == "f32":
                _, mode, kernel, n = item
                h32 = jax.tree.map(
                    lambda a: a.astype(np.float32) if a.dtype == np.float64 else a, host[n]
                )
                _gpu_row(rec, gpu, mode, kernel, n, h32, "float32", refs.get((mode, n)))
            else:
                dev = jax.devices("cpu")[0] if item[1] == "cpu" else item[1]
                _maneuver_row(rec, dev, item[2])
        except Exception as err:  # a failed row is a result too: say it and go on
            rec.add(part="qp", error=f"{item}: {type(err).__name__}: {err}"[:500])


def format_table(rows) -> str:
    keys = [
        ("device", "{}"),
        ("kernel", "{}"),
        ("mode", "{}"),
        ("dtype", "{}"),
        ("batch", "{}"),
        ("us_per_qp", "{:.3g}"),
        ("qps_per_s", "{:.4g}"),
        ("iterations", "{:.3g}"),
        ("nonfinite", "{}"),
        ("launches", "{}"),
        ("compile_s", "{:.1f}"),
        ("planned_mb", "{:.0f}"),
        ("peak_mb", "{:.0f}"),
        ("max_rel_objective_error", "{:.1e}"),
    ]
    qp = [r for r in rows if r.get("part") == "qp" and "error" not in r]
    out = ["| " + " | ".join(k for k, _ in keys) + " |", "|" + " --- |" * len(keys)]
    for r in qp:
        cells = []
        for k, f in keys:
            v = r.get(k)
            cells.append("" if v is None or (isinstance(v, float) and np.isnan(v)) else f.format(v))
        out.append("| " + " | ".join(cells) + " |")
    for r in rows:
        if r.get("part") == "maneuver":
            out.append(
                f"one fastmpc-3d maneuver on {r['device']} ({r['kernel']}): "
                f"{r['ms_per_step']:.3g} ms per MPC "
                f"step ({r['steps']} steps, compile {r['compile_s']:.1f} s)"
            )
        if "error" in r:
            out.append(f"error: {r['error']}")
    return "\n".join(out)


def _positive_ints(text: str, name: str):
    """Comma-separated integers >= 1, or False after one line naming ``name``."""
    try:
        values = tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        values = ()
    if not values or min(values) < 1:
        print(f"{name} must be integers >= 1, comma-separated, got {text!r}")
        return False
    return values


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("part", nargs="?", default="all", choices=("qp", "study", "all"))
    ap.add_argument("--out", default="results/gpu", help="directory for gpu_benchmark.jsonl")
    ap.add_argument("--budget-s", type=float, default=None, help="seconds per part (290)")
    ap.add_argument("--smoke", action="store_true", help="tiny sizes: test the script")
    ap.add_argument(
        "--kernels",
        default="xla,pallas",
        help="Newton-step forms: auto, xla, unrolled, pallas (block I/O, then entry-wise, at"
        " the largest batch), pallas-block-io, pallas-block-factor, pallas-block-fused,"
        " pallas-block-rows, pallas-rows (at every batch)",
    )
    ap.add_argument("--sizes", default=None, help="batch sizes, comma-separated (1,16384,65536)")
    ap.add_argument("--unrolls", default="", help="stages a loop trip for extra unrolled rows")
    ap.add_argument("--no-cpu", action="store_true", help="leave out the CPU cores' rows")
    ap.add_argument("--hlo", action="store_true", help="write the largest batch's HLO to --out")
    ap.add_argument(
        "--padded-blocks",
        action="store_true",
        help="also each form at the largest batch with the block kernels' arrays padded to a"
        " power of two of entries (the layout until 2026-11-28)",
    )
    ap.add_argument(
        "--shared-model",
        action="store_true",
        help="also each form at the largest batch with one model (A, B, c, Q, R) for every QP",
    )
    ap.add_argument(
        "--modes",
        default="accurate,paper",
        help="the solver's modes of the QP rows, comma-separated (accurate,paper)",
    )
    args = ap.parse_args(argv)
    modes = tuple(m for m in args.modes.split(",") if m)
    if not modes or set(modes) - {"accurate", "paper"}:
        print(f"--modes: accurate and/or paper, comma-separated; got {args.modes!r}")
        return 2
    kernels = tuple(k for k in args.kernels.split(",") if k)
    from rvdjax.solver.types import KERNELS

    forms = tuple(k for k in KERNELS if k != "pallas-fused")  # its compile takes minutes
    bad = set(kernels) - set(forms)
    if bad:
        print(f"--kernels: unknown {', '.join(sorted(bad))}; choose from {', '.join(forms)}")
        return 2
    sizes = _positive_ints(args.sizes, "--sizes") if args.sizes else None
    unrolls = _positive_ints(args.unrolls, "--unrolls") if args.unrolls else ()
    if sizes is False or unrolls is False:
        return 2
    if args.budget_s is not None and not args.budget_s > 0:
        print(f"--budget-s must be > 0 seconds, got {args.budget_s}")
        return 2
    budget = args.budget_s or (60.0 if args.smoke else 290.0)
    from rvdjax.outputs import check_dir

    check_dir(args.out, "--out")
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, "gpu_benchmark.jsonl")
    rec = Recorder(path)
    from rvdjax.bench import machine_info
    from rvdjax.provenance import benchmark_block

    rec.add(
        part="machine",
        machine=machine_info(),
        devices=[str(d) for d in jax.devices()],
        provenance=benchmark_block("sweeps/gpu_benchmark.py", vars(args)),
    )
    if args.part in ("qp", "all"):
        qp_part(
            rec,
            budget,
            args.smoke,
            kernels,
            sizes,
            unrolls,
            cpu=not args.no_cpu,
            hlo_dir=args.out if args.hlo else None,
            padded=args.padded_blocks,
            shared=args.shared_model,
            modes=modes,
        )
    if args.part in ("study", "all"):
        sys.path.insert(0, os.path.dirname(__file__))
        import gpu_study_benchmark

        study_args = ["--out", args.out, "--budget-s", str(budget)]
        gpu_study_benchmark.main(study_args + (["--smoke"] if args.smoke else []))
    print(format_table(rec.rows))
    print(f"rows: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
