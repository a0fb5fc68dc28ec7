"""sweeps/gpu_profile.py: a profiler trace's kernels summed by name and matched to the HLO."""

import inspect
import os
import sys

import jax
import jax.numpy as jnp
import pytest
from jax import lax

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "sweeps"))
import gpu_profile  # noqa: E402


def test_trace_kernels_are_summed_and_matched_to_their_hlo(tmp_path):
    """Three calls of a program of one fusion give that fusion three calls in the trace, and
    its name leads to the jax operations that made it and to the line that wrote them."""
    x = jnp.linspace(0.0, 1.0, 4096)
    line = inspect.currentframe().f_lineno + 1
    compiled = jax.jit(lambda v: jnp.sum(jnp.sin(v) * 3.0)).lower(x).compile()
    jax.block_until_ready(compiled(x))
    with jax.profiler.trace(str(tmp_path)):
        for _ in range(3):
            jax.block_until_ready(compiled(x))
    rows, planes = gpu_profile.kernel_times(str(tmp_path))
    assert planes and rows
    assert rows == sorted(rows, key=lambda r: -r["self_ms"])
    sources = gpu_profile.hlo_sources(compiled.as_text())
    matched = [r for r in rows if r["name"] in sources]
    assert matched, [r["name"] for r in rows]
    assert all(r["calls"] == 3 for r in matched)
    assert any("sin" in sources[r["name"]] or "reduce" in sources[r["name"]] for r in matched)
    # the source line, from the metadata or (jax 0.10) the stack frame tables after the module
    where = {gpu_profile.source_line(sources[r["name"]]) for r in matched}
    assert f"test_gpu_profile.py:{line}" in {w.split(os.sep)[-1] for w in where}, where
    # and the kernels' time summed by that line
    for r in rows:
        r["source"] = sources.get(r["name"])
    lines = gpu_profile.by_line(rows)
    assert abs(sum(r["self_ms"] for r in lines) - sum(r["self_ms"] for r in rows)) < 1e-9
    assert lines == sorted(lines, key=lambda r: -r["self_ms"])


def test_a_host_thunk_that_runs_others_keeps_only_its_own_time(tmp_path):
    """On the CPU a conditional's thunk runs its branch's thunks: its own time leaves theirs
    out, so the rows' own times add up to no more than the outermost thunks' time."""
    if jax.default_backend() != "cpu":
        pytest.skip("a device's kernels do not nest")
    x = jnp.linspace(0.0, 1.0, 1 << 16)

    def branch(f):
        return lambda v: jnp.sum(f(v) * jnp.exp(v) + jnp.sqrt(v + 1.0))

    compiled = jax.jit(lambda p, v: lax.cond(p, branch(jnp.sin), branch(jnp.cos), v))
    compiled = compiled.lower(True, x).compile()
    jax.block_until_ready(compiled(True, x))
    with jax.profiler.trace(str(tmp_path)):
        for _ in range(3):
            jax.block_until_ready(compiled(True, x))
    rows, _ = gpu_profile.kernel_times(str(tmp_path))
    cond = [r for r in rows if r["name"].startswith("cond")]
    assert len(cond) == 1 and cond[0]["calls"] == 3, [r["name"] for r in rows]
    # the branch's work (a 65 536-long sine, exponential and square root) is the cond's
    # time, not its own
    assert cond[0]["self_ms"] < 0.5 * cond[0]["total_ms"], cond
    inner = [r for r in rows if r is not cond[0] and r["total_ms"] > 0.5 * cond[0]["total_ms"]]
    assert inner and all(r["total_ms"] <= cond[0]["total_ms"] for r in inner), rows
    assert all(r["self_ms"] >= 0 for r in rows)
    assert not any(r["name"].endswith("(wait for completion)") for r in rows)
