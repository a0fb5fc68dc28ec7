"""sweeps/gpu_profile.py: a profiler trace's kernels summed by name and matched to the HLO."""

import os
import sys

import jax
import jax.numpy as jnp

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "sweeps"))
import gpu_profile  # noqa: E402


def test_trace_kernels_are_summed_and_matched_to_their_hlo(tmp_path):
    """Three calls of a program of one fusion give that fusion three calls in the trace, and
    its name leads to the jax operations that made it."""
    x = jnp.linspace(0.0, 1.0, 4096)
    compiled = jax.jit(lambda v: jnp.sum(jnp.sin(v) * 3.0)).lower(x).compile()
    jax.block_until_ready(compiled(x))
    with jax.profiler.trace(str(tmp_path)):
        for _ in range(3):
            jax.block_until_ready(compiled(x))
    rows, planes = gpu_profile.kernel_times(str(tmp_path))
    assert planes and rows
    assert rows == sorted(rows, key=lambda r: -r["total_ms"])
    sources = gpu_profile.hlo_sources(compiled.as_text())
    matched = [r for r in rows if r["name"] in sources]
    assert matched, [r["name"] for r in rows]
    assert all(r["calls"] == 3 for r in matched)
    assert any("sin" in sources[r["name"]] or "reduce" in sources[r["name"]] for r in matched)
