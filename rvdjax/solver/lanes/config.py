"""The kernels' static launch configuration, and the one the solver traces them with."""

from __future__ import annotations

import contextlib
import dataclasses

import jax


@dataclasses.dataclass(frozen=True)
class KernelConfig:
    """Static launch configuration of the kernels.

    Attributes:
        block: problems per program (the lanes of one tile); a power of two.
        num_warps: warps per program (Triton): 4 warps = 128 threads, one problem each at
            block = 128.
        interpret: run the kernels in Pallas' interpreter (the CPU; tests).
        fused: the solver's factorisation and first step in one kernel
            (:func:`~rvdjax.solver.lanes.calls.factor_solve`) instead of
            :func:`~rvdjax.solver.lanes.calls.factor` then :func:`~rvdjax.solver.lanes.calls.apply`,
            and a step with its refinement in one kernel
            (:func:`~rvdjax.solver.lanes.calls.apply_refined`) (the solver:
            ``kernel="pallas-fused"``, entry by entry, and ``"pallas-block-fused"``, with
            ``block_io``). On an H200 (2026-11-26) Triton compiled the entry-wise ``factor``
            alone in 51 s and ``apply`` in about 3 s; the entry-wise fused kernel did not finish
            in 165 s on an H100. With ``block_io`` the program XLA compiles for an H100 here,
            Triton's kernels included, took 37 s instead of 14 (65 536 fastmpc-3d QPs).
        block_io: load and store a stage's block of each array at once (entries flattened,
            in at most two power-of-two chunks, split into lane vectors and joined back inside
            the kernel) instead of entry by entry (the solver: ``kernel="pallas-block-io"``).
            Triton's compile time is its coalescing pass, which costs about (loads and
            stores) x (kernel size)^2 (``sweeps/triton_compile_profile.py``); this cuts the
            loads and stores from hundreds to a few.
        solve_block_io: with ``block_io``, the solves (``apply``, ``apply_refined``) load and
            store blocks too; without it (the solver: ``kernel="pallas-block-factor"``,
            ``"pallas-rows"`` and ``"pallas-entries"``) only the factorisation does, and the
            solves read the factorisation, the model and the right-hand sides entry by entry,
            straight from their arrays (a solve's kernel is small enough to compile in seconds
            either way). A block's split into lane vectors and join back pass through shared
            memory, with a barrier each: assembled by ptxas for an H100, the block form of the
            refined solve holds 585 barriers, the entry-wise form none
            (``sweeps/gpu_registers.py``).
        padded_blocks: with ``block_io``, the block arrays hold each stage's entries padded to a
            power of two (one load or store a stage, but a padded copy of every input and a
            slice of every output outside the kernel), instead of the entries as they are,
            read and written in two overlapping power-of-two chunks
            (:func:`~rvdjax.solver.lanes.refs._chunks`). The padded form was the only one until
            2026-11-28; in the program compiled for an H100 its pads and slices moved 123 of an
            accurate iteration's 765 KB a problem (``sweeps/gpu_traffic.py``,
            docs/benchmark.md). It stays for comparison (``sweeps/gpu_benchmark.py
            --padded-blocks``).
        model_blocks_only: with ``block_io``, the factorisation reads only the model [B, A] in
            blocks and every other operand, and its outputs, entry by entry (the solver:
            ``kernel="pallas-entries"``). Assembled for an H100, the factorisation's kernel
            then holds 12 barriers instead of 369 in thesis-vbar's engine (the model from the
            phase table), 108 instead of 465 for QPs with a model each and none instead of 357
            with one model, with as many spills or fewer; read entry by entry, the model's 54
            entries a stage made it spill more (docs/benchmark.md).

    The solver takes ``fused``, ``block_io``, ``solve_block_io`` and ``model_blocks_only`` from
    its kernel name, and the rest from :func:`default_config`.
    """

    block: int = 128
    num_warps: int = 4
    interpret: bool = False
    fused: bool = False
    block_io: bool = False
    solve_block_io: bool = True
    padded_blocks: bool = False
    model_blocks_only: bool = False


_DEFAULT = [KernelConfig()]


def default_config() -> KernelConfig:
    """The launch configuration the solver's kernels are traced with."""
    return _DEFAULT[0]


@contextlib.contextmanager
def configured(**changes):
    """Trace the solver's kernels with another launch configuration inside the block (e.g.
    ``block=64`` in a benchmark). JAX's caches are cleared on entry and exit when the
    configuration changes: a jitted solve would otherwise reuse a program traced with the
    other one (the configuration is not part of its cache key)."""
    old = _DEFAULT[0]
    new = dataclasses.replace(old, **changes)
    if new != old:
        jax.clear_caches()
    _DEFAULT[0] = new
    try:
        yield new
    finally:
        _DEFAULT[0] = old
        if new != old:
            jax.clear_caches()
