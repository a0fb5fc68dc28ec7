"""Pieces shared by the families whose model is time invariant and whose cost tracks a
reference (rendezvous, planar docking, POSEIDYN): the OCP assembled from the model, the
reference and the constraint blocks, and the family functions that read fixed parameters.

Their parameters carry ``A``, ``B`` (the discrete model), ``Q``, ``R``, ``Q_f`` (stage and
terminal weights) and ``ts`` (the sample time, s); their configuration carries ``N``.
"""

from __future__ import annotations

import jax.numpy as jnp

from rvdjax.constraints import Block, stack
from rvdjax.ocp import OCP, time_invariant_model


def tracking_ocp(model, x, x_ref, state_blocks, input_box: Block) -> OCP:
    """The OCP sum_t (x_t+1 - x_ref,t)' Q_t (x_t+1 - x_ref,t) + u_t' R_t u_t (paper 000 Eq. 1)
    over ``model`` = stage-wise (A, B, c, Q, R), from the state ``x``, with the stacked
    ``state_blocks`` as soft state rows and ``input_box`` as the hard input rows."""
    A, B, c, Q, R = model
    N, nx = x_ref.shape
    Fx, fx, rho, x_mask = stack(state_blocks)
    return OCP(
        A=A,
        B=B,
        c=c,
        x0=x,
        Q=Q,
        R=R,
        x_ref=x_ref,
        q=jnp.zeros((N, nx), x.dtype),
        r=jnp.zeros((N, B.shape[-1]), x.dtype),
        Fu=input_box.F,
        fu=input_box.f,
        u_mask=input_box.mask,
        Fx=Fx,
        fx=fx,
        rho=rho,
        x_mask=x_mask,
    )


def model(p, fc):
    """(A, B, c, Q, R) of the OCP: time invariant, the terminal weight on the last stage."""
    return time_invariant_model(p.A, p.B, p.Q, p.R, p.Q_f, fc.N)


def control(p, fc, g, sol):
    """The first input of the plan (receding horizon)."""
    return sol.u[0]


def sample_time(p, g):
    return p.ts


def truth_model(p, g):
    return p.A, p.B
