"""Pieces shared by the families whose model is time invariant and whose cost tracks a
reference (rendezvous, planar docking, POSEIDYN): the OCP assembled from the model, the
reference and the constraint blocks, and the family functions that read fixed parameters.

Their parameters carry ``A``, ``B`` (the discrete model), ``Q``, ``R``, ``Q_f`` (stage and
terminal weights) and ``ts`` (the sample time, s); their configuration carries ``N``.
"""

from __future__ import annotations

import jax.numpy as jnp

from rvdjax.constraints import Block, stack, thrust_box
from rvdjax.loop.plant import Plant
from rvdjax.ocp import OCP, time_invariant_model


def tracking_ocp(model, x, x_ref, state_blocks, input_box: Block) -> OCP:
    """The OCP sum_t (x_t+1 - x_ref,t)' Q_t (x_t+1 - x_ref,t) + u_t' R_t u_t (paper 000 Eq. 1)
    over ``model`` = stage-wise (A, B, c, Q, R), from the state ``x``, with the stacked
    ``state_blocks`` as soft state rows and ``input_box`` as the hard input rows."""
    Fx, fx, rho, x_mask = stack(state_blocks)
    return OCP(
        x0=x, x_ref=x_ref, Fx=Fx, fx=fx, rho=rho, x_mask=x_mask, **fixed_fields(model, input_box)
    )


def fixed_fields(model, input_box: Block) -> dict:
    """The fields of :func:`tracking_ocp`'s OCP that do not depend on the state: the model
    (A, B, c, Q, R), zero linear costs (q, r) and the input rows (Fu, fu, u_mask)."""
    A, B, c, Q, R = model
    N, nx = c.shape
    return dict(
        A=A,
        B=B,
        c=c,
        Q=Q,
        R=R,
        q=jnp.zeros((N, nx), c.dtype),
        r=jnp.zeros((N, B.shape[-1]), c.dtype),
        Fu=input_box.F,
        fu=input_box.f,
        u_mask=input_box.mask,
    )


def model(p, fc, g=None):
    """(A, B, c, Q, R) of the OCP: time invariant, the terminal weight on the last stage (the
    same for every guidance state ``g``)."""
    return time_invariant_model(p.A, p.B, p.Q, p.R, p.Q_f, fc.N)


def tracking_fixed(p, fc, g=None):
    """The family hook ``model`` of a family whose OCP is ``tracking_ocp(model(p, fc), ...,
    thrust_box(p.u_max, fc.N))``: :func:`fixed_fields`, the same for every guidance state
    ``g``, which the batch engine rebuilds instead of storing per slot (runs with shared
    parameters share them unbatched)."""
    fields = fixed_fields(model(p, fc), thrust_box(p.u_max, fc.N))
    del fields["u_mask"]  # stays in the slot (rvdjax.loop.engine.slots.ROWS_REBUILT)
    return fields


def control(p, fc, g, sol):
    """The first input of the plan (receding horizon)."""
    return sol.u[0]


def sample_time(p, g):
    return p.ts


def truth_model(p, g):
    return p.A, p.B


def weight_diag(W):
    """The diagonals (..., n) of weight matrices (..., n, n)."""
    return jnp.diagonal(W, axis1=-2, axis2=-1)


def with_weight_diag(W, d):
    """``W`` rescaled symmetrically so that its diagonal becomes ``d``: S W S with S =
    diag(sqrt(d / diag W)) (exactly diag(d) for a diagonal W; positive (semi)definiteness is
    kept). The tuner's weights are diagonals (DESIGN §7: log-diagonals of Q and R)."""
    s = jnp.sqrt(d / weight_diag(W))
    return W * s[..., :, None] * s[..., None, :]


def weight_tunables(phases: str = "") -> dict:
    """The ``Q`` and ``R`` :class:`~rvdjax.loop.family.Tunable` entries (log-diagonals)."""
    from rvdjax.loop.family import Tunable

    where = f" {phases}" if phases else ""
    return {
        "Q": Tunable(
            f"state weight diagonal{where} (log scale)",
            get=lambda p: weight_diag(p.Q),
            set=lambda p, v: p._replace(Q=with_weight_diag(p.Q, v)),
            derived=True,
        ),
        "R": Tunable(
            f"input weight diagonal{where} (log scale)",
            get=lambda p: weight_diag(p.R),
            set=lambda p, v: p._replace(R=with_weight_diag(p.R, v)),
            derived=True,
        ),
    }


def derive_terminal(p, names, scale=1.0):
    """Q_f = scale * P_bar, P_bar the DARE solution of (A, B, Q, R), when Q, R or the model
    changed (how every time-invariant family builds its terminal weight)."""
    from rvdjax.dynamics import dare

    if not names:
        return p
    return p._replace(Q_f=scale * dare(p.A, p.B, p.Q, p.R))


def smooth_norm(v, eps=1e-9):
    """sqrt(|v|^2 + eps^2): the Euclidean norm with a finite derivative at v = 0 [units of v]."""
    return jnp.sqrt(jnp.sum(v * v, axis=-1) + eps * eps)


def smooth_excess(d, tol):
    """Smooth max(0, d - tol) (width 0.1 tol): the distance left to a docking region of
    radius ``tol``. Near 0 where a run docks, so a docking step earlier or later moves the
    tuning surrogate's time integral (:mod:`rvdjax.tune.loss`) by almost nothing."""
    z = d - tol
    w = 0.1 * tol
    return 0.5 * (z + jnp.sqrt(z * z + w * w))


def field_tunable(field: str, description: str, **options):
    """A :class:`~rvdjax.loop.family.Tunable` reading and replacing the parameters' ``field``
    (``options``: transform, bounds, derived)."""
    from rvdjax.loop.family import Tunable

    return Tunable(
        description,
        get=lambda p: getattr(p, field),
        set=lambda p, v: p._replace(**{field: v}),
        **options,
    )


def horizon(fc) -> int:
    """The OCP's horizon of a family whose configuration has one ``N`` (steps)."""
    return fc.N


#: The hooks most families share (``Hooks.of(globals(), **SHARED_HOOKS, ...)``): u_0 of the plan,
#: the phase's sample time and model, one horizon ``N``.
SHARED_HOOKS = dict(
    control=control, sample_time=sample_time, truth_model=truth_model, horizon=horizon
)


def make_plant(mass, Ac, Bc, **fields) -> Plant:
    """The :class:`~rvdjax.loop.plant.Plant` of a family's parameters: the mass [kg], the
    continuous model with its force input [N, N m] (the truth integrates it under thruster
    pulses, :mod:`rvdjax.actuators.response`) and the other plant fields (``orbit``, ``drag``,
    ``disturbances``; the thrusters are attached by the scenario)."""
    return Plant(mass=jnp.asarray(mass), Ac=jnp.asarray(Ac), Bc=jnp.asarray(Bc), **fields)
