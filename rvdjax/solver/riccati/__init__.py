"""The structured Newton step: the Riccati recursion on the KKT system of
:mod:`rvdjax.solver.kkt`, and the batching rules that run it on XLA's loops or the GPU kernels.

:func:`riccati_solve` eliminates the system stage by stage (a discrete Riccati recursion on
the KKT system, equivalent to the block Cholesky factorisation of Y = C Phi^-1 C^T of
paper 000 Eqs. 24-26): O(N (nx + nu)^3) work, `lax.scan` over stages, no dense matrix. Under
``vmap``, custom batching rules choose the layout (batch axis last or first) or the kernels of
:mod:`rvdjax.solver.lanes`; derivatives are those of the dot form. Notation and sign
convention as in :mod:`rvdjax.solver.kkt`.

The modules: :mod:`~rvdjax.solver.riccati.recursion` (the types and XLA's recursion),
:mod:`~rvdjax.solver.riccati.xla_rules` and :mod:`~rvdjax.solver.riccati.lane_rules` (the
batching rules for XLA's loops and for the kernels) and :mod:`~rvdjax.solver.riccati.ops`
(the operations the solver calls, dispatched by device and form; the device's side is
:mod:`rvdjax.solver.platform`).
"""

from __future__ import annotations

from rvdjax.solver.platform import (  # noqa: F401  (their home until 2026-12-07: still found here)
    AUTO_ON_CUDA,
    cuda_or_default,
    kernel_on,
    traces_cuda,
    tracing_for_cuda,
)
from rvdjax.solver.riccati.ops import (
    REFINED_IN_KERNEL,
    ROWS_BLOCK_IO,
    ROWS_IN_KERNEL,
    SYSTEM_CARRIED,
    riccati_apply,
    riccati_apply_refined,
    riccati_factor,
    riccati_factor_solve,
    riccati_solve,
)
from rvdjax.solver.riccati.recursion import (  # noqa: F401  (whole: as before)
    ModelTable,
    NewtonStep,
    RiccatiFactor,
    SymStored,
    newton_residual,
    whole,
)
from rvdjax.solver.riccati.xla_rules import BATCH_LAST_MAX
from rvdjax.solver.types import KERNELS

__all__ = [
    "ModelTable",
    "NewtonStep",
    "SymStored",
    "RiccatiFactor",
    "riccati_factor",
    "riccati_apply",
    "riccati_solve",
    "KERNELS",
    "riccati_factor_solve",
    "riccati_apply_refined",
    "newton_residual",
    "REFINED_IN_KERNEL",
    "ROWS_IN_KERNEL",
    "ROWS_BLOCK_IO",
    "SYSTEM_CARRIED",
    "BATCH_LAST_MAX",
]
