"""Where Triton's compile of the Newton step's Pallas kernels goes, on a machine without a GPU.

    PYTHONPATH=. python sweeps/triton_compile_profile.py factor|apply|factor_solve
        [--warps 4] [--block-io] [--out DIR] [--triton-python PYTHON]

Lowers one kernel of :mod:`rvdjax.solver.lanes` for CUDA (compute capability 9.0; no GPU
needed), writes its Triton IR to ``DIR/<kernel>.ttir`` and counts its operations; then, if the
``triton`` package is installed for this Python or ``--triton-python`` (``pip install
triton``: it carries its own ``ptxas``), compiles that IR for sm_90 with MLIR's pass timing
and prints the passes that took the time.
XLA compiles a Pallas kernel with its own copy of Triton, whose passes are these; the times
differ with the machine and the version, the shares hardly.
"""

from __future__ import annotations

import argparse
import collections
import os
import re
import subprocess
import sys
import time

import jax

import rvdjax  # noqa: F401  (float64)
from rvdjax.solver import lanes

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import pallas_compile  # noqa: E402  (the kernels' inputs and calls)


def triton_ir(part: str, warps: int, block_io: bool = False) -> list[str]:
    """The Triton IR (text) of each Pallas kernel in ``part``'s program."""
    from jax._src.pallas.triton import lowering as tl
    from jax._src.pallas.triton import pallas_call_registration as reg

    captured = []
    original = tl.lower_jaxpr_to_triton_module

    def spy(*args, **kwargs):
        result = original(*args, **kwargs)
        captured.append(result.module.operation.get_asm(enable_debug_info=False))
        return result

    reg.lowering.lower_jaxpr_to_triton_module = spy
    try:
        cfg = lanes.KernelConfig(num_warps=warps, block_io=block_io)
        fn = pallas_compile._fns(part, cfg)[0]
        jax.jit(fn).trace(*pallas_compile._inputs(256)).lower(lowering_platforms=("cuda",))
    finally:
        reg.lowering.lower_jaxpr_to_triton_module = original
    return captured


def op_counts(text: str) -> collections.Counter:
    return collections.Counter(
        re.findall(r"= (?:\"?)([a-z_]+\.[a-z_.]+)", text)
    ) + collections.Counter(re.findall(r"^\s+(tt\.store)", text, flags=re.M))


_COMPILE = """
import sys, time
import triton
from triton.backends.compiler import GPUTarget
t0 = time.time()
triton.compile(sys.argv[1], target=GPUTarget("cuda", 90, 32),
               options={"num_warps": int(sys.argv[2]), "num_stages": 1})
print(f"compiled in {time.time() - t0:.1f} s")
"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("part", choices=("apply", "factor", "factor_solve"))
    ap.add_argument("--warps", type=int, default=4)
    ap.add_argument("--block-io", action="store_true", help="KernelConfig.block_io")
    ap.add_argument("--out", default="results/triton")
    ap.add_argument("--triton-python", default=sys.executable, help="a Python with triton")
    args = ap.parse_args(argv)
    has_triton = (
        subprocess.run([args.triton_python, "-c", "import triton"], capture_output=True).returncode
        == 0
    )
    os.makedirs(args.out, exist_ok=True)
    for i, text in enumerate(triton_ir(args.part, args.warps, args.block_io)):
        path = os.path.join(args.out, f"{args.part}{'_block' if args.block_io else ''}_{i}.ttir")
        with open(path, "w", encoding="utf-8") as f:
            f.write(text)
        counts = op_counts(text)
        memops = counts["tt.load"] + counts["tt.store"]
        print(f"{path}: {sum(counts.values())} operations, {memops} loads and stores")
        if not has_triton:
            print(f"  no triton for {args.triton_python}: no compile (pip install triton)")
            continue
        env = dict(os.environ, MLIR_ENABLE_TIMING="1")
        t0 = time.perf_counter()
        out = subprocess.run(
            [args.triton_python, "-c", _COMPILE, path, str(args.warps)],
            env=env,
            capture_output=True,
            text=True,
            check=False,
        )
        print(f"  wall {time.perf_counter() - t0:.1f} s; {out.stdout.strip()}")
        passes = re.findall(r"^\s+([\d.]+) \(\s*([\d.]+)%\)\s+(\S.*)$", out.stderr, flags=re.M)
        top = sorted(passes, key=lambda p: -float(p[0]))
        for seconds, share, name in [p for p in top if p[2] != "Total"][:5]:
            print(f"  {float(seconds):9.2f} s {float(share):5.1f} %  {name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
