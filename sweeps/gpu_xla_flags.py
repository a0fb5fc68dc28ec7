"""XLA's GPU options against rvdjax's latency-bound programs: the same measurements under
several ``XLA_FLAGS``, each in its own process, in one run of a few minutes.

    PYTHONPATH=. python sweeps/gpu_xla_flags.py [--variants default,while] [--out DIR]
        [--budget-s 150] [--smoke]

From the repository root on a machine whose jax has GPU support; nothing to install.

Why: on a GPU rvdjax's solves and engine ticks are bound by launch latency, not by
arithmetic or memory (docs/benchmark.md, "On a GPU"). XLA records sequences of fused kernels
into CUDA graphs ("command buffers"), but by default not ``while`` loops: every iteration of
the solver's loop (a ``lax.while_loop`` that stops when every problem has converged) and
every tick of an engine segment goes back to the host, which launches the body's kernels
again and, for a loop without a known trip count, first copies its predicate back. With
``WHILE`` and ``CONDITIONAL`` among the command-buffer types, XLA records the loop itself
(CUDA conditional graph nodes), so a whole solve or segment can run as one graph.

Each variant (``VARIANTS``, or ``NAME=FLAGS`` on the command line) runs in a fresh process
with its options added to ``XLA_FLAGS`` (XLA reads them once, at start) and measures, in
this order, each within the variant's ``--budget-s``:

1. the batch engine: ``thesis-vbar`` maneuvers/s at 4 096 slots
   (``gpu_study_benchmark.throughput``; compile apart);
2. 65 536 fastmpc-3d QPs, accurate mode, ``jit(vmap(solve))`` (``gpu_benchmark``'s QP row);
3. one fastmpc-3d QP alone;
4. one fastmpc-3d maneuver (rvdjax run's closed loop), per MPC step;
5. the 65 536 QPs in paper mode.

Every row goes to ``OUT/gpu_xla_flags.jsonl`` as it is measured; each variant's QP
objectives and iteration counts go to ``OUT/answers_<variant>.npz``, so the table can say
whether a variant computes the same bits as the first. ``--smoke`` runs tiny sizes on
whatever device there is (the CPU here, where the GPU options are parsed and ignored): the
script's own test.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np

# Added to XLA_FLAGS (XLA's default command-buffer types: FUSION, CUBLAS, CUBLASLT,
# CUSTOM_CALL, CUDNN, DYNAMIC_SLICE_FUSION; "+" adds to them).
VARIANTS = {
    "default": "",
    "while": "--xla_gpu_enable_command_buffer=+WHILE,+CONDITIONAL",
    "none": "--xla_gpu_enable_command_buffer=",
}
QP_BATCH, SMOKE_QP_BATCH = 65536, 256
SLOTS, SMOKE_SLOTS = 4096, 32
ROWS = "gpu_xla_flags.jsonl"


# ------------------------------------------------------------------------------ a variant


def child(variant: str, out: str, budget_s: float, smoke: bool) -> None:
    """One variant's measurements in this process (XLA_FLAGS already set by the parent)."""
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import gpu_benchmark
    import gpu_study_benchmark
    import jax

    from rvdjax.provenance import benchmark_block

    t_start = time.perf_counter()

    class Tagged(gpu_study_benchmark.Recorder):
        def add(self, **row):
            return super().add(variant=variant, **row)

    rec = Tagged(os.path.join(out, ROWS))
    rec.add(
        part="variant",
        xla_flags=os.environ.get("XLA_FLAGS", ""),
        devices=[str(d) for d in jax.devices()],
        provenance=benchmark_block(
            "sweeps/gpu_xla_flags.py", {"variant": variant, "budget_s": budget_s, "smoke": smoke}
        ),
    )
    accel = [d for d in jax.devices() if d.platform != "cpu"]
    gpu = accel[0] if accel else jax.devices("cpu")[0]
    n_qp = SMOKE_QP_BATCH if smoke else QP_BATCH
    slots = SMOKE_SLOTS if smoke else SLOTS
    answers = {}

    def left() -> float:
        return budget_s - (time.perf_counter() - t_start)

    def qp(mode: str, n: int) -> None:
        host = jax.device_get(gpu_benchmark._ocps(n))
        sol = gpu_benchmark._gpu_row(rec, gpu, mode, "auto", n, host)
        answers[f"{mode}_{n}_objective"] = np.asarray(sol.objective)
        answers[f"{mode}_{n}_iterations"] = np.asarray(sol.iterations)

    def engine() -> None:
        budget = min(0.45 * budget_s, left() - 10)
        rec.add(**gpu_study_benchmark.throughput("thesis-vbar", slots, budget, smoke))

    plan = [
        ("engine", engine),
        ("qp accurate", lambda: qp("accurate", n_qp)),
        ("qp alone", lambda: qp("accurate", 1)),
        ("maneuver", lambda: gpu_benchmark._maneuver_row(rec, gpu, "auto")),
        ("qp paper", lambda: qp("paper", n_qp)),
    ]
    for name, step in plan:
        if left() < 15:
            rec.add(part="skipped", what=name, reason="variant budget reached")
            continue
        try:
            step()
        except Exception as err:  # a failed measurement is a result: say it and go on
            rec.add(part="error", what=name, error=f"{type(err).__name__}: {err}"[:500])
    np.savez(os.path.join(out, f"answers_{variant}.npz"), **answers)


# ------------------------------------------------------------------------------ the table


def _same_answers(out: str, first: str, other: str) -> str:
    """'bits' when every QP answer both variants computed is equal to the bit, else the
    largest relative objective difference and the iteration counts that differ."""
    try:
        a = np.load(os.path.join(out, f"answers_{first}.npz"))
        b = np.load(os.path.join(out, f"answers_{other}.npz"))
    except OSError:
        return "n/a"
    keys = sorted(set(a.files) & set(b.files))
    if not keys:
        return "n/a"
    if all(np.array_equal(a[k], b[k]) for k in keys):
        return "bits"
    worst, its = 0.0, 0
    for k in keys:
        if k.endswith("objective"):
            x, y = a[k].astype(float), b[k].astype(float)
            ok = np.isfinite(x) & np.isfinite(y)
            worst = max(worst, float(np.max(np.abs(x[ok] - y[ok]) / np.abs(x[ok]), initial=0)))
        else:
            its += int(np.sum(a[k] != b[k]))
    return f"objective {worst:.1e}, {its} iteration counts differ"


def format_table(rows: list[dict], variants: list[str], out: str) -> str:
    big = (QP_BATCH, SMOKE_QP_BATCH)

    def pick(v, part, mode=None, batches=None):
        for r in rows:
            if r.get("variant") != v or r.get("part") != part:
                continue
            if mode and r.get("mode") != mode or batches and r.get("batch") not in batches:
                continue
            return r
        return None

    measures = [  # label, (part, mode, batches), key, scale, format
        ("thesis-vbar maneuvers/s, engine", ("throughput",), "maneuvers_per_s", 1, "{:.0f}"),
        ("  its compile, s", ("throughput",), "compile_s", 1, "{:.1f}"),
        ("µs per QP, 65 536, accurate", ("qp", "accurate", big), "us_per_qp", 1, "{:.3g}"),
        ("  its compile, s", ("qp", "accurate", big), "compile_s", 1, "{:.1f}"),
        ("ms for one QP alone, accurate", ("qp", "accurate", (1,)), "us_per_qp", 1e-3, "{:.3g}"),
        ("ms per MPC step, one maneuver", ("maneuver",), "ms_per_step", 1, "{:.3g}"),
        ("µs per QP, 65 536, paper", ("qp", "paper", big), "us_per_qp", 1, "{:.3g}"),
    ]
    lines = ["| measure | " + " | ".join(variants) + " |", "|" + " --- |" * (len(variants) + 1)]
    for label, match, key, scale, fmt in measures:
        cells = []
        for v in variants:
            r = pick(v, *match)
            val = None if r is None else r.get(key)
            cells.append("" if val is None else fmt.format(val * scale))
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    same = [_same_answers(out, variants[0], v) for v in variants]
    lines.append("| QP answers against the first variant's | " + " | ".join(same) + " |")
    for r in rows:
        if r.get("part") in ("error", "skipped", "failed"):
            why = r.get("error") or r.get("reason")
            lines.append(f"{r.get('variant')}: {r['part']} {r.get('what', '')}: {why}")
    return "\n".join(lines)


# ------------------------------------------------------------------------------- the parent


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--variants",
        default="default,while",
        help=f"names ({', '.join(VARIANTS)}) or NAME=FLAGS, comma-separated (FLAGS may not"
        " hold a comma: use ';' between command-buffer types)",
    )
    ap.add_argument("--out", default="results/gpu-xla-flags", help="directory for the rows")
    ap.add_argument("--budget-s", type=float, default=None, help="seconds a variant (150)")
    ap.add_argument("--smoke", action="store_true", help="tiny sizes: test the script")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    budget = args.budget_s or (120.0 if args.smoke else 150.0)
    if args.child:
        child(args.child, args.out, budget, args.smoke)
        return 0
    variants, flags = [], {}
    for item in (v for v in args.variants.split(",") if v):
        name, sep, value = item.partition("=")
        if not sep and name not in VARIANTS:
            print(f"--variants: unknown {name!r}; choose from {', '.join(VARIANTS)} or NAME=FLAGS")
            return 2
        variants.append(name)
        flags[name] = value.replace(";", ",") if sep else VARIANTS[name]
    if budget <= 30:
        print(f"--budget-s: must be over 30 s a variant, got {budget:g}")
        return 2
    from rvdjax.outputs import check_dir

    check_dir(args.out, "--out")
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, ROWS)
    for stale in [ROWS] + [f"answers_{v}.npz" for v in variants]:  # a fresh comparison
        if os.path.exists(os.path.join(args.out, stale)):
            os.remove(os.path.join(args.out, stale))
    base = os.environ.get("XLA_FLAGS", "")
    for name in variants:
        env = dict(os.environ, XLA_FLAGS=f"{base} {flags[name]}".strip(), PYTHONUNBUFFERED="1")
        cmd = [sys.executable, os.path.abspath(__file__), "--child", name, "--out", args.out,
               "--budget-s", str(budget)] + (["--smoke"] if args.smoke else [])  # fmt: skip
        print(f"== variant {name}: XLA_FLAGS += {flags[name]!r}", flush=True)
        t0 = time.perf_counter()
        try:
            rc = subprocess.run(cmd, env=env, timeout=budget + 90).returncode
        except subprocess.TimeoutExpired:
            rc = "timeout"
        if rc != 0:
            with open(path, "a", encoding="utf-8") as f:
                f.write(json.dumps(dict(variant=name, part="failed", error=f"exit {rc}")) + "\n")
        print(f"== variant {name}: {time.perf_counter() - t0:.0f} s, exit {rc}", flush=True)
    rows = []
    with open(path, encoding="utf-8") as f:
        rows = [json.loads(line) for line in f if line.strip()]
    print(format_table(rows, variants, args.out))
    print(f"rows: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
