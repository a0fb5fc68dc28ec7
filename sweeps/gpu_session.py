"""One GPU session's measurements in one command, in under 5 minutes, compile included: the
QPs with today's Newton step and with the form last timed on a GPU, one maneuver alone on the
GPU, and the batch engine's maneuvers per second.

A lent GPU has about 15 minutes of device time in all, its start included; this runs the
GPU figures the targets need (docs/benchmark.md), each step in its own process under its
own time limit, and writes every step's output as it goes (``OUT/<step>.log``, the steps'
JSON lines under ``OUT/<step>/``, and ``OUT/gpu_session.jsonl``: a row a step with its exit
status and seconds). From the repository root, on a machine whose jax has GPU support (nothing to
install):

    PYTHONPATH=. python sweeps/gpu_session.py --out results/gpu-session
    python sweeps/gpu_session.py --smoke     # tiny sizes on any device: the script's test
    python sweeps/gpu_session.py --dry-run   # the commands it would run

The steps (accurate mode, the GPU's rows only):

- ``qp``: ``sweeps/gpu_benchmark.py qp`` with ``kernel="auto"`` (on a CUDA GPU, today's
  kernels) at B = 65 536, 16 384 and 1, then 65 536 QPs with one model for the batch (the
  engine's case, the one ``sweeps/gpu_traffic.py --shared-model`` counts), then one
  fastmpc-3d maneuver alone (ms per MPC step);
- ``qp-before``: the same with ``"pallas-block-factor"`` (the default when a GPU last timed
  the kernels, 2026-11-27) at B = 65 536, in a process of its own;
- ``engine``: ``sweeps/gpu_study_benchmark.py --parts throughput``, thesis-vbar at 4 096 and
  32 768 slots.

Each benchmark skips what its budget no longer covers, in that order.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)


def steps(out: str, smoke: bool) -> list[tuple[str, list[str], int]]:
    """(name, argv after the interpreter, time limit in seconds) of each step, in order."""
    qp = [os.path.join(HERE, "gpu_benchmark.py"), "qp", "--out", os.path.join(out, "qp")]
    qp_before = qp[:-1] + [os.path.join(out, "qp-before")]
    engine = [os.path.join(HERE, "gpu_study_benchmark.py"), "--out", os.path.join(out, "engine")]
    if smoke:
        return [
            ("qp", qp + ["--smoke", "--kernels", "auto", "--no-cpu"], 240),
            ("engine", engine + ["--smoke", "--parts", "throughput"], 240),
        ]
    accurate = ["--modes", "accurate", "--no-cpu", "--shared-model"]
    return [
        (  # today's kernels: 65 536, 16 384 and one QP, one model for the batch, one maneuver
            "qp",
            qp + ["--kernels", "auto", "--sizes", "1,16384,65536", "--budget-s", "120"] + accurate,
            135,
        ),
        (  # the form the GPU last timed, at the largest batch, in a process of its own
            "qp-before",
            qp_before
            + ["--kernels", "pallas-block-factor", "--sizes", "65536", "--budget-s", "45"]
            + accurate,
            60,
        ),
        (
            "engine",
            engine
            + ["--parts", "throughput", "--scenarios", "thesis-vbar", "--slots", "4096,32768"]
            + ["--budget-s", "85"],
            95,
        ),
    ]


def run_step(name: str, argv: list[str], limit_s: int, out: str) -> dict:
    """Run one step in its own process, its output to ``OUT/<name>.log``; a row."""
    # the steps import rvdjax from this checkout, installed or not
    path = os.pathsep.join(p for p in (ROOT, os.environ.get("PYTHONPATH", "")) if p)
    env = dict(os.environ, PYTHONPATH=path)
    t0 = time.perf_counter()
    with open(os.path.join(out, f"{name}.log"), "w") as log:
        try:
            rc = subprocess.run(
                [sys.executable, *argv],
                stdout=log,
                stderr=subprocess.STDOUT,
                timeout=limit_s,
                env=env,
                cwd=ROOT,
            ).returncode
        except subprocess.TimeoutExpired:
            rc = "timeout"
    return dict(step=name, rc=rc, seconds=round(time.perf_counter() - t0, 1), argv=argv)


def _provenance(args) -> dict:
    """The session's provenance block (the code, the machine, the options), with JAX on the CPU
    alone: JAX takes most of a GPU's memory in the first process that uses the GPU, and that
    must be the steps'. Each step's rows carry their own block, with the device they ran on."""
    saved = os.environ.get("JAX_PLATFORMS")
    os.environ["JAX_PLATFORMS"] = "cpu"
    try:
        if ROOT not in sys.path:
            sys.path.insert(0, ROOT)
        from rvdjax.provenance import benchmark_block

        return benchmark_block("sweeps/gpu_session.py", vars(args), device="each step's own")
    finally:  # the steps start with this process's environment as it was
        if saved is None:
            os.environ.pop("JAX_PLATFORMS", None)
        else:
            os.environ["JAX_PLATFORMS"] = saved


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=os.path.join("results", "gpu-session"))
    ap.add_argument("--smoke", action="store_true", help="tiny sizes on any device")
    ap.add_argument("--dry-run", action="store_true", help="print the commands only")
    args = ap.parse_args(argv)
    args.out = os.path.abspath(args.out)
    plan = steps(args.out, args.smoke)
    if args.dry_run:
        for name, step_argv, limit in plan:
            print(f"{name} (at most {limit} s): python {' '.join(step_argv)}")
        return 0
    try:
        os.makedirs(args.out, exist_ok=True)
        with open(os.path.join(args.out, "gpu_session.jsonl"), "a"):
            pass
    except OSError as e:
        print(f"--out: cannot write to {args.out!r} ({e.strerror})", file=sys.stderr)
        return 2
    provenance = _provenance(args)
    rows = []
    for name, step_argv, limit in plan:
        print(f"[gpu_session] {name}: at most {limit} s", flush=True)
        row = run_step(name, step_argv, limit, args.out)
        rows.append(row)
        with open(os.path.join(args.out, "gpu_session.jsonl"), "a") as f:
            f.write(json.dumps(dict(row, provenance=provenance)) + "\n")
        with open(os.path.join(args.out, f"{name}.log")) as f:
            tail = f.read()[-4000:]
        print(tail, flush=True)
    print("| step | exit | seconds |\n| --- | --- | --- |")
    for r in rows:
        print(f"| {r['step']} | {r['rc']} | {r['seconds']} |")
    return 0 if all(r["rc"] == 0 for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
