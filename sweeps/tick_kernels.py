"""Kernels in a tick of the batch engine: the optimised HLO of one device's segment program,
counted by computation (docs/history.md, "A tick in few kernels").

    python sweeps/tick_kernels.py [--scenarios thesis-vbar,poseidyn-lqmpc,fastmpc-3d]
        [--slots 64] [--chunk 32] [--refresh masked,compacted] [--platform cpu] [--json FILE]

A *kernel* is an instruction of the optimised HLO that does work on its own: a fusion, a
custom call, a copy, a (dynamic-update-)slice, a scatter or gather, a sort, a reduction, ...
(everything but parameters, constants, tuples, bitcasts and the control flow itself). The tick
is the body of the segment's outer ``while`` (over ticks); the counts are static (each
computation counted once): the tick's own kernels, the refresh's (advance, refill, prepare and
the solver's start, in the ``cond``/``while`` they run in) and the solver iterations' (whose
inner loops run once per iteration). XLA's ``cost_analysis()`` of the program (flops and
bytes, each loop body counted once) is printed beside them. Works on the engine of any commit
that has ``rvdjax.loop.engine._segment`` (the before/after counts of the history page).
"""

from __future__ import annotations

import argparse
import inspect
import json
import re
from collections import Counter

import jax
import jax.numpy as jnp

import rvdjax  # noqa: F401  (float64, XLA options)
from rvdjax.bench import perturbed_states
from rvdjax.loop import engine as E
from rvdjax.scenarios import get_scenario
from rvdjax.solver import SolverParams

FREE = {
    "parameter",
    "constant",
    "tuple",
    "get-tuple-element",
    "bitcast",
    "while",
    "conditional",
    "call",
    "after-all",
    "partition-id",
    "replica-id",
    "opt-barrier",
}
_INSTR = re.compile(r"^\s*(?:ROOT\s+)?%?([\w.\-]+)\s*=\s*(.*)$")
_OPCODE = re.compile(r"(?:^|\s)([a-z][a-z0-9\-]*)\(")
_HEADER = re.compile(r"^(?:ENTRY\s+)?%?([\w.\-]+)\s.*\{\s*$")


def parse(text: str) -> tuple[dict, str]:
    """{computation: [(opcode, attributes text)]} and the entry computation's name."""
    comps, entry, cur = {}, None, None
    for line in text.splitlines():
        if cur is None:
            m = _HEADER.match(line)
            if m and not line.startswith("HloModule"):
                cur = m.group(1)
                comps[cur] = []
                if line.startswith("ENTRY"):
                    entry = cur
            continue
        if line.strip() == "}":
            cur = None
            continue
        m = _INSTR.match(line)
        if m:
            op = _OPCODE.search(m.group(2))
            if op:
                comps[cur].append((op.group(1), m.group(2)))
    return comps, entry


def _called(attrs: str, key: str) -> list[str]:
    m = re.search(key + r"=\{?([^}]*?)\}?(?:,\s*\w+=|$)", attrs)
    if not m:
        return []
    return [c.strip().lstrip("%") for c in m.group(1).split(",") if c.strip()]


def kernels(comps: dict, name: str, seen=None) -> Counter:
    """Kernels of computation ``name`` and of the computations its control flow runs (not
    the fused ones: a fusion is one kernel)."""
    seen = set() if seen is None else seen
    if name in seen or name not in comps:
        return Counter()
    seen.add(name)
    out = Counter()
    for op, attrs in comps[name]:
        if op == "while":
            for key in ("condition", "body"):
                for c in _called(attrs, key):
                    out += kernels(comps, c, seen)
        elif op == "conditional":
            for key in ("branch_computations", "true_computation", "false_computation"):
                for c in _called(attrs, key):
                    out += kernels(comps, c, seen)
        elif op == "call":
            for c in _called(attrs, "to_apply"):
                out += kernels(comps, c, seen)
        elif op not in FREE:
            out[op] += 1
    return out


def tick_body(comps: dict, entry: str) -> str:
    """The body of the segment's outer while loop (the ticks)."""
    stack = [entry]
    while stack:
        name = stack.pop()
        for op, attrs in comps.get(name, []):
            if op == "while":
                return _called(attrs, "body")[0]
            if op in ("call", "conditional"):
                stack += _called(attrs, "to_apply") + _called(attrs, "branch_computations")
    raise ValueError("no while loop in the segment program")


def inner_loops(comps: dict, body: str) -> list[tuple[str, Counter]]:
    """The while loops reachable from ``body`` (not through another while), with their
    kernels."""
    out, stack, seen = [], [body], set()
    while stack:
        name = stack.pop()
        if name in seen:
            continue
        seen.add(name)
        for op, attrs in comps.get(name, []):
            if op == "while":
                b = _called(attrs, "body")[0]
                out.append((b, kernels(comps, b)))
            elif op in ("call", "conditional"):
                stack += (
                    _called(attrs, "to_apply")
                    + _called(attrs, "branch_computations")
                    + _called(attrs, "true_computation")
                    + _called(attrs, "false_computation")
                )
    return out


def program(scenario: str, slots: int, chunk: int, refresh: str, platform: str | None):
    """(optimised HLO text, cost analysis) of one device's segment program."""
    sc = get_scenario(scenario)
    params, x0 = sc.build()
    loop = sc.loop()
    sp = SolverParams.for_settings(loop.config.settings)
    source = E.arrays_source(perturbed_states(x0, 8))
    if hasattr(E, "segment_program"):  # this engine
        cfg = E.EngineConfig(slots=slots, chunk=chunk, refresh=refresh, platform=platform)
        lowered = E.segment_program(loop, cfg, source.fn).lower(
            *E._abstract_args(loop, cfg, source, params, sp)
        )
    else:  # the engine before the refresh (one argument list, no refresh setting)
        cfg = E.EngineConfig(slots=slots, chunk=chunk)
        seg = jax.jit(E._segment(loop, cfg, source.fn))
        n = len(inspect.signature(E._initial_state_one).parameters)
        extra = (8,) if n == 6 else ()
        eng = E._initial_state_one(loop, cfg, source, params, sp, *extra)
        lowered = seg.lower(eng, source.data, params, sp, jnp.asarray(cfg.ticks_per_segment))
    compiled = lowered.compile()
    cost = compiled.cost_analysis()
    cost = cost[0] if isinstance(cost, list) else cost
    return compiled.as_text(), cost


def count(text: str) -> dict:
    comps, entry = parse(text)
    body = tick_body(comps, entry)
    total = kernels(comps, body)
    loops = inner_loops(comps, body)
    in_loops = sum((c for _, c in loops), Counter())
    return {
        "tick_total": sum(total.values()),
        "tick_outside_inner_loops": sum(total.values()) - sum(in_loops.values()),
        "inner_loops": len(loops),
        "inner_loop_kernels": sorted((sum(c.values()) for _, c in loops), reverse=True),
        "fusions": total["fusion"],
        "by_opcode": dict(total.most_common(12)),
    }


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenarios", default="thesis-vbar,poseidyn-lqmpc,fastmpc-3d")
    ap.add_argument("--slots", type=int, default=64)
    ap.add_argument("--chunk", type=int, default=32)
    ap.add_argument("--refresh", default="masked,compacted")
    ap.add_argument("--platform", default=None)
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    rows = []
    modes = args.refresh.split(",") if hasattr(E, "segment_program") else ["before"]
    for name in args.scenarios.split(","):
        for mode in modes:
            text, cost = program(name, args.slots, args.chunk, mode, args.platform)
            row = {"scenario": name, "refresh": mode, **count(text)}
            row["flops"] = float(cost.get("flops", float("nan")))
            row["bytes_accessed"] = float(cost.get("bytes accessed", float("nan")))
            rows.append(row)
            print(
                f"{name:<16}{mode:<10} kernels in a tick {row['tick_total']:>5} "
                f"(outside the inner loops {row['tick_outside_inner_loops']:>4}, "
                f"{row['inner_loops']} inner loops), fusions {row['fusions']:>5}, "
                f"XLA cost {row['flops'] / 1e6:.2f} Mflop / "
                f"{row['bytes_accessed'] / 2**20:.1f} MiB",
                flush=True,
            )
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
