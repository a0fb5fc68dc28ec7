"""Registers, spills and occupancy of the Newton step's GPU kernels, read from the program XLA
compiles for a GPU, on a machine without one.

    pip install "jax[cuda13]==$(python -c 'import jax; print(jax.__version__)')"  # no GPU needed
    python sweeps/gpu_registers.py [qp] [--batch 65536] [--kernels auto] [--shared-model]
    python sweeps/gpu_registers.py engine [--scenario thesis-vbar] [--slots 4096,32768]
        [--out DIR]

XLA compiles the program deviceless, as ``sweeps/gpu_traffic.py`` does, and writes each
kernel's PTX (``--xla_dump_to``); ``ptxas`` (from the ``nvidia-cuda-nvcc`` wheel that
``jax[cuda13]`` installs) assembles each Pallas kernel's PTX for the target's architecture
(sm_90a) and reports what the GPU would run: registers a thread, the stack frame and the bytes
of spill stores and loads in the code (a spill inside the stage loop runs every stage), and,
from the PTX, the barriers and shared-memory loads and stores. From
the registers follow the programs a multiprocessor holds at once (Hopper: 65 536 registers,
allocated 256 at a time per warp; at most 64 warps and 32 programs) and, for the batch, the
warps each multiprocessor has to hide a problem's serial stage loop with (one problem per
thread). (No register cap is tried: XLA passes no option to its own ptxas, Pallas' Triton
parameters have none, and this ptxas left the kernels at 255 registers under -maxrregcount.)

Prints one table per program; rows go to ``OUT/gpu_registers.jsonl``. Without jax's CUDA
plugin or ptxas it says so in one line and exits with status 2.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

# Hopper (sm_90): the multiprocessor's limits (CUDA C Programming Guide, compute capability
# 9.0 table; the register allocation unit is 256 registers per warp)
SM_REGISTERS = 65536
SM_WARPS = 64
SM_PROGRAMS = 32
REGISTER_UNIT = 256
SMS = 132  # H100 SXM and H200: 132 multiprocessors
ARCH = "sm_90a"

_PTXAS_ENTRY = re.compile(r"Compiling entry function '([\w$.]+)'")
_PTXAS_FRAME = re.compile(
    r"(\d+) bytes stack frame, (\d+) bytes spill stores, (\d+) bytes spill loads"
)
_PTXAS_REGS = re.compile(r"Used (\d+) registers")


def parse_ptxas(text: str) -> dict[str, dict]:
    """``ptxas -v``'s report as {kernel: {registers, stack, spill_stores, spill_loads}}."""
    out: dict[str, dict] = {}
    name = None
    for line in text.splitlines():
        m = _PTXAS_ENTRY.search(line)
        if m:
            name = m.group(1)
            out[name] = dict(registers=0, stack=0, spill_stores=0, spill_loads=0)
            continue
        if name is None:
            continue
        m = _PTXAS_FRAME.search(line)
        if m:
            out[name].update(
                stack=int(m.group(1)), spill_stores=int(m.group(2)), spill_loads=int(m.group(3))
            )
        m = _PTXAS_REGS.search(line)
        if m:
            out[name]["registers"] = int(m.group(1))
    return out


def programs_per_sm(registers: int, threads: int) -> int:
    """Programs (thread blocks) of ``threads`` threads a Hopper multiprocessor holds at once
    with ``registers`` a thread (shared memory not counted)."""
    warps = -(-threads // 32)
    per_warp = -(-registers * 32 // REGISTER_UNIT) * REGISTER_UNIT
    by_registers = (SM_REGISTERS // per_warp) // warps if per_warp else SM_PROGRAMS
    return max(0, min(by_registers, SM_WARPS // warps, SM_PROGRAMS))


def warps_at(batch: int, lanes: int, threads: int, held: int, sms: int = SMS) -> float:
    """Warps a multiprocessor runs at once, on average, for a kernel over ``batch`` problems
    in programs of ``lanes`` problems and ``threads`` threads, ``held`` of which fit a
    multiprocessor: the grid's warps spread over the multiprocessors, at most ``held``
    programs' worth each."""
    programs = -(-batch // lanes)
    warps = -(-threads // 32)
    return min(held, programs / sms) * warps


def find_ptxas() -> str | None:
    """ptxas on the PATH, or the one in the nvidia-cuda-nvcc wheel (jax[cuda13] installs it)."""
    found = shutil.which("ptxas")
    if found:
        return found
    import importlib.util

    try:
        spec = importlib.util.find_spec("nvidia")
    except ImportError:
        return None
    for root in list(spec.submodule_search_locations or []) if spec else []:
        for path in glob.glob(os.path.join(root, "*", "bin", "ptxas")):
            return path
    return None


def kernel_ptx(dump: str, prefix: str = "rvdjax_") -> dict[str, str]:
    """{kernel name: PTX file} of the Pallas kernels (entries named ``prefix``...) in an XLA
    dump directory; a kernel met in several files (the same program dumped twice) once."""
    out = {}
    for path in sorted(glob.glob(os.path.join(dump, "*.ptx"))):
        with open(path) as f:
            text = f.read()
        for name in re.findall(r"\.entry (\w+)", text):
            if name.startswith(prefix):
                out.setdefault(name, path)
    return out


def threads_of(ptx_path: str) -> int:
    with open(ptx_path) as f:
        m = re.search(r"\.reqntid (\d+)", f.read())
    return int(m.group(1)) if m else 128


def ptx_counts(ptx_path: str) -> dict[str, int]:
    """Barriers (``bar.sync``) and shared-memory loads and stores in a kernel's PTX: a block's
    split into lane vectors and join back pass through shared memory, a barrier each."""
    with open(ptx_path) as f:
        text = f.read()
    return dict(
        barriers=len(re.findall(r"\bbar\.sync\b", text)),
        shared=len(re.findall(r"\b(?:ld|st)\.shared\b", text)),
    )


def assemble(ptxas: str, ptx_path: str) -> dict[str, dict]:
    """``ptxas -v`` of one PTX file for :data:`ARCH`."""
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [ptxas, f"-arch={ARCH}", "-v", ptx_path, "-o", os.path.join(tmp, "k.cubin")]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    if proc.returncode != 0:
        raise RuntimeError(f"ptxas failed on {ptx_path}: {proc.stderr[-500:]}")
    return parse_ptxas(proc.stdout + proc.stderr)


def report(dump: str, ptxas: str, batches: list[int], lanes: int) -> list[dict]:
    """One row per Pallas kernel in ``dump``."""
    rows = []
    for name, path in kernel_ptx(dump).items():
        threads = threads_of(path)
        info = assemble(ptxas, path)[name]
        held = programs_per_sm(info["registers"], threads)
        row = dict(kernel=name, threads=threads, programs_per_sm=held, **info)
        row.update(ptx_counts(path))
        row["warps_per_sm"] = {b: warps_at(b, lanes, threads, held) for b in batches}
        rows.append(row)
    return rows


def format_table(rows: list[dict], batches: list[int]) -> str:
    head = ["kernel", "registers", "stack B", "spill stores / loads B", "barriers",
            "shared ld/st", "programs a SM"]  # fmt: skip
    head += [f"warps a SM at {b}" for b in batches]
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for r in rows:
        spills = f"{r['spill_stores']} / {r['spill_loads']}"
        cells = [r["kernel"], str(r["registers"]), str(r["stack"]), spills]
        cells += [str(r.get("barriers", "")), str(r.get("shared", ""))]
        cells += [str(r["programs_per_sm"])]
        cells += [f"{r['warps_per_sm'][b]:.1f}" for b in batches]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _ints(text: str, name: str, low: int) -> list[int] | str:
    try:
        vals = [int(v) for v in text.split(",") if v]
    except ValueError:
        vals = []
    if not vals or min(vals) < low:
        return f"gpu_registers: --{name} must be comma-separated integers >= {low}, got {text!r}"
    return vals


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("part", nargs="?", default="qp", choices=("qp", "engine"))
    ap.add_argument("--batch", default="65536", help="qp: QPs in the batch (>= 1)")
    ap.add_argument("--scenario", default="thesis-vbar", help="engine: the scenario")
    ap.add_argument("--slots", default="4096,32768", help="engine: slots; the first is compiled")
    ap.add_argument("--kernels", default="auto", help="qp: the Newton step's form")
    ap.add_argument("--mode", choices=("accurate", "paper"), default="accurate")
    ap.add_argument("--shared-model", action="store_true", help="qp: one model for every QP")
    ap.add_argument("--out", default="results/gpu-registers", help="directory for the rows")
    args = ap.parse_args(argv)
    engine = args.part == "engine"
    sizes = _ints(args.slots if engine else args.batch, "slots" if engine else "batch", 1)
    if isinstance(sizes, str):
        print(sizes)
        return 2
    from rvdjax.scenarios import SCENARIOS

    if engine and args.scenario not in SCENARIOS:
        print(f"gpu_registers: --scenario must be a named scenario (rvdjax list), got "
              f"{args.scenario!r}")  # fmt: skip
        return 2
    from rvdjax.solver.types import KERNELS

    if args.kernels not in KERNELS:
        print(f"gpu_registers: --kernels must be one of {', '.join(KERNELS)}, got "
              f"{args.kernels!r}")  # fmt: skip
        return 2
    from rvdjax.outputs import check_dir

    check_dir(args.out, "--out")
    import gpu_traffic

    missing = gpu_traffic._cuda_missing()
    ptxas = find_ptxas()
    if missing or not ptxas:
        print(missing or "gpu_registers: needs ptxas (pip install nvidia-cuda-nvcc or jax[cuda13])")
        return 2
    dump = tempfile.mkdtemp(prefix="gpu-registers-")
    # before jax starts its backends, so that the GPU compiler writes each kernel's PTX
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} --xla_dump_to={dump}".strip()
    from rvdjax.provenance import benchmark_block
    from rvdjax.solver import lanes

    t0 = time.perf_counter()
    if args.part == "engine":
        gpu_traffic._compile_engine(args.scenario, sizes[0], "h100", args.kernels)
        what = f"{args.scenario}'s engine segment, {sizes[0]} slots"
    else:
        gpu_traffic._compile(args.kernels, sizes[0], args.mode, "h100", args.shared_model)
        what = f"one {args.mode} iteration of {sizes[0]} fastmpc-3d QPs"
    compile_s = time.perf_counter() - t0
    rows = report(dump, ptxas, sizes, lanes.default_config().block)
    shutil.rmtree(dump, ignore_errors=True)
    if not rows:
        print("gpu_registers: the program has no Pallas kernel (kernel 'xla'?)")
        return 2
    os.makedirs(args.out, exist_ok=True)
    provenance = benchmark_block("sweeps/gpu_registers.py", vars(args))
    with open(os.path.join(args.out, "gpu_registers.jsonl"), "a") as f:
        for r in rows:
            row = dict(r, program=what, kernel_form=args.kernels, compile_s=compile_s)
            f.write(json.dumps(dict(row, provenance=provenance)) + "\n")
    print(f"{what}, Newton step {args.kernels!r}, compiled for an H100 ({ARCH}, no GPU used) "
          f"in {compile_s:.1f} s here; one problem a thread:")  # fmt: skip
    print(format_table(rows, sizes))
    return 0


if __name__ == "__main__":
    sys.exit(main())
