"""The three-phase family's thrusters (paper 003 Eq. 3.1 with finite burns): the thrust along
each axis, the impulsive model linearised about the previous plan's burns, and the drift back
from a sample to the instants between samples."""

from __future__ import annotations

import jax.numpy as jnp

from rvdjax.actuators.thrusters import Thrusters
from rvdjax.families.phases_inputs import Params
from rvdjax.solver.platform import cuda_or_default

SUBSAMPLES = 8  # intervals a step is cut into for the truth between samples


def _coast_back(Ac, ts):
    """(..., SUBSAMPLES - 1, 6, 6) e^{-Ac (ts - tau_j)} for tau_j = j ts / SUBSAMPLES, for
    sample times ``ts`` (...): the state at tau_j from the state at ts when nothing fires in
    between (power series; n ts <= 0.1). :func:`ocp` takes every phase's and indexes it by
    the phase: with parameters shared by a batch, one small product for all slots instead
    of a chain of 12 per slot (on a GPU, 23 launches of a thesis-vbar refresh's 208)."""
    s = ts[..., None] * (1.0 - jnp.arange(1, SUBSAMPLES, dtype=Ac.dtype) / SUBSAMPLES)
    eye = jnp.eye(Ac.shape[0], dtype=Ac.dtype)
    M = -s[..., None, None] * Ac

    def horner(M, mm):
        out = jnp.broadcast_to(eye, M.shape)
        for k in range(12, 0, -1):  # Horner: I + M (I + M / 2 (I + M / 3 (...)))
            out = eye + mm(M / k, out)
        return out

    # on a GPU the products as multiplies and sums, which XLA fuses (12 launches fewer a tick)
    return cuda_or_default(
        M, cuda=lambda M: horner(M, _mm_sum), default=lambda M: horner(M, jnp.matmul)
    )


def _mm_sum(X, Y):
    """X @ Y of stacks of small matrices as a multiply and a sum."""
    return jnp.sum(X[..., :, :, None] * Y[..., None, :, :], axis=-2)


def axis_thrust(thr: Thrusters):
    """(3,), (3,) thrust [N] along +x, +y, +z and -x, -y, -z of a set whose body axes are the
    model's (``frame="fixed"``): each direction's thrusters fire together on a demand along
    it (the least-thrust allocation), so a delta-v dv_j takes m |dv_j| / F_j seconds."""
    d = thr.direction  # (T, 3)
    plus = jnp.sum(thr.thrust[:, None] * jnp.maximum(d, 0.0), axis=0)
    minus = jnp.sum(thr.thrust[:, None] * jnp.maximum(-d, 0.0), axis=0)
    return plus, minus


def finite_burn(p: Params, A, ts, dv_bar):
    """The impulsive model (paper 003 Eq. 3.1) with the thrusters' finite burns, linearised
    about the delta-v of the previous plan: (B (N, 6, 3), c (N, 6)) per stage.

    A delta-v dv_j on axis j is a burn of w_j = m |dv_j| / F_j seconds from the period's start
    (PWM aligned to the start; the thesis' on-time bound u_max keeps w_j <= 5 s). Its effect
    at the period's end is A (1 / w) int_0^w e^{-Ac s} ds b_j dv_j
    = A (I - w/2 Ac + w^2/6 Ac^2) b_j dv_j + O(w^3) (b_j the unit delta-v column): for the
    double integrator the position lags the impulse's by m dv_j |dv_j| / (2 F_j). That is
    nonlinear in dv_j; its tangent at the previous plan's delta-v dv_bar (shifted one stage) is

        B_t = A (b - Ac b diag(w) + Ac^2 b diag(w^2) / 2),
        c_t = A (Ac b (w / 2 * dv_bar) - Ac^2 b (w^2 / 3 * dv_bar))

    with w = w(dv_bar): exact where the plan keeps its delta-v (the error is
    m (|dv| - |dv_bar|)^2 / (2 F) per axis otherwise). With ideal impulses (no thrusters)
    the family keeps Eq. 3.1 exactly.
    """
    plus, minus = axis_thrust(p.plant.thrusters)
    F = jnp.where(dv_bar >= 0.0, plus, minus)
    w = jnp.minimum(p.plant.mass * jnp.abs(dv_bar) / jnp.maximum(F, 1e-12), ts)  # (N, 3)
    b = jnp.concatenate([jnp.zeros((3, 3)), jnp.eye(3)]).astype(A.dtype)  # unit delta-v columns
    Ab = p.plant.Ac @ b  # (6, 3)
    AAb = p.plant.Ac @ Ab
    B = jnp.einsum(
        "ij,tjk->tik", A, b[None] - Ab[None] * w[:, None, :] + 0.5 * AAb[None] * (w**2)[:, None, :]
    )
    c = jnp.einsum("ij,tj->ti", A @ Ab, 0.5 * w * dv_bar) - jnp.einsum(
        "ij,tj->ti", A @ AAb, (w**2 / 3.0) * dv_bar
    )
    return B, c
