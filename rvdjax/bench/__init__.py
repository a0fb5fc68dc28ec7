"""Benchmarks: QP solves against the peer solvers (:mod:`.qp`) and closed-loop maneuvers per
second (:mod:`.closed_loop`)."""

from __future__ import annotations

from rvdjax.bench.closed_loop import (
    FAMILY_SCENARIOS,
    closed_loop_batch_benchmark,
    format_closed_loop,
    perturbed_states,
)
from rvdjax.bench.qp import BenchConfig, format_table, machine_info, run_benchmark

__all__ = [
    "BenchConfig",
    "run_benchmark",
    "format_table",
    "machine_info",
    "FAMILY_SCENARIOS",
    "perturbed_states",
    "closed_loop_batch_benchmark",
    "format_closed_loop",
]
