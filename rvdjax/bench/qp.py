"""Side-by-side benchmark of rvdjax and peer QP solvers on the `fastmpc-3d` first-step QP.

One run solves the same batch of problems (the paper 000 Table 1 first MPC step with x0
perturbed, :func:`rvdjax.problems.fastmpc3d_first_step_batch`) with rvdjax (one jitted call;
vmapped batches; paper and accurate modes) and with Clarabel, PIQP, DAQP, OSQP and qpax, and
reports per problem: median time, solves/s, ratio to Clarabel, objective gap to a tight
Clarabel reference, constraint violation, iterations, compile time and memory. Then the
horizon scaling N = 15 .. 60.

Timing: wall clock, median over repeats, after a warm-up call (compile excluded and reported
separately). Pin the process to one core for the published figures (``rvdjax bench`` sets
XLA to one thread; run it under ``taskset -c 0``).
"""

from __future__ import annotations

import dataclasses
import resource
import statistics
import time
from collections.abc import Callable, Sequence

import jax
import numpy as np

from rvdjax.peers import PEERS, available_peers, hpipm_unavailable, qpax_batch_solver
from rvdjax.peers_host import SOLVED
from rvdjax.problems import fastmpc3d_first_step_batch, perturbed_x0
from rvdjax.qp import to_qp
from rvdjax.solver import SolverSettings, max_violation, solve, solve_batch

__all__ = ["BenchConfig", "run_benchmark", "format_table", "machine_info"]


@dataclasses.dataclass(frozen=True)
class BenchConfig:
    """What to run. Defaults reproduce the README table (a few minutes on 2 cores)."""

    batches: Sequence[int] = (64, 1024, 4096)
    horizons: Sequence[int] = (15, 30, 45, 60)
    horizon_batch: int = 256
    n_peer: int = 32  # problems per peer solver (solved one at a time)
    qpax_batch: int = 64  # qpax's dense vmapped solve slows sharply past ~64 on this CPU
    peers: Sequence[str] | None = None  # None: every installed peer
    repeats: int = 3
    seed: int = 0
    obstacles: bool = True


def _rss_mb() -> float:
    """Peak resident set size of this process so far [MB] (Linux: ru_maxrss is in kB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _compile(fn, *args):
    """(compiled executable, compile seconds, planned memory [MB]: args + outputs + temps)."""
    t0 = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    seconds = time.perf_counter() - t0
    try:
        m = compiled.memory_analysis()
        mem = (m.argument_size_in_bytes + m.output_size_in_bytes + m.temp_size_in_bytes) / 2**20
    except Exception:  # memory analysis is backend dependent
        mem = float("nan")
    return compiled, seconds, mem


def _time(call: Callable[[], object], repeats: int) -> tuple[float, float]:
    """(first-call seconds, median seconds of ``repeats`` further calls)."""
    t0 = time.perf_counter()
    jax.block_until_ready(call())
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(call())
        times.append(time.perf_counter() - t0)
    return first, statistics.median(times)


def _qp_violation(qp, z) -> float:
    """Largest row-normalised inequality violation and equality residual of a QP solution."""
    g = qp.G @ z - qp.h
    norms = np.sqrt(np.asarray(qp.G.multiply(qp.G).sum(axis=1))).ravel()
    v_ineq = np.max(np.maximum(g / np.maximum(norms, 1e-300), 0.0), initial=0.0)
    v_eq = np.max(np.abs(qp.A_eq @ z - qp.b_eq), initial=0.0)
    return float(max(v_ineq, v_eq))


def _row(
    solver,
    mode,
    batch,
    N,
    sec_per_problem,
    clarabel_ms,
    gaps,
    viol,
    iters,
    compile_s,
    mem_mb,
    note="",
):
    ms = 1e3 * sec_per_problem
    return {
        "solver": solver,
        "mode": mode,
        "batch": batch,
        "N": N,
        "ms_per_problem": ms,
        "solves_per_s": 1.0 / sec_per_problem if sec_per_problem > 0 else float("inf"),
        "ratio_to_clarabel": (clarabel_ms / ms) if clarabel_ms else float("nan"),
        "rel_objective_gap": float(np.max(np.abs(gaps))) if len(gaps) else float("nan"),
        "median_rel_objective_gap": float(np.median(gaps)) if len(gaps) else float("nan"),
        "max_violation": float(viol),
        "iterations": float(np.median(iters)) if len(iters) else float("nan"),
        "compile_s": compile_s,
        "mem_MB": mem_mb,
        "note": note,
    }


def _rvdjax_rows(
    ocps, J_ref, settings_by_mode, batches, repeats, N, clarabel_ms, progress, chunk=32
):
    rows = []
    for mode, settings in settings_by_mode.items():
        # One jitted call on one problem (no vmap).
        one = jax.tree.map(lambda a: a[0], ocps)
        f1, compile_s, mem = _compile(lambda o, s=settings: solve(o, s), one)
        _, med = _time(lambda f1=f1, one=one: f1(one), repeats=max(repeats, 10))
        sol = f1(one)
        gap = (float(sol.objective) - J_ref[0]) / abs(J_ref[0])
        viol = float(max_violation(one, sol.u, sol.x))
        rows.append(
            _row(
                "rvdjax",
                mode,
                1,
                N,
                med,
                clarabel_ms,
                [gap],
                viol,
                [int(sol.iterations)],
                compile_s,
                mem,
                note="single jitted call",
            )
        )
        progress(f"rvdjax {mode} N={N} batch=1: {1e3 * med:.3f} ms")
        for B in batches:
            b = jax.tree.map(lambda a, B=B: a[:B], ocps)
            variants = [(mode, jax.vmap(lambda o, s=settings: solve(o, s)), None)]
            if B >= 4 * chunk:
                variants.append(
                    (
                        f"{mode}/c{chunk}",
                        lambda o, s=settings: solve_batch(o, s, chunk=chunk),
                        f"solve_batch: lax.map of vmap chunks of {chunk}",
                    )
                )
            for label, fn, note in variants:
                fb, compile_s, mem = _compile(fn, b)
                _, med = _time(lambda fb=fb, b=b: fb(b), repeats)
                sol = fb(b)
                gaps = (np.asarray(sol.objective) - J_ref[:B]) / np.abs(J_ref[:B])
                viol = float(np.max(jax.vmap(max_violation)(b, sol.u, sol.x)))
                statuses = np.bincount(np.asarray(sol.status), minlength=4)
                note = note or "status counts " + "/".join(str(int(c)) for c in statuses)
                rows.append(
                    _row(
                        "rvdjax",
                        label,
                        B,
                        N,
                        med / B,
                        clarabel_ms,
                        gaps,
                        viol,
                        np.asarray(sol.iterations),
                        compile_s,
                        mem,
                        note=note,
                    )
                )
                progress(f"rvdjax {label} N={N} batch={B}: {1e3 * med / B:.3f} ms/problem")
    return rows


def _peer_rows(qps, J_ref, names, N, progress):
    rows = []
    clarabel_ms = None
    for name in names:
        if name == "qpax":
            continue
        fn = PEERS[name]
        kwargs = {"mode": "benchmark"} if name == "clarabel" else {}
        rss0 = _rss_mb()
        results = [fn(qp, **kwargs) for qp in qps]
        times = [r.solve_ms for r in results]
        med_ms = statistics.median(times)
        if name == "clarabel":
            clarabel_ms = med_ms
        gaps = [(r.objective - J) / abs(J) for r, J in zip(results, J_ref, strict=False)]
        viol = max(_qp_violation(qp, r.z) for qp, r in zip(qps, results, strict=False))
        bad = sum(r.status not in SOLVED for r in results)
        rows.append(
            _row(
                name,
                "default",
                1,
                N,
                med_ms / 1e3,
                clarabel_ms,
                gaps,
                viol,
                [r.iterations for r in results],
                0.0,
                max(_rss_mb() - rss0, 0.0),
                note=f"{bad} not solved" if bad else "",
            )
        )
        progress(f"{name} N={N}: {med_ms:.3f} ms")
    for row in rows:
        row["ratio_to_clarabel"] = clarabel_ms / row["ms_per_problem"] if clarabel_ms else np.nan
    return rows, clarabel_ms


def _qpax_rows(qps, J_ref, N, clarabel_ms, repeats, batch, progress):
    rows = []
    batch = min(batch, len(qps))
    qb = qpax_batch_solver(qps[:batch])
    first, med = _time(qb, repeats)
    z, converged, iters = qb()
    z = np.asarray(z)
    from rvdjax.qp import qp_objective

    gaps = [(qp_objective(qp, z[i]) - J_ref[i]) / abs(J_ref[i]) for i, qp in enumerate(qps[:batch])]
    viol = max(_qp_violation(qp, z[i]) for i, qp in enumerate(qps[:batch]))
    bad = int(np.sum(~np.asarray(converged, dtype=bool)))
    rows.append(
        _row(
            "qpax",
            "jit+vmap",
            batch,
            N,
            med / batch,
            clarabel_ms,
            gaps,
            viol,
            np.asarray(iters),
            first - med,
            float("nan"),
            note=(f"{bad} not converged; " if bad else "") + "Ruiz-scaled",
        )
    )
    progress(f"qpax N={N} batch={batch}: {1e3 * med / batch:.3f} ms/problem")
    return rows


def run_benchmark(config: BenchConfig = BenchConfig(), progress=print) -> list[dict]:
    """Run the benchmark and return one dict per table row (see ``format_table``)."""
    names = list(config.peers) if config.peers is not None else available_peers()
    missing = [p for p in names if p not in available_peers()]
    for p in missing:
        why = hpipm_unavailable() if p == "hpipm" else "pip install 'rvdjax[peers]'"
        progress(f"note: peer {p!r} is not installed; skipped ({why})")
    names = [p for p in names if p not in missing]
    if "clarabel" not in names:
        names.insert(0, "clarabel")
    settings_by_mode = {"accurate": SolverSettings(), "paper": SolverSettings.paper()}

    rows: list[dict] = []
    horizons = sorted(set(config.horizons) | {30})
    for N in horizons:
        main = N == 30
        B_max = max(config.batches) if main else config.horizon_batch
        n_ref = max(B_max, config.n_peer) if main else max(config.horizon_batch, 8)
        x0s = perturbed_x0(config.seed, n_ref)
        ocps = fastmpc3d_first_step_batch(x0s, obstacles=config.obstacles, N=N)
        # Reference optimum of every problem from a tight Clarabel solve of the hard QP. The
        # soft rows' penalty (rho = 1e8) exceeds every multiplier, so soft == hard optimum.
        n_check = n_ref if main else config.horizon_batch
        qps = [to_qp(jax.tree.map(lambda a, i=i: a[i], ocps), soft=False) for i in range(n_check)]
        progress(f"N={N}: computing {n_check} Clarabel reference solutions ...")
        J_ref = np.array([PEERS["clarabel"](qp).objective for qp in qps])

        peer_names = names if main else ["clarabel"]
        peer_rows, clarabel_ms = _peer_rows(qps[: config.n_peer], J_ref, peer_names, N, progress)
        rows += peer_rows
        batches = config.batches if main else [config.horizon_batch]
        rows += _rvdjax_rows(
            ocps, J_ref, settings_by_mode, batches, config.repeats, N, clarabel_ms, progress
        )
        if main and "qpax" in names:
            rows += _qpax_rows(
                qps, J_ref, N, clarabel_ms, config.repeats, config.qpax_batch, progress
            )
    return rows


def format_table(rows: list[dict]) -> str:
    """Render benchmark rows as a fixed-width text table."""
    cols = [
        ("solver", "{:<9}"),
        ("mode", "{:<12}"),
        ("N", "{:>3}"),
        ("batch", "{:>5}"),
        ("ms_per_problem", "{:>9.4f}"),
        ("solves_per_s", "{:>10.0f}"),
        ("ratio_to_clarabel", "{:>8.2f}"),
        ("rel_objective_gap", "{:>9.1e}"),
        ("max_violation", "{:>8.1e}"),
        ("iterations", "{:>6.1f}"),
        ("compile_s", "{:>7.2f}"),
        ("mem_MB", "{:>7.1f}"),
        ("note", "{}"),
    ]
    heads = {
        "ms_per_problem": "ms/prob",
        "solves_per_s": "solves/s",
        "ratio_to_clarabel": "xClarabel",
        "rel_objective_gap": "max gap",
        "max_violation": "max viol",
        "iterations": "iters",
        "compile_s": "compile",
        "mem_MB": "mem MB",
    }
    widths = []
    for key, fmt in cols:
        sample = fmt.format(rows[0][key]) if rows else key
        widths.append(max(len(sample), len(heads.get(key, key))))
    out = [
        "  ".join(
            heads.get(k, k).rjust(w)
            if k not in ("solver", "mode", "note")
            else heads.get(k, k).ljust(w)
            for (k, _), w in zip(cols, widths, strict=True)
        )
    ]
    for r in rows:
        cells = []
        for (k, fmt), w in zip(cols, widths, strict=True):
            cell = fmt.format(r[k]) if not (isinstance(r[k], float) and np.isnan(r[k])) else "-"
            cells.append(cell.ljust(w) if k in ("solver", "mode", "note") else cell.rjust(w))
        out.append("  ".join(cells))
    return "\n".join(out)


def machine_info() -> str:
    import os
    import platform

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    from rvdjax.devices import current

    return (
        f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, "
        f"jax {jax.__version__}, device {current()}"
    )


#: One scenario per family: the default of ``rvdjax bench --closed-loop``.
