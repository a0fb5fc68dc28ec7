"""The closed loop: one kernel for every guidance family, and the batch engine.

:mod:`.family` (what a family supplies), :mod:`.plant` (the truth step), :mod:`.kernel`
(``init`` / ``step`` / ``fly``), :mod:`.actuation` (command to truth input), :mod:`.metrics`
(the figures of merit and the table of their fields), :mod:`.engine` (many runs through a fixed set
of slots), :mod:`.reference` (the same step driven from Python with Clarabel).
"""

from rvdjax.loop.family import Family, Layout
from rvdjax.loop.kernel import (
    Loop,
    LoopConfig,
    LoopState,
    Metrics,
    RunStatus,
    StepInfo,
    advance,
    fly,
    init,
    metrics,
    prepare,
    step,
)

__all__ = [
    "Family",
    "Layout",
    "Loop",
    "LoopConfig",
    "LoopState",
    "Metrics",
    "RunStatus",
    "StepInfo",
    "advance",
    "fly",
    "init",
    "metrics",
    "prepare",
    "step",
]
