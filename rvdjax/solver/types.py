"""Types of the solver: static settings, traced parameters, statuses, plans and solutions.

The split follows what a change costs. :class:`SolverSettings` is static (hashable, part of
the compiled program: mode, linear algebra, iteration caps); :class:`SolverParams` holds the
numbers a user tunes (kappa, the line-search constants, tolerances) as traced arrays, so they
can be batched with ``jax.vmap`` and differentiated without a recompile.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["Status", "SolverSettings", "SolverParams", "Solution", "Plan"]

MODES = ("paper", "accurate", "barrier", "dual")
METHODS = ("riccati", "dense")
BACKENDS = ("rvdjax", "clarabel", "piqp", "daqp", "daqp-condensed", "hpipm")
PAPER_STARTS = ("feasible", "warm", "track")
STEP_FRACTIONS = ("adaptive", "fixed")


class KernelForm(NamedTuple):
    """What a Pallas form of the Newton step runs (``SolverSettings.kernel``; the kernels:
    :mod:`rvdjax.solver.lanes` and :mod:`rvdjax.solver.rows_kernel`).

    Attributes:
        block_io: the factorisation's kernel loads and stores a stage's blocks at once
            (:class:`rvdjax.solver.lanes.KernelConfig`), instead of entry by entry.
        solve_block_io: with ``block_io``, the solves' kernels do too.
        fused: the factorisation and the first step are one kernel, and a step and its
            refinement another (:func:`rvdjax.solver.lanes.factor_solve`,
            :func:`~rvdjax.solver.lanes.apply_refined`).
        rows: the accurate mode's row work runs as three kernels too, before, between and
            after the solves (:mod:`rvdjax.solver.rows_kernel`).
        rows_block_io: those load and store blocks, instead of entry by entry with the soft
            rows in a loop.
        model_blocks_only: with ``block_io``, the factorisation reads only the model [B, A]
            in blocks, every other operand and its outputs entry by entry.
        carried: with ``rows``, the corrector's step kernel also forms the next iteration's
            Newton system at the new point, which the solve's state carries
            (:attr:`rvdjax.solver.pd_algebra.PDState.system`): an iteration is four kernels,
            without the blocks' kernel (the start forms the first system).
    """

    block_io: bool = False
    solve_block_io: bool = True
    fused: bool = False
    rows: bool = False
    rows_block_io: bool = False
    model_blocks_only: bool = False
    carried: bool = False


# the Newton step's Pallas forms, in the order they were built (docs/solver.md measures them)
PALLAS_FORMS = {
    "pallas": KernelForm(),
    "pallas-block-io": KernelForm(block_io=True),
    "pallas-block-factor": KernelForm(block_io=True, solve_block_io=False),
    "pallas-fused": KernelForm(fused=True),
    "pallas-block-fused": KernelForm(block_io=True, fused=True),
    "pallas-block-rows": KernelForm(block_io=True, fused=True, rows=True, rows_block_io=True),
    "pallas-rows": KernelForm(block_io=True, solve_block_io=False, fused=True, rows=True),
    # "pallas-rows" with the factorisation entry by entry too, but for the model [B, A]
    "pallas-entries": KernelForm(
        block_io=True, solve_block_io=False, fused=True, rows=True, model_blocks_only=True
    ),
    # "pallas-entries" with the next Newton system formed by the step's kernel
    "pallas-carried": KernelForm(
        block_io=True,
        solve_block_io=False,
        fused=True,
        rows=True,
        model_blocks_only=True,
        carried=True,
    ),
}
# every form of the Newton step (rvdjax.solver.riccati, which takes them from here): "auto",
# XLA's loops, the Pallas kernels and their algebra as XLA loops
KERNELS = ("auto", "xla", *PALLAS_FORMS, "unrolled")


class Status:
    """Integer status codes of a solve (``Solution.status``)."""

    CONVERGED = 0  # stopping test met
    MAX_ITER = 1  # iteration cap reached; the last iterate is returned
    INFEASIBLE = 2  # state constraints cannot be met (soft penalty active at the optimum),
    #                 or no strictly feasible input exists
    NONFINITE = 3  # the step became non-finite; the last finite iterate is returned

    names = ("converged", "max_iter", "infeasible", "nonfinite")

    @classmethod
    def name(cls, code: int) -> str:
        return cls.names[int(code)]

    @classmethod
    def counts(cls, status, active):
        """(4,) number of entries with each status among the ``active`` ones."""
        return jnp.stack([jnp.sum(active & (status == k)) for k in range(len(cls.names))])


@dataclasses.dataclass(frozen=True)
class SolverSettings:
    """Static solver configuration (hashable: a change recompiles).

    Attributes:
        mode: "paper" (fixed kappa, Algorithm 1 of paper 000), "accurate" (primal-dual
            barrier continuation, the default), "barrier" (primal barrier continuation) or
            "dual" (paper 001's solver: ``max_iter`` multiplicative updates of the PQP dual
            method, :mod:`rvdjax.solver.dual`; through :func:`solve` only, not the batch
            engine's start / iterate / finish).
        method: "riccati" (structured step) or "dense" (ISNM, dense KKT solve).
        max_iter: Newton iteration cap.
        max_line_search: cap on backtracking steps per iteration (when it is reached the
            last, smallest step is taken).
        line_search_batch: trial step lengths evaluated at once by the backtracking line
            search (the first accepted one is taken, as in sequential backtracking; a batch
            of problems then waits for its slowest member's line search in steps of this
            many trials instead of one).
        backend: "rvdjax" (this solver) or "clarabel": the same OCP solved by Clarabel on the
            host through ``jax.pure_callback`` — the reference "Clarabel in the loop" for any
            jitted closed loop (not differentiable; batches are solved one by one); "piqp",
            "daqp", "daqp-condensed": the same with a peer solver (the ``peers`` extra;
            :mod:`rvdjax.peers`); "hpipm": with HPIPM, where its library is installed
            (:mod:`rvdjax.peers_hpipm`).
        paper_start: paper mode's starting states. "feasible" (default): the states the
            warm-start inputs produce through the dynamics, so the equality residual is zero
            from the first iterate and an iterate cut at ``max_iter`` is a flyable plan.
            "warm": the warm start's own states (Algorithm 1's infeasible start, paper 000
            Sec. III.D: "the solution may not be primal feasible"). "track": feasible, from
            inputs that follow the warm start's states from the new x0 (the LQR correction
            with the OCP's own Q, R; one extra Riccati solve). docs/reproduction.md gives the
            measurements behind the default.
        kernel: how the Riccati sweeps of the Newton step run. "auto" (default):
            "pallas-rows" on a CUDA GPU, XLA's loops elsewhere, chosen by the device the
            program is compiled for; "xla": XLA's loops everywhere; "pallas": GPU kernels
            (:mod:`rvdjax.solver.lanes`), compiled for a CUDA GPU and interpreted elsewhere
            (the tests check them there), loading and storing entry by entry;
            "pallas-block-io": the same with block loads and stores (a compile of seconds instead of
            over a minute on a GPU); "pallas-block-factor": block loads and stores in the
            factorisation only, the solves entry by entry; "pallas-fused": the factorisation and
            first step in one kernel, and the corrector's step with its refinement in another;
            "pallas-block-fused": the same with block loads and stores; "pallas-block-rows":
            that, and the accurate mode's row work as two more kernels: between its two solves
            (the predictor's step length, Mehrotra's sigma, the corrector's right-hand side)
            and after them (the corrector's step length, the complementarity and the dual
            residual's row terms) (:mod:`rvdjax.solver.rows_kernel`); "pallas-rows": the same
            kernels with the solves and the row work loading and storing entry by entry (the
            factorisation in blocks: no shared memory, no barriers); "unrolled": the
            kernels' entry-by-entry algebra as XLA loops (:mod:`rvdjax.solver.unrolled`). They
            give the same iterates to rounding. The measurements behind "auto" are in
            docs/solver.md.
        step_fraction: how far to the boundary the accurate mode's corrector steps:
            "adaptive" (default), 1 - sigma of the way, between 0.99 and 0.9999 (fewer
            iterations: Nocedal & Wright 2006, Sec. 14.2); "fixed", 0.99 of the way. A solve
            under differentiation (``jax.grad``, ``jax.vjp``) runs "fixed" whatever this says:
            its iterates stay near the central path, where the implicit derivative, which holds
            each row's complementarity product fixed, is accurate (docs/solver.md). Both stop
            at the same tolerances.
    """

    mode: str = "accurate"
    method: str = "riccati"
    max_iter: int = 100
    max_line_search: int = 40
    line_search_batch: int = 8
    backend: str = "rvdjax"
    paper_start: str = "feasible"
    kernel: str = "auto"
    step_fraction: str = "adaptive"

    def __post_init__(self):
        for name, allowed in (
            ("mode", MODES),
            ("method", METHODS),
            ("backend", BACKENDS),
            ("paper_start", PAPER_STARTS),
            ("kernel", KERNELS),
            ("step_fraction", STEP_FRACTIONS),
        ):
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name} must be one of {allowed}, got {getattr(self, name)!r}")
        for name in ("max_iter", "line_search_batch"):
            v = getattr(self, name)
            if not (isinstance(v, (int, np.integer)) and v >= 1):
                raise ValueError(f"{name} must be an integer >= 1, got {v!r}")
        v = self.max_line_search
        if not (isinstance(v, (int, np.integer)) and v >= 0):
            raise ValueError(f"max_line_search must be an integer >= 0, got {v!r}")

    @classmethod
    def paper(cls, **overrides) -> SolverSettings:
        """Paper 000 Sec. IV.A: at most 10 iterations (kappa, alpha, beta: :meth:`SolverParams.
        paper`). Algorithm 1 backtracks until the residual decreases, without a cap; the
        fixed-shape loop needs one, so it is set where t has shrunk to 0.95^300 ~ 2e-7."""
        base = dict(mode="paper", max_iter=10, max_line_search=300)
        base.update(overrides)
        return cls(**base)

    @classmethod
    def accurate(cls, **overrides) -> SolverSettings:
        return cls(**overrides)


class SolverParams(NamedTuple):
    """Traced solver parameters (scalars; batch them with ``jax.vmap``, differentiate them).

    Attributes:
        kappa: barrier weight in paper mode (paper 000 Sec. IV.A: 0.05).
        alpha, beta: backtracking line-search parameters (paper 000: 0.01, 0.95).
        tol: relative tolerance: residual (paper mode), gap (accurate, barrier modes).
            Floored at 1e3 machine epsilon.
        kappa0_rel: accurate / barrier modes: first kappa = kappa0_rel (1 + |J(start)|) / m.
        kappa_factor: barrier mode: kappa is divided by this when the iterate is centred.
        centring: barrier mode: centred when decrement^2 / 2 <= centring m kappa.
        violation_tol: a soft state row counts as violated above this distance
            (row-normalised units of the state, e.g. metres).
        derivative_probe: no effect on the solve. The implicit derivative returns, as its
            cotangent, the number of back-solves it set to zero because they were not
            finite (:func:`rvdjax.solver.implicit.implicit_bwd`): the derivative of a loss
            with respect to it counts them, so a zeroed derivative is never silent.
    """

    kappa: jnp.ndarray | float = 0.05
    alpha: jnp.ndarray | float = 0.01
    beta: jnp.ndarray | float = 0.5
    tol: jnp.ndarray | float = 1e-9
    kappa0_rel: jnp.ndarray | float = 1.0
    kappa_factor: jnp.ndarray | float = 10.0
    centring: jnp.ndarray | float = 1.0
    violation_tol: jnp.ndarray | float = 1e-6
    derivative_probe: jnp.ndarray | float = 0.0

    @classmethod
    def paper(cls, **overrides) -> SolverParams:
        """Paper 000 Sec. IV.A: kappa = 0.05, alpha = 0.01, beta = 0.95, tol = 1e-9."""
        base = dict(kappa=0.05, alpha=0.01, beta=0.95, tol=1e-9)
        base.update(overrides)
        return cls(**base).checked()

    @classmethod
    def accurate(cls, **overrides) -> SolverParams:
        return cls(**overrides).checked()

    @classmethod
    def for_settings(cls, settings: SolverSettings, **overrides) -> SolverParams:
        """The defaults of ``settings.mode`` (paper 000's constants in paper mode)."""
        if settings.mode == "paper":
            return cls.paper(**overrides)
        return cls.accurate(**overrides)

    def checked(self) -> SolverParams:
        """Range-check the concrete entries (tracers pass); ValueError names the field."""
        bounds = {
            "kappa": (0.0, None),
            "alpha": (0.0, 0.5),
            "beta": (0.0, 1.0),
            "tol": (0.0, None),
            "kappa0_rel": (0.0, None),
            "kappa_factor": (1.0, None),
            "centring": (0.0, None),
            "violation_tol": (0.0, None),
        }
        for name, (lo, hi) in bounds.items():
            v = getattr(self, name)
            if isinstance(v, jax.core.Tracer):
                continue
            a = np.asarray(v, dtype=float)
            ok = np.all(np.isfinite(a)) and np.all(a > lo) and (hi is None or np.all(a < hi))
            if not ok:
                rng = f"({lo:g}, {'inf' if hi is None else f'{hi:g}'})"
                raise ValueError(f"solver parameter {name} must be in {rng}, got {v!r}")
        return self

    def astype(self, dtype) -> SolverParams:
        return SolverParams(*(jnp.asarray(v, dtype) for v in self))


class Solution(NamedTuple):
    """Result of one solve. Batched solves carry a leading batch axis on every field.

    Attributes:
        u: (N, nu) planned inputs u_k .. u_{k+N-1}.
        x: (N, nx) planned states x_{k+1} .. x_{k+N}.
        nu: (N, nx) multipliers of the dynamics (see :mod:`rvdjax.solver.kkt` for the sign).
        objective: QP objective at (u, x), soft rows as rho * max(0, g) (no barrier term).
        kappa: barrier weight of the returned iterate.
        iterations: Newton iterations taken.
        residual: relative KKT residual of the barrier problem at the returned iterate.
        status: :class:`Status` code.
    """

    u: jnp.ndarray
    x: jnp.ndarray
    nu: jnp.ndarray
    objective: jnp.ndarray
    kappa: jnp.ndarray
    iterations: jnp.ndarray
    residual: jnp.ndarray
    status: jnp.ndarray


class Plan(NamedTuple):
    """A warm start: u (N, nu), x (N, nx), nu (N, nx) — e.g. :func:`shift_solution`."""

    u: jnp.ndarray
    x: jnp.ndarray
    nu: jnp.ndarray
