"""Kernels in a tick of the batch engine: the optimised HLO of one device's segment program,
counted by computation (docs/history.md, "A tick in few kernels").

    python sweeps/tick_kernels.py [--scenarios thesis-vbar,poseidyn-lqmpc,fastmpc-3d]
        [--slots 64] [--chunk 32] [--refresh masked,compacted] [--platform cpu] [--json FILE]

A *kernel* is an instruction of the optimised HLO that does work on its own: a fusion, a
custom call, a copy, a (dynamic-update-)slice, a scatter or gather, a sort, a reduction, ...
(everything but parameters, constants, tuples, bitcasts and the control flow itself). The tick
is the body of the segment's outer ``while`` (over ticks); the counts are static (each
computation counted once, whatever its trip count): the solver iterations' (the loop of
``iterations`` trips and what it runs) and the rest (assignment, the refresh: advance,
refill, prepare and the solver's start; the ring). The solver's inner loops (stages) are
compiled whole on a CPU, one task per loop, not one per kernel. XLA's ``cost_analysis()`` of
the program (flops and bytes, each loop body counted once) is printed beside them. Works on
the engine of any commit that has ``rvdjax.loop.engine._segment`` (the before/after counts
of the history page).
"""

from __future__ import annotations

import argparse
import inspect
import json
import os
import re
from collections import Counter

import jax
import jax.numpy as jnp

import rvdjax  # noqa: F401  (float64, XLA options)
from rvdjax.bench import perturbed_states
from rvdjax.loop import engine as E
from rvdjax.scenarios import FlightOptions, get_scenario
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


SCOPES = ("iterations", "refresh", "ring")


def scope(attrs: str) -> str:
    """The engine's named scope of an instruction (its metadata's op_name), or "other"."""
    m = re.search(r'op_name="([^"]*)"', attrs)
    name = m.group(1) if m else ""
    return next((s for s in SCOPES if f"/{s}/" in f"/{name}/"), "other")


def kernels(comps: dict, name: str, seen=None, by=None) -> Counter:
    """Kernels of computation ``name`` and of the computations its control flow runs (not
    the fused ones: a fusion is one kernel), by opcode (or by ``by(attrs)``)."""
    seen = set() if seen is None else seen
    if name in seen or name not in comps:
        return Counter()
    seen.add(name)
    out = Counter()
    for op, attrs in comps[name]:
        if op == "while":
            for key in ("condition", "body"):
                for c in _called(attrs, key):
                    out += kernels(comps, c, seen, by)
        elif op == "conditional":
            for key in ("branch_computations", "true_computation", "false_computation"):
                for c in _called(attrs, key):
                    out += kernels(comps, c, seen, by)
        elif op == "call":
            for c in _called(attrs, "to_apply"):
                out += kernels(comps, c, seen, by)
        elif op not in FREE:
            out[op if by is None else by(attrs)] += 1
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


def loops_with_trips(comps: dict, body: str, trips: int) -> list[str]:
    """Bodies of the while loops reachable from ``body`` whose known trip count is ``trips``
    (the solver iterations of a tick: ``fori_loop(0, iterations)``)."""
    out, stack, seen = [], [body], set()
    while stack:
        name = stack.pop()
        if name in seen:
            continue
        seen.add(name)
        for op, attrs in comps.get(name, []):
            called = (
                _called(attrs, "to_apply")
                + _called(attrs, "branch_computations")
                + _called(attrs, "true_computation")
                + _called(attrs, "false_computation")
            )
            if op == "while":
                b = _called(attrs, "body")[0]
                if f'"known_trip_count":{{"n":"{trips}"}}' in attrs:
                    out.append(b)
                else:
                    stack.append(b)
            elif op in ("call", "conditional"):
                stack += called
    return out


def program(scenario: str, slots: int, chunk: int, refresh: str, platform: str | None):
    """(optimised HLO text, cost analysis) of one device's segment program."""
    sc = get_scenario(scenario)
    flight = sc.flight(FlightOptions())
    params, x0, loop = flight.params, flight.x0, flight.loop
    sp = SolverParams.for_settings(loop.config.settings)
    source = E.arrays_source(perturbed_states(x0, 8))
    if hasattr(E, "segment_program"):  # this engine
        cfg = E.EngineConfig(slots=slots, chunk=chunk, refresh=refresh, platform=platform)
        abstract = getattr(E, "_abstract_args", None) or E.stream._abstract_args
        lowered = E.segment_program(loop, cfg, source.fn).lower(
            *abstract(loop, cfg, source, params, sp)
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


def count(text: str, iterations: int = 3) -> dict:
    """Kernels of a tick: in all, in the solver iterations (the loops of ``iterations``
    trips) and the rest (assignment, refresh: advance, refill, prepare, start; ring)."""
    comps, entry = parse(text)
    body = tick_body(comps, entry)
    total = kernels(comps, body)
    solver = Counter()
    for b in loops_with_trips(comps, body, iterations):
        solver += kernels(comps, b)
    return {
        "tick_total": sum(total.values()),
        "solver_iterations": sum(solver.values()),
        "refresh_and_rest": sum(total.values()) - sum(solver.values()),
        "fusions": total["fusion"],
        "by_scope": dict(kernels(comps, body, by=scope)),
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
    ap.add_argument("--dump", metavar="DIR", help="write each program's optimised HLO there")
    ap.add_argument("--count", metavar="FILE", nargs="+", help="only count these HLO dumps")
    args = ap.parse_args(argv)
    if args.count:
        for path in args.count:
            with open(path) as f:
                print(os.path.basename(path), json.dumps(count(f.read())))
        return
    rows = []
    modes = args.refresh.split(",") if hasattr(E, "segment_program") else ["before"]
    for name in args.scenarios.split(","):
        for mode in modes:
            text, cost = program(name, args.slots, args.chunk, mode, args.platform)
            if args.dump:
                os.makedirs(args.dump, exist_ok=True)
                with open(os.path.join(args.dump, f"{name}-{mode}.hlo.txt"), "w") as f:
                    f.write(text)
            row = {"scenario": name, "refresh": mode, **count(text)}
            row["flops"] = float(cost.get("flops", float("nan")))
            row["bytes_accessed"] = float(cost.get("bytes accessed", float("nan")))
            rows.append(row)
            print(
                f"{name:<16}{mode:<10} kernels in a tick {row['tick_total']:>5}: solver "
                f"iterations {row['solver_iterations']:>4}, refresh and the rest "
                f"{row['refresh_and_rest']:>4} (fusions {row['fusions']:>5}), "
                f"XLA cost {row['flops'] / 1e6:.2f} Mflop / "
                f"{row['bytes_accessed'] / 2**20:.1f} MiB",
                flush=True,
            )
    if args.json:
        from rvdjax.provenance import benchmark_block

        with open(args.json, "w") as f:
            prov = benchmark_block("sweeps/tick_kernels.py", vars(args))
            json.dump({"provenance": prov, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
