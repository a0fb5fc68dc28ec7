"""float32 against float64 on the fastmpc-3d first-step QPs: how many solves end NONFINITE and
how far the objective moves.

The GPU path keeps float64 unless float32 is both robust (no NONFINITE solve, objective within
1e-6 of float64) and at least 1.8x faster. Robustness does not depend on the device; this
script measures it on the CPU (the speed is measured on a GPU by sweeps/gpu_benchmark.py).

    python sweeps/float32_qps.py --batch 65536 [--modes paper,accurate]
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

import rvdjax  # noqa: F401  (float64)
from rvdjax.problems import fastmpc3d_first_step_batch, perturbed_x0
from rvdjax.solver import SolverSettings, Status, solve_batch


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--batch", type=int, default=4096)
    ap.add_argument("--modes", default="paper,accurate")
    args = ap.parse_args(argv)
    ocps = fastmpc3d_first_step_batch(perturbed_x0(0, args.batch))
    ocps32 = jax.tree.map(lambda a: a.astype(jnp.float32) if a.dtype == jnp.float64 else a, ocps)
    print(f"{args.batch} fastmpc-3d first-step QPs (paper 000 Table 1, x0 perturbed)")
    print("| mode | dtype | NONFINITE | converged | max rel. objective error | s |")
    print("| --- | --- | --- | --- | --- | --- |")
    for mode in args.modes.split(","):
        settings = SolverSettings.paper() if mode == "paper" else SolverSettings()
        fn = jax.jit(lambda o, s=settings: solve_batch(o, s, chunk=32))
        ref = None
        for name, data in (("float64", ocps), ("float32", ocps32)):
            t0 = time.perf_counter()
            sol = jax.block_until_ready(fn(data))
            sec = time.perf_counter() - t0
            status = np.asarray(sol.status)
            J = np.asarray(sol.objective, float)
            err = "-"
            if ref is None:
                ref = J
            else:
                ok = np.isfinite(J)
                err = f"{np.max(np.abs(J[ok] - ref[ok]) / np.abs(ref[ok]), initial=0.0):.1e}"
            print(
                f"| {mode} | {name} | {int(np.sum(status == Status.NONFINITE))} | "
                f"{int(np.sum(status == Status.CONVERGED))} | {err} | {sec:.1f} |",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
