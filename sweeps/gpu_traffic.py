"""A solver iteration's GPU memory traffic, read from the program XLA compiles for a GPU, on a
machine without one.

    pip install "jax[cuda13]==$(python -c 'import jax; print(jax.__version__)')"  # no GPU needed
    python sweeps/gpu_traffic.py [qp] [--batch 65536] [--kernels auto,pallas,pallas-block-io]
        [--mode accurate] [--target h100|h200] [--padded-blocks] [--top 12] [--out DIR] [--hlo]
    python sweeps/gpu_traffic.py engine [--scenario thesis-vbar] [--slots 4096] [--target h100]
    python sweeps/gpu_traffic.py solve [--batch 65536] [--kernels auto,pallas-entries]
        [--shared-model]
    python sweeps/gpu_traffic.py maneuver [--scenario fastmpc-3d] [--kernels auto]

XLA compiles for a GPU it is not running on ("deviceless" ahead-of-time compilation: a
``jax.experimental.topologies`` description of one H100 or H200, the CUDA plugin's compiler
and Triton's, no driver). The program is one iteration of ``jit(vmap(iterate))`` on
``--batch`` fastmpc-3d first-step QPs (each with its own copy of the model, as
``sweeps/gpu_benchmark.py`` solves them). In the optimised program every launch (a fusion, a
Pallas kernel, a copy; a ``while`` loop's body counted once per trip) reads its operands and
writes its outputs through device memory; their sizes, per problem, are the iteration's
traffic. At these batch sizes an iteration is bound by that traffic: on an H100 the ratios of
the forms' bytes matched the ratios of their measured times to 5 % (docs/benchmark.md), so
a change that moves fewer bytes is measured here before a GPU is lent. The traffic divided by
the card's bandwidth is the time the iteration cannot go below.

``engine``: one tick of the batch engine's segment program (the engine's settings for a GPU),
by the engine's scopes: the solver iterations, the refresh, the ring and the rest.

``solve``: a whole ``jit(vmap(solve))`` of the QPs, as ``sweeps/gpu_benchmark.py qp`` times it
(with ``--shared-model``, its one-model path): the solve loop's body, one iteration as the
loop runs it (its carried state, its copies), and the whole program with the loop counted
once (the start, the finish and one iteration).

``maneuver``: one maneuver flown alone (``rvdjax.loop.fly``, as ``rvdjax run --device gpu``
flies it): the launches of an MPC step with its solve loop counted once, and of the solve
loop's iteration.

Prints one row per form (launches, KB read and written a problem, the Pallas kernels' share,
that bound at ``--batch``, the compile's seconds on this machine, Triton's included) and each
form's largest sources of traffic by line of the solver's code; rows go to
``OUT/gpu_traffic.jsonl``. Without a CUDA build of jaxlib it says so in one line and exits
with status 2.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import re
import sys
import time

# The CUDA plugin checks its libraries against a driver at start; there is none here.
os.environ.setdefault("JAX_SKIP_CUDA_CONSTRAINTS_CHECK", "1")

_DEVICE = """gpu_device_info {{
  threads_per_block_limit: 1024
  threads_per_warp: 32
  shared_memory_per_block: 49152
  shared_memory_per_core: 233472
  threads_per_core_limit: 2048
  core_count: 132
  fpus_per_core: 128
  block_dim_limit_x: 2147483647
  block_dim_limit_y: 65535
  block_dim_limit_z: 65535
  memory_bandwidth: {bandwidth}
  l2_cache_size: 52428800
  clock_rate_ghz: 1.98
  device_memory_size: {memory}
  shared_memory_per_block_optin: 232448
  cuda_compute_capability {{
    major: 9
  }}
  registers_per_core_limit: 65536
  registers_per_block_limit: 65536
}}
platform_name: "CUDA"
dnn_version_info {{
  major: 9
  minor: 8
}}
runtime_version {{
  major: 13
  minor: 0
  patch: 0
}}
device_description_str: "{name}"
"""
# (name, bytes/s, memory bytes): the cards' data sheets (both Hopper, 132 SMs)
TARGETS = {
    "h100": ("NVIDIA H100 80GB HBM3", 3.35e12, 84929347584),
    "h200": ("NVIDIA H200", 4.8e12, 150754820096),
}

_SIZES = {"f64": 8, "s64": 8, "u64": 8, "f32": 4, "s32": 4, "u32": 4, "f16": 2, "bf16": 2}
_SIZES.update({"s16": 2, "u16": 2, "s8": 1, "u8": 1, "pred": 1})
_SHAPE = re.compile(r"\b(" + "|".join(_SIZES) + r")\[([\d,]*)\]")
_INSTR = re.compile(r"\s*(?:ROOT\s+)?%?([\w.\-]+)\s*=\s*(.*?)\s([\w\-]+)\((.*)")
_HEAD = re.compile(r"^(ENTRY\s+)?%?([\w.\-]+)\s.*\{\s*$")
_FREE = {"parameter", "constant", "tuple", "get-tuple-element", "bitcast", "after-all"}
_MOVES = {"copy", "transpose", "reshape"}


def nbytes(text: str) -> int:
    """Bytes of every array shape written in ``text`` (an HLO shape or a tuple of them)."""
    total = 0
    for dtype, dims in _SHAPE.findall(text):
        n = 1
        for d in dims.split(","):
            if d:
                n *= int(d)
        total += n * _SIZES[dtype]
    return total


def _computations(hlo: str) -> tuple[dict, str]:
    comps, cur, entry = {}, None, None
    for line in hlo.splitlines():
        m = _HEAD.match(line)
        if m and not line.startswith(" "):
            cur = m.group(2)
            comps[cur] = []
            entry = cur if m.group(1) else entry
        elif cur and line.startswith("  "):
            comps[cur].append(line)
    return comps, entry


def _section(hlo: str, name: str) -> list[str]:
    parts = hlo.split("\n" + name + "\n")
    return parts[1].split("\n\n")[0].splitlines() if len(parts) > 1 else []


#: the small-product helpers the solver's lines call (a source is the line that called them)
HELPERS = ("stagewise.py", "lanes/")


def _name(path: str) -> str:
    """A source file's name as the tables print it: its base name, with its package's for the
    Riccati kernels' modules (rows_kernel and lanes both have a stage.py)."""
    parts = path.replace(os.sep, "/").split("/")
    if len(parts) > 1 and parts[-2] in ("lanes", "rows_kernel"):
        return "/".join(parts[-2:])
    return parts[-1]


def _source_lines(hlo: str, keep=("solver/",)):
    """stack_frame_id -> "file:line function" of the innermost frame whose file is in the
    package's solver (else the innermost frame), from the HLO's stack-frame tables."""
    files = {
        int(a): b.strip('"') for a, b in (ln.split(" ", 1) for ln in _section(hlo, "FileNames"))
    }
    funcs = {
        int(a): b.strip('"') for a, b in (ln.split(" ", 1) for ln in _section(hlo, "FunctionNames"))
    }
    locs = {}
    for ln in _section(hlo, "FileLocations"):
        m = re.match(r"(\d+) \{file_name_id=(\d+) function_name_id=(\d+) line=(\d+)", ln)
        if m:
            f = files[int(m.group(2))]
            locs[int(m.group(1))] = (f, funcs[int(m.group(3))], int(m.group(4)))
    frames = {}
    for ln in _section(hlo, "StackFrames"):
        m = re.match(r"(\d+) \{file_location_id=(\d+) parent_frame_id=(\d+)", ln)
        if m:
            frames[int(m.group(1))] = (int(m.group(2)), int(m.group(3)))

    def where(fid: int) -> str:
        chain, seen = [], set()
        while fid in frames and fid not in seen:
            seen.add(fid)
            loc, fid = frames[fid]
            chain.append(locs[loc])
        for f, fn, line in chain:
            if any(k in f for k in keep) and not _name(f).startswith(HELPERS):
                return f"{_name(f)}:{line} {fn}"
        if chain:
            f, fn, line = chain[0]
            return f"{_name(f)}:{line} {fn}"
        return "?"

    return where


def _in_place(comps: dict, fused: str, shapes: dict):
    """For a fusion whose root is a dynamic-update-slice or a scatter (or a tuple of them): the
    positions of the fusion's operands it updates in place and the bytes of the updates, else
    None. (XLA's GPU backend writes both into their operand's buffer; where that buffer is
    still needed, copy insertion adds a ``copy``, counted as a launch of its own.)"""
    lines = comps.get(fused, [])
    params, roots = {}, []
    for ln in lines:
        m = _INSTR.match(ln)
        if not m:
            continue
        name, _, op, rest = m.groups()
        if op == "parameter":
            params[name] = int(re.match(r"(\d+)", rest).group(1))
        if ln.lstrip().startswith("ROOT"):
            roots = [(name, op, rest)]
    if not roots:
        return None
    name, op, rest = roots[0]
    ops = {}
    for ln in lines:
        m = _INSTR.match(ln)
        if m:
            ops[m.group(1)] = (m.group(3), m.group(4))
    targets = [name] if op in _UPDATES else []
    if op == "tuple":
        targets = re.findall(r"%([\w.\-]+)", rest.split(")")[0])
        if not all(ops.get(t, ("",))[0] in _UPDATES for t in targets):
            return None
    if not targets:
        return None
    aliased, update = [], 0
    for t in targets:
        buf, upd = _update_operands(ops[t][0], re.findall(r"%([\w.\-]+)", ops[t][1].split(")")[0]))
        if buf not in params:
            return None
        aliased.append(params[buf])
        update += shapes.get(upd, 0)
    return aliased, update


# ops that write part of their first operand's buffer in place: (op, position of the update)
_UPDATES = {"dynamic-update-slice": 1, "scatter": 2}


def _update_operands(op: str, operands: list) -> tuple:
    """(the updated buffer, the update) among an in-place op's operands."""
    return operands[0], operands[_UPDATES[op]] if len(operands) > _UPDATES[op] else None


def _sliced_reads(comps: dict, fused: str, shapes: dict) -> dict:
    """{operand position: bytes} for a fusion's parameters that it only reads through
    (dynamic-)slices: a stage of a stacked array read inside a loop."""
    params, users = {}, {}
    for ln in comps.get(fused, []):
        m = _INSTR.match(ln)
        if not m:
            continue
        name, shape, op, rest = m.groups()
        if op == "parameter":
            params[name] = int(re.match(r"(\d+)", rest).group(1))
            continue
        for i, o in enumerate(re.findall(r"%([\w.\-]+)", rest.split("), ")[0])):
            users.setdefault(o, []).append((op, i, nbytes(shape)))
    out = {}
    for name, k in params.items():
        uses = users.get(name, [])
        if uses and all(op in ("dynamic-slice", "slice") and i == 0 for op, i, _ in uses):
            out[k] = sum(b for _, _, b in uses)
    return out


def kernel_sweeps(jaxpr) -> dict[str, tuple[int, int]]:
    """{name: (bytes read, bytes written) a launch} of every Pallas kernel in a traced program
    (``jax.make_jaxpr`` or ``.trace(...).jaxpr``, traced for a CUDA GPU), from the kernel's own
    loads and stores: a loop over the stages reads each array it loads once per trip, whatever
    entries of it a trip loads (a trip's neighbouring stages and a block's overlapping chunks
    come from the cache), so a kernel whose sweeps read an array again reads it again from
    device memory. The operands-once count of :func:`traffic` is right for a kernel that reads
    each operand in one sweep and low for the fused kernels, whose later sweeps read the
    factorisation and the rows again: on a GPU a tile's arrays (megabytes for 128 problems)
    do not stay in the 50 MB L2 cache between sweeps while a hundred tiles run at once."""
    import math

    import jax
    import jax.extend

    def ref_bytes(aval, keys) -> int:
        return len(keys) * aval.shape[-1] * aval.dtype.itemsize

    def static(v):
        """A static index's int, None for a traced one."""
        v = getattr(v, "val", v)
        return int(v) if isinstance(v, int) or hasattr(v, "__index__") else None

    def entry_keys(indices) -> set:
        """The entries the indices of the entry axes take (an indexer's all but the stage,
        first, and the problems, last)."""
        keys = {()}
        for i in indices:
            if hasattr(i, "size"):  # a slice: its entries, or as many anonymous ones
                start = static(i.start)
                ax = (
                    [("?", k) for k in range(i.size)]
                    if start is None
                    else range(start, start + i.size)
                )
            else:  # a traced index: the entry it takes, one per index variable (a loop over
                # rows reads row i's entries i n + j as n variables, n entries a trip)
                ax = [static(i) if static(i) is not None else ("?", i)]
            keys = {k + (v,) for k in keys for v in ax}
        return keys

    def gathered(indexer) -> bool:
        """Whether an indexer gathers (a vector of indices first: a model table read at
        each problem's index)."""
        first = indexer.indices[0]
        return not hasattr(first, "size") and bool(getattr(first, "aval", first).shape)

    def body(j, refs: dict, trips: int, acc: list):
        """Add the loads and stores of ``j`` (refs: var -> kernel ref index) run ``trips``
        times to acc = [read, written]. A gather from a table of K models ([model][stage]
        [entry...], no problem axis) counts the table's K rows of the entries it takes, as a
        shared model counts its entries: once a tile's sweep, however many lanes read them."""
        loads, stores = collections.defaultdict(set), collections.defaultdict(set)
        avals, tables = {}, {}
        for eqn in j.eqns:
            name = eqn.primitive.name
            if name in ("get", "swap"):
                ref = eqn.invars[0]
                leaves = eqn.invars[1:] if name == "get" else eqn.invars[2:]
                indexers = jax.tree_util.tree_unflatten(eqn.params["tree"], leaves)
                who = refs.get(ref, ref)  # the kernel's ref a loop's variable stands for
                avals[who] = ref.aval
                if not indexers:  # the whole ref (a tile's indices)
                    keys = {()}
                elif gathered(indexers[0]):  # [model][stage][entries]
                    keys = entry_keys(indexers[0].indices[2:])
                    tables[who] = ref.aval.shape[0]
                else:
                    keys = entry_keys(indexers[0].indices[1:-1])
                (loads if name == "get" else stores)[who] |= keys
            elif name == "scan":
                inner = eqn.params["jaxpr"].jaxpr
                sub = {
                    v: refs.get(o, o)
                    for v, o in zip(inner.invars, eqn.invars, strict=False)
                    if not isinstance(o, jax.extend.core.Literal)
                }
                body(inner, sub, trips * eqn.params["length"], acc)
            elif name in ("while", "cond", "pjit", "closed_call"):
                for sub_j in jax.extend.core.jaxprs_in_params(eqn.params):
                    body(sub_j, refs, trips, acc)
        acc[0] += trips * sum(
            len(k) * tables[r] * avals[r].dtype.itemsize if r in tables else ref_bytes(avals[r], k)
            for r, k in loads.items()
        )
        acc[1] += trips * sum(ref_bytes(avals[r], k) for r, k in stores.items())

    found = {}

    def visit(j):
        for eqn in j.eqns:
            if eqn.primitive.name == "pallas_call":
                acc = [0, 0]
                kernel = eqn.params["jaxpr"]
                body(kernel, {v: i for i, v in enumerate(kernel.invars)}, 1, acc)
                grid = math.prod(eqn.params["grid_mapping"].grid)
                found[str(eqn.params["name"])] = (acc[0] * grid, acc[1] * grid)
            for sub_j in jax.extend.core.jaxprs_in_params(eqn.params):
                visit(sub_j)

    visit(jaxpr)
    return found


def traffic(hlo: str, start: str | None = None, key=None, kernels: dict | None = None) -> dict:
    """Launches and bytes of an optimised GPU program (``compiled.as_text()``): every fusion,
    custom call (a Pallas kernel among them) and other launch reads its operands and writes its
    outputs once; a ``while`` body counts once per trip (its ``known_trip_count``, else once);
    a ``conditional`` counts one branch, the one that does work (the heaviest of them): a
    branch that only copies its operands out is the engine refresh's skip of a group with
    nothing to load or prepare, which a group of thousands of slots does not take.
    Returns launches, read and written bytes, the Pallas kernels' (``pallas``: launches, read,
    written), the ``while`` loops met (``loops``) and bytes by source line (``by_source``:
    {source: [launches, bytes]}). A launch that updates part of an array in place (a
    dynamic-update-slice, alone or at a fusion's root) reads its other operands and writes the
    update only; a fusion that reads an operand only through slices reads the slices.
    ``start``: the computation to count from (default the entry, once); ``key(line)``: what
    ``by_source`` groups by (default the solver's source line); ``kernels``: {name: (read,
    written)} a launch of the Pallas kernels of that name (:func:`kernel_sweeps`), counted
    instead of their operands once."""
    comps, entry = _computations(hlo)
    where = _source_lines(hlo)
    shapes: dict[str, int] = {}
    for lines in comps.values():
        for ln in lines:
            m = _INSTR.match(ln)
            if m:
                shapes[m.group(1)] = nbytes(m.group(2))
    out = dict(launches=0, read=0, written=0, pallas=[0, 0, 0], loops=0)
    by_source: dict[str, list] = collections.defaultdict(lambda: [0, 0])

    def source(ln: str) -> str:
        called = re.search(r"calls=%?([\w.\-]+)", ln)
        frames = []
        if called and called.group(1) in comps:
            for inner in comps[called.group(1)]:
                frames += re.findall(r"stack_frame_id=(\d+)", inner)
        frames = frames or re.findall(r"stack_frame_id=(\d+)", ln)
        if not frames:
            return "(no source)"
        # the solver's own lines before the small-product helpers they call, where both appear
        ranked = collections.Counter(where(int(f)) for f in frames).most_common()
        own = [s for s, _ in ranked if not s.startswith(HELPERS)]
        return own[0] if own else ranked[0][0]

    def walk(comp: str, times: int):
        for ln in comps.get(comp, []):
            m = _INSTR.match(ln)
            if not m:
                continue
            name, shape, op, rest = m.groups()
            if op in _FREE:
                continue
            if op == "while":
                out["loops"] += 1
                body = re.search(r"body=%?([\w.\-]+)", ln).group(1)
                trips = re.search(r'known_trip_count":\{"n":"(\d+)"', ln)
                walk(body, times * (int(trips.group(1)) if trips else 1))
                continue
            if op in ("call", "conditional"):
                after = ln.split("(", 1)[1].split(")", 1)[1]  # the called computations' names
                called = [c for c in re.findall(r"%([\w.\-]+)", after) if c in comps]
                if op == "call":
                    for c in called:
                        walk(c, times)
                else:  # one branch runs: the one that works
                    branch(called, times)
                continue
            operands = re.findall(r"%([\w.\-]+)", rest.split("), ")[0])
            read, written = sum(shapes.get(o, 0) for o in operands), nbytes(shape)
            called = re.search(r"calls=%?([\w.\-]+)", ln)
            place = _in_place(comps, called.group(1), shapes) if op == "fusion" and called else None
            if place is None and op in _UPDATES:
                place = ([0], shapes.get(_update_operands(op, operands)[1], 0))
            if place is not None:  # the buffer stays where it is: read and write the update
                aliased, update = place
                read -= sum(shapes.get(operands[i], 0) for i in aliased if i < len(operands))
                written = update
            if op == "fusion" and called:
                for i, b in _sliced_reads(comps, called.group(1), shapes).items():
                    if i < len(operands) and (place is None or i not in place[0]):
                        read -= shapes.get(operands[i], 0) - b
            kernel = re.search(r"/(\w+)/pallas_call", ln) if op == "custom-call" else None
            if kernels and kernel and kernel.group(1) in kernels:
                read, written = kernels[kernel.group(1)]
            out["launches"] += times
            out["read"] += times * read
            out["written"] += times * written
            if "pallas" in name or "__gpu$xla.gpu.triton" in ln:
                p = out["pallas"]
                p[0] += times
                p[1] += times * read
                p[2] += times * written
            src = by_source[key(ln) if key else source(ln)]
            src[0] += times
            src[1] += times * (read + written)

    def snapshot():
        return dict(out, pallas=list(out["pallas"])), {k: list(v) for k, v in by_source.items()}

    def restore(state):
        out.clear()
        out.update(state[0])
        by_source.clear()
        by_source.update(state[1])

    def moves_only(comp: str) -> bool:
        """Whether ``comp`` only moves data: copies, transposes, (fused) layout changes."""
        for ln in comps.get(comp, []):
            m = _INSTR.match(ln)
            if not m or m.group(3) in _FREE or m.group(3) in _MOVES:
                continue
            called = re.search(r"calls=%?([\w.\-]+)", ln)
            if m.group(3) == "fusion" and called and moves_only(called.group(1)):
                continue
            return False
        return True

    def branch(names, times):
        # the branch that does work, the heaviest if several: a branch that only copies its
        # operands out (in the layouts the other branch gives them) is the skip of a refresh
        # with nothing to load or prepare, which a group of thousands of slots does not take
        working = [c for c in names if not moves_only(c)] or names
        before, best = snapshot(), None
        for c in working:
            walk(c, times)
            moved = (out["read"] + out["written"], out["launches"])
            if best is None or moved > best[0]:
                best = (moved, snapshot())
            restore(before)
        if best is not None:
            restore(best[1])

    walk(start or entry, 1)
    out["by_source"] = dict(by_source)
    return out


def _sharding(target: str):
    """A sharding on one compile-only GPU of ``target`` (no device needed)."""
    from jax.experimental import topologies
    from jax.sharding import NamedSharding
    from jax.sharding import PartitionSpec as P

    name, bandwidth, memory = TARGETS[target]
    config = _DEVICE.format(name=name, bandwidth=int(bandwidth), memory=memory)
    topo = topologies.get_topology_desc(platform="cuda", target_config=config, topology="1x1x1")
    return NamedSharding(topologies.make_mesh(topo, (1,), ("x",)), P())


def _batch_specs(ocps, batch: int, sharding, shared: set):
    """(vmap's in_axes, the abstract batch) of ``batch`` OCPs shaped as the small batch
    ``ocps``, the fields in ``shared`` without the batch axis (one for every problem)."""
    import jax

    def spec(a, batched):
        shape = (batch, *a.shape[1:]) if batched else a.shape[1:]
        return jax.ShapeDtypeStruct(shape, a.dtype, sharding=sharding)

    axes = type(ocps)(*(None if f in shared else 0 for f in ocps._fields))
    return axes, type(ocps)(*(spec(getattr(ocps, f), f not in shared) for f in ocps._fields))


def _compile(kernel: str, batch: int, mode: str, target: str, shared_model: bool = False):
    """The optimised GPU program of one solver iteration on ``batch`` fastmpc-3d QPs and its
    Pallas kernels' sweeps (:func:`kernel_sweeps`): (HLO text, sweeps); with
    ``shared_model`` the model fields (A, B, c, Q, R) carry no batch axis (one model for every
    problem, as the batch engine solves a Monte Carlo's MPC steps)."""
    import jax

    import rvdjax  # noqa: F401  (float64)
    from rvdjax.problems import fastmpc3d_first_step_batch, perturbed_x0
    from rvdjax.solver import SolverParams, SolverSettings, tracing_for_cuda
    from rvdjax.solver.driver import MODEL_FIELDS, iterate, start

    sharding = _sharding(target)
    settings = (SolverSettings.paper if mode == "paper" else SolverSettings)(kernel=kernel)
    params = SolverParams.for_settings(settings)
    # shapes from a small batch started on the host (as for a GPU: where the Newton step's
    # form carries the Newton system, the state holds it); the GPU program for ``batch``
    small = fastmpc3d_first_step_batch(perturbed_x0(0, 4))
    with tracing_for_cuda():
        ocps, state = jax.jit(jax.vmap(lambda o: start(o, settings, params)))(small)

    axes, ocps = _batch_specs(ocps, batch, sharding, set(MODEL_FIELDS) if shared_model else set())
    state = jax.tree.map(
        lambda a: jax.ShapeDtypeStruct((batch, *a.shape[1:]), a.dtype, sharding=sharding), state
    )
    step = jax.jit(jax.vmap(lambda o, s: iterate(o, settings, params, s), in_axes=(axes, 0)))
    with tracing_for_cuda():  # no GPU backend here: keep the CUDA form in the trace
        traced = step.trace(ocps, state)
        return traced.lower().compile().as_text(), kernel_sweeps(traced.jaxpr.jaxpr)


def _compile_engine(scenario: str, slots: int, target: str, kernel: str = "auto"):
    """One device's segment program of the batch engine for ``scenario`` with the engine's
    accelerator settings (:func:`rvdjax.loop.engine.config.auto_config` on a GPU: every slot in
    one chunk, 4 solver iterations a tick, 128 ticks a segment, the compacted refresh in
    groups of a quarter of the slots, runs to any free slot), compiled for ``target``, with
    the Newton step's form ``kernel``: (HLO text, the EngineConfig, the Pallas kernels'
    sweeps: :func:`kernel_sweeps`)."""
    import jax

    import rvdjax  # noqa: F401  (float64)
    from rvdjax.bench import perturbed_states
    from rvdjax.loop import engine as E
    from rvdjax.loop.engine import config as C
    from rvdjax.loop.engine.stream import _abstract_args
    from rvdjax.scenarios import FlightOptions, get_scenario
    from rvdjax.solver import SolverParams, tracing_for_cuda

    sharding = _sharding(target)
    sc = get_scenario(scenario)
    options = FlightOptions()
    flight = sc.flight(options, settings=sc.settings(options.mode, kernel=kernel))
    loop, params = flight.loop, flight.params
    sp = SolverParams.for_settings(loop.config.settings)
    source = E.arrays_source(perturbed_states(flight.x0, 8))
    cfg = E.EngineConfig(
        slots=slots,
        chunk=slots,
        iterations=C.ACCEL_ITERATIONS,
        ticks_per_segment=C.ACCEL_TICKS,
        refresh="compacted",
        assign="any",
        group=max(1, slots // C.ACCEL_REFRESH_SHARE),
        platform="cuda",
    )
    args = _abstract_args(loop, cfg, source, params, sp)
    args = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=sharding), args)
    with tracing_for_cuda():  # no GPU backend here: keep the CUDA form in the trace
        traced = E.segment_program(loop, cfg, source.fn).trace(*args)
        return traced.lower().compile().as_text(), cfg, kernel_sweeps(traced.jaxpr.jaxpr)


def _compile_solve(kernel: str, batch: int, mode: str, target: str, shared_model: bool = False):
    """The optimised GPU program of a whole ``jit(vmap(solve))`` on ``batch`` fastmpc-3d QPs
    and its Pallas kernels' sweeps: (HLO text, sweeps); with ``shared_model`` one model for
    every QP, passed through as ``sweeps/gpu_benchmark.py`` passes it (``trusted_model``)."""
    import jax

    import rvdjax  # noqa: F401  (float64)
    from rvdjax.problems import fastmpc3d_first_step_batch, perturbed_x0
    from rvdjax.solver import SolverParams, SolverSettings, driver, solve, tracing_for_cuda

    sharding = _sharding(target)
    settings = (SolverSettings.paper if mode == "paper" else SolverSettings)(kernel=kernel)
    params = SolverParams.for_settings(settings)
    small = fastmpc3d_first_step_batch(perturbed_x0(0, 4))
    shared = set(driver.MODEL_FIELDS) if shared_model else set()
    axes, ocps = _batch_specs(small, batch, sharding, shared)

    def one(ocp):
        if not shared_model:
            return solve(ocp, settings)
        sol, ocp_safe, _ = driver._forward_state(ocp, params, None, settings, trusted_model=True)
        return driver.with_objective(ocp_safe, sol)

    with tracing_for_cuda():  # no GPU backend here: keep the CUDA form in the trace
        traced = jax.jit(jax.vmap(one, in_axes=(axes,))).trace(ocps)
        return traced.lower().compile().as_text(), kernel_sweeps(traced.jaxpr.jaxpr)


def _written(path: str, row: dict) -> dict:
    """``row`` appended to the rows file ``path`` (one JSON line), as it is."""
    with open(path, "a", encoding="utf-8") as f:
        f.write(json.dumps(row) + "\n")
    return row


def _outer_loop(comps: dict, comp: str) -> str | None:
    """The body of the first ``while`` met from ``comp`` (through calls): a solve's loop."""
    for ln in comps.get(comp, []):
        m = _INSTR.match(ln)
        if m and m.group(3) == "while":
            return re.search(r"body=%?([\w.\-]+)", ln).group(1)
        called = re.search(r"to_apply=%?([\w.\-]+)", ln) if m and m.group(3) == "call" else None
        found = _outer_loop(comps, called.group(1)) if called else None
        if found:
            return found
    return None


def solve_main(args, kernels, provenance, path) -> int:
    per = 1e3 * args.batch
    rows = []
    for kernel in kernels:
        t0 = time.perf_counter()
        hlo, sweeps = _compile_solve(kernel, args.batch, args.mode, args.target, args.shared_model)
        compile_s = time.perf_counter() - t0
        body = _outer_loop(*_computations(hlo))
        whole, loop = traffic(hlo, kernels=sweeps), traffic(hlo, body, kernels=sweeps)
        row = dict(
            part="solve",
            kernel=kernel + (", shared model" if args.shared_model else ""),
            mode=args.mode,
            target=args.target,
            batch=args.batch,
            loop_launches=loop["launches"],
            loop_pallas=loop["pallas"][0],
            loop_kb=(loop["read"] + loop["written"]) / per,
            launches=whole["launches"],
            kb=(whole["read"] + whole["written"]) / per,
            compile_s=compile_s,
            provenance=provenance,
        )
        rows.append(_written(path, row))
    print(
        f"a {args.mode}-mode jit(vmap(solve)) of {args.batch} fastmpc-3d QPs compiled for an "
        f"{TARGETS[args.target][0]} (no GPU used); KB a problem:"
    )
    print(
        "| form | the loop's body: launches (Pallas) | KB an iteration | whole program, the "
        "loop once: launches | KB | compile |"
    )
    print("| --- | --- | --- | --- | --- | --- |")
    for r in rows:
        print(
            f"| {r['kernel']} | {r['loop_launches']} ({r['loop_pallas']}) | {r['loop_kb']:.1f} | "
            f"{r['launches']} | {r['kb']:.1f} | {r['compile_s']:.1f} s |"
        )
    print(f"rows: {path}")
    return 0


def _compile_maneuver(scenario: str, kernel: str, target: str):
    """The optimised GPU program of one maneuver of ``scenario`` flown alone
    (:func:`rvdjax.loop.fly` with the scenario's published x0 and the Newton step's form
    ``kernel``) and its Pallas kernels' sweeps: (HLO text, sweeps, MPC steps)."""
    import jax

    import rvdjax  # noqa: F401  (float64)
    from rvdjax.loop.kernel import fly
    from rvdjax.scenarios import FlightOptions, get_scenario
    from rvdjax.solver import tracing_for_cuda

    sc = get_scenario(scenario)
    options = FlightOptions()
    flight = sc.flight(options, settings=sc.settings(options.mode, kernel=kernel))
    sharding = _sharding(target)
    args = (flight.params, flight.x0, flight.key, flight.solver_params)
    args = jax.tree.map(
        lambda a: jax.ShapeDtypeStruct(
            jax.numpy.shape(a), jax.numpy.result_type(a), sharding=sharding
        ),
        args,
    )
    with tracing_for_cuda():  # no GPU backend here: keep the CUDA form in the trace
        traced = jax.jit(lambda p, x0, k, sp: fly(flight.loop, p, x0, k, sp)).trace(*args)
        hlo = traced.lower().compile().as_text()
    return hlo, kernel_sweeps(traced.jaxpr.jaxpr), flight.loop.config.n_steps


def _loops(comps: dict) -> list[tuple[str, int | None]]:
    """Every ``while`` of a program: (its body, its known trip count or None)."""
    found = []
    for lines in comps.values():
        for ln in lines:
            m = _INSTR.match(ln)
            if m and m.group(3) == "while":
                trips = re.search(r'known_trip_count":\{"n":"(\d+)"', ln)
                found.append(
                    (
                        re.search(r"body=%?([\w.\-]+)", ln).group(1),
                        int(trips.group(1)) if trips else None,
                    )
                )
    return found


def maneuver_main(args, kernels, provenance, path) -> int:
    rows = []
    for kernel in kernels:
        t0 = time.perf_counter()
        hlo, sweeps, n_steps = _compile_maneuver(args.scenario, kernel, args.target)
        compile_s = time.perf_counter() - t0
        comps, _ = _computations(hlo)
        loops = _loops(comps)
        # the MPC steps' scan (its trip count the steps) and the solve loop (the largest
        # loop of unknown trip count)
        step = next((b for b, n in loops if n == n_steps), None)
        open_ended = [
            (traffic(hlo, b, kernels=sweeps)["launches"], b) for b, n in loops if n is None
        ]
        solve = max(open_ended)[1] if open_ended else None
        if step is None or solve is None:
            print(f"gpu_traffic: no loop over the {n_steps} MPC steps or no solve loop found")
            return 1
        row = dict(
            part="maneuver",
            scenario=args.scenario,
            kernel=kernel,
            target=args.target,
            mpc_steps=n_steps,
            step_launches=traffic(hlo, step, kernels=sweeps)["launches"],
            solve_iteration_launches=max(open_ended)[0],
            compile_s=compile_s,
            provenance=provenance,
        )
        rows.append(_written(path, row))
    print(
        f"one {args.scenario} maneuver flown alone ({rows[0]['mpc_steps']} MPC steps), "
        f"compiled for an {TARGETS[args.target][0]} (no GPU used); launches:"
    )
    print("| form | an MPC step, its solve loop once | the solve loop's iteration | compile |")
    print("| --- | --- | --- | --- |")
    for r in rows:
        print(
            f"| {r['kernel']} | {r['step_launches']} | {r['solve_iteration_launches']} | "
            f"{r['compile_s']:.1f} s |"
        )
    print(f"rows: {path}")
    return 0


def tick(hlo: str, kernels: dict | None = None) -> dict:
    """:func:`traffic` of one tick of an engine segment program (the body of its loop over
    ticks), grouped by the engine's scopes: the solver iterations, the refresh (advance,
    refill, the next MPC step's start), the ring and the rest (the compacted refresh's
    gathers and scatters of the slots, the tick's bookkeeping)."""
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import tick_kernels

    comps, entry = tick_kernels.parse(hlo)
    start = tick_kernels.tick_body(comps, entry)
    return traffic(hlo, start=start, key=tick_kernels.scope, kernels=kernels)


def _fields(t: dict, per: float, bandwidth: float, once: dict | None = None) -> dict:
    """A row's figures from :func:`traffic`'s count: per ``per`` (1e3 x problems or slots:
    KB each) and the time the bytes take at ``bandwidth``; ``once``: the same program's count
    with every kernel's operands read once (the count of this script until 2026-11-28)."""
    extra = {} if once is None else dict(operands_once_kb=(once["read"] + once["written"]) / per)
    return dict(
        **extra,
        launches=t["launches"],
        read_kb=t["read"] / per,
        written_kb=t["written"] / per,
        pallas_launches=t["pallas"][0],
        pallas_kb=(t["pallas"][1] + t["pallas"][2]) / per,
        bound_ms=1e3 * (t["read"] + t["written"]) / bandwidth,
    )


def engine_main(args, provenance, path) -> int:
    t0 = time.perf_counter()
    kernel = args.kernels.split(",")[0]
    hlo, cfg, sweeps = _compile_engine(args.scenario, args.slots, args.target, kernel)
    compile_s = time.perf_counter() - t0
    if args.hlo:
        with open(os.path.join(args.out, f"hlo_engine_{args.scenario}.txt"), "w") as f:
            f.write(hlo)
    t, once = tick(hlo, sweeps), tick(hlo)
    per = 1e3 * args.slots
    row = dict(
        part="engine",
        scenario=args.scenario,
        slots=args.slots,
        target=args.target,
        kernel=kernel,
        iterations_per_tick=cfg.iterations,
        **_fields(t, per, TARGETS[args.target][1], once),
        compile_s=compile_s,
        by_scope={k: [v[0], v[1] / per] for k, v in t["by_source"].items()},
        provenance=provenance,
    )
    _written(path, row)
    total = row["read_kb"] + row["written_kb"]
    print(
        f"one tick of the batch engine, {args.scenario} at {args.slots} slots, compiled for an "
        f"{TARGETS[args.target][0]} (no GPU used; {cfg.iterations} solver iterations a tick; "
        f"kernel {kernel}):"
    )
    print(
        f"{row['launches']} launches ({row['pallas_launches']} Pallas kernels), "
        f"{total:.0f} KB a slot ({row['read_kb']:.0f} read, {row['written_kb']:.0f} written; "
        f"{row['operands_once_kb']:.0f} with each kernel's operands read once), "
        f"{row['bound_ms']:.2f} ms at the card's bandwidth; compiled in {compile_s:.1f} s"
    )
    print("| scope | launches | KB a slot | share |")
    print("| --- | --- | --- | --- |")
    for k, (n, kb) in sorted(row["by_scope"].items(), key=lambda kv: -kv[1][1]):
        print(f"| {k} | {n} | {kb:.0f} | {kb / total:.0%} |")
    print(f"rows: {path}")
    return 0


def _cuda_missing() -> str | None:
    import importlib.util

    try:
        found = any(importlib.util.find_spec(f"jax_plugins.xla_cuda{v}") for v in (12, 13))
    except ImportError:  # no jax_plugins namespace at all
        found = False
    if found:
        return None
    return (
        "gpu_traffic: needs jax's CUDA plugin (pip install 'jax[cuda13]' at this jax's "
        "version); no GPU is needed"
    )


def main(argv=None) -> int:
    from rvdjax.solver.types import KERNELS as ALL

    KERNELS = tuple(k for k in ALL if k != "pallas-fused")  # its compile takes minutes
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("part", nargs="?", default="qp", choices=("qp", "engine", "solve", "maneuver"))
    ap.add_argument("--batch", type=int, default=65536, help="qp: QPs in the batch (>= 1)")
    ap.add_argument(
        "--scenario", default=None, help="engine (thesis-vbar), maneuver (fastmpc-3d): the scenario"
    )
    ap.add_argument("--slots", type=int, default=4096, help="engine: slots (>= 1)")
    ap.add_argument("--kernels", default="auto", help=f"forms, comma-separated: {KERNELS}")
    ap.add_argument("--mode", choices=("accurate", "paper"), default="accurate")
    ap.add_argument("--target", choices=tuple(TARGETS), default="h100")
    ap.add_argument("--padded-blocks", action="store_true", help="the block kernels' padded form")
    ap.add_argument(
        "--shared-model", action="store_true", help="qp: one model (A, B, c, Q, R) for every QP"
    )
    ap.add_argument("--top", type=int, default=12, help="sources of traffic printed per form")
    ap.add_argument("--out", default="results/gpu-traffic", help="directory for the rows")
    ap.add_argument("--hlo", action="store_true", help="also write each compiled program to --out")
    args = ap.parse_args(argv)
    kernels = [k for k in args.kernels.split(",") if k]
    bad = [k for k in kernels if k not in KERNELS]
    if bad or not kernels:
        print(f"gpu_traffic: --kernels must be among {', '.join(KERNELS)}, got {args.kernels!r}")
        return 2
    for name in ("batch", "slots"):
        if getattr(args, name) < 1:
            print(f"gpu_traffic: --{name} must be >= 1, got {getattr(args, name)}")
            return 2
    if args.scenario is None:
        args.scenario = "fastmpc-3d" if args.part == "maneuver" else "thesis-vbar"
    if args.part in ("engine", "maneuver"):
        from rvdjax.scenarios import SCENARIOS

        if args.scenario not in SCENARIOS:
            print(f"gpu_traffic: --scenario must be a named scenario (rvdjax list), got "
                  f"{args.scenario!r}")  # fmt: skip
            return 2
    from rvdjax.outputs import check_dir

    check_dir(args.out, "--out")
    missing = _cuda_missing()
    if missing:
        print(missing)
        return 2
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, "gpu_traffic.jsonl")
    from rvdjax.provenance import benchmark_block
    from rvdjax.solver import lanes

    provenance = benchmark_block("sweeps/gpu_traffic.py", vars(args))
    if args.part == "engine":
        return engine_main(args, provenance, path)
    if args.part == "solve":
        return solve_main(args, kernels, provenance, path)
    if args.part == "maneuver":
        return maneuver_main(args, kernels, provenance, path)
    bandwidth = TARGETS[args.target][1]
    rows = []
    for kernel in kernels:
        t0 = time.perf_counter()
        with lanes.configured(padded_blocks=args.padded_blocks):
            hlo, sweeps = _compile(kernel, args.batch, args.mode, args.target, args.shared_model)
        t, once = traffic(hlo, kernels=sweeps), traffic(hlo)
        if args.hlo:
            variant = ("_padded" if args.padded_blocks else "") + (
                "_shared" if args.shared_model else ""
            )
            name = f"hlo_{kernel}{variant}_{args.mode}.txt"
            with open(os.path.join(args.out, name), "w", encoding="utf-8") as f:
                f.write(hlo)
        compile_s = time.perf_counter() - t0
        per = 1e3 * args.batch
        row = dict(
            kernel=kernel
            + (", padded blocks" if args.padded_blocks else "")
            + (", shared model" if args.shared_model else ""),
            mode=args.mode,
            target=args.target,
            batch=args.batch,
            **_fields(t, per, bandwidth, once),
            compile_s=compile_s,
            loops=t["loops"],
            by_source={k: [v[0], v[1] / per] for k, v in t["by_source"].items()},
            provenance=provenance,
        )
        rows.append(_written(path, row))
    print(
        f"one {args.mode} iteration of {args.batch} fastmpc-3d QPs compiled for an "
        f"{TARGETS[args.target][0]} (no GPU used); KB a problem:"
    )
    print(
        "| form | launches | read | written | total | operands once | Pallas kernels "
        "(launches, KB) | bound | compile |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        total = r["read_kb"] + r["written_kb"]
        print(
            f"| {r['kernel']} | {r['launches']} | {r['read_kb']:.1f} | {r['written_kb']:.1f} | "
            f"{total:.1f} | {r['operands_once_kb']:.1f} | {r['pallas_launches']}, "
            f"{r['pallas_kb']:.1f} | "
            f"{r['bound_ms']:.2f} ms | {r['compile_s']:.1f} s |"
        )
    for r in rows:
        print(f"\n{r['kernel']}: largest sources (launches, KB a problem)")
        top = sorted(r["by_source"].items(), key=lambda kv: -kv[1][1])[: args.top]
        for src, (n, kb) in top:
            print(f"  {kb:7.1f} KB {n:4d}  {src}")
    print(f"rows: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
