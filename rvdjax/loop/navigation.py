"""Navigation filter: a linear Kalman filter on the guidance's relative-motion model.

Paper 003 flies its robustness study (Ch. 5) without a filter: the guidance sees the measured
state, true state plus white noise (:func:`rvdjax.disturbances.measure`). The filter here is
rvdjax's choice, not the thesis' (``LoopConfig(nav_filter=True)``, disturbed runs only): the
standard linear Kalman filter a GNC engineer puts between the navigation sensor and the
guidance, on the discrete model the guidance plans with. Every MPC step

1. measures z_k (as without the filter), then initialises the filter from it on the first step
   (x_hat = z_0, P = R) or updates the prediction with it (:func:`nav_update`);
2. gives the guidance x_hat instead of z (the family's ``ocp``);
3. predicts to the next step with the command the guidance believes was applied
   (:func:`nav_predict`).

Assumptions:

* **Model**: the family's discrete model of the step, x_{k+1} = A x_k + B u_k with (A, B) =
  ``truth_model(params, g)`` of the step's guidance state (three-phase family: the impulsive
  Clohessy-Wiltshire model of the phase; exact for the linear truth, a model mismatch under the
  nonlinear truths that only the process-noise floor below stands for).
* **Measurement**: the full state, H = I, z = x + v, v ~ N(0, R), R = diag(sigma_pos^2 on
  ``Layout.pos``, sigma_vel^2 on ``Layout.vel``, sigma_att^2 on ``Layout.att``): the noise of
  :func:`~rvdjax.disturbances.measure`. A component measured exactly (sigma = 0, or not in
  pos / vel / att) gets the variance floor :data:`R_FLOOR` so that P + R stays invertible; the
  estimate then follows the measurement there.
* **Input**: the prediction uses u_cmd after the minimum impulse bit (the actuator's
  deterministic logic, known on board) and before the thrust-amplitude factor (1 + w / 100):
  w is unknown to the filter (no bias state is estimated).
* **Process noise**: the thrust-amplitude error as white noise on the input, Qp = B diag((s_w
  |u|)^2) B^T + Q_FLOOR R, s_w the stationary 1-sigma of w as a fraction
  (:func:`~rvdjax.disturbances.gm_stationary_std`: 4.62 % for paper 003 Table 5.1). The true w
  is correlated over hours (tau = 1 h); treating it as white from step to step is the usual
  conservative simplification. The floor Q_FLOOR R (a 1-sigma of 1 % of the measurement noise
  per step; :data:`Q_FLOOR`) keeps Qp positive definite (B has fewer columns than rows) and the
  gain from vanishing over long coasts.
* **Update**: Joseph form P+ = (I - K) P (I - K)^T + K R K^T with K = P S^-1 by a linear solve
  (S = P + R; P and S symmetric, so K^T = solve(S, P)), symmetrised.

Everything is a pure function of arrays (jit / vmap / grad).
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

from rvdjax.disturbances import Disturbances, gm_stationary_std

__all__ = [
    "NavState",
    "R_FLOOR",
    "Q_FLOOR",
    "measurement_covariance",
    "process_noise",
    "thrust_error_fraction",
    "nav_init",
    "nav_update",
    "nav_predict",
    "NAV_FILTER_NOTES",
]

# variance floor of an exactly measured component [state units^2] (a 1-sigma of 1e-6)
R_FLOOR = 1e-12
# process-noise floor per step as a fraction of the measurement covariance R
Q_FLOOR = 1e-4

NAV_FILTER_NOTES = (
    "navigation filter (rvdjax's choice; paper 003 has none): linear Kalman filter on the "
    "guidance's discrete model, full-state measurement (H = I, R from the navigation noise), "
    "initialised from the first measurement; prediction with the command after the minimum "
    "impulse bit (thrust error unknown), process noise B diag((s_w |u|)^2) B^T + 1e-4 R with "
    "s_w the thrust error's stationary 1-sigma; the guidance sees the estimate",
)


class NavState(NamedTuple):
    """The filter's estimate.

    Attributes:
        x_hat: (nx,) estimated state.
        P: (nx, nx) its error covariance.
    """

    x_hat: jnp.ndarray
    P: jnp.ndarray


def measurement_covariance(layout, d: Disturbances, dtype=None):
    """(nx, nx) diagonal R of the navigation noise of a family's ``layout`` (module doc),
    floored at :data:`R_FLOOR`."""
    dtype = jnp.result_type(float) if dtype is None else dtype
    var = jnp.zeros(layout.nx, dtype)
    var = var.at[jnp.asarray(layout.pos, int)].set(d.sigma_pos**2)
    var = var.at[jnp.asarray(layout.vel, int)].set(d.sigma_vel**2)
    if len(layout.att):
        var = var.at[jnp.asarray(layout.att, int)].set(d.sigma_att**2)
    return jnp.diag(jnp.maximum(var, R_FLOOR))


def process_noise(B, u_cmd, s_w, R_meas, floor: float = Q_FLOOR):
    """(nx, nx) Qp = B diag((s_w |u_cmd|)^2) B^T + floor R_meas: the thrust-amplitude error
    (fraction s_w, white from step to step) of the command ``u_cmd`` through B, plus a floor."""
    var_u = (s_w * u_cmd) ** 2
    Qp = (B * var_u) @ B.T + floor * R_meas
    return 0.5 * (Qp + Qp.T)


def thrust_error_fraction(d: Disturbances, dt):
    """s_w: the stationary 1-sigma of the thrust-amplitude error w as a fraction (w is in %)."""
    return gm_stationary_std(d, dt) / 100.0


def nav_init(x_meas0, R_meas) -> NavState:
    """The filter at the first measurement: x_hat = z_0, P = R."""
    return NavState(x_hat=jnp.asarray(x_meas0), P=jnp.asarray(R_meas))


def nav_update(nav: NavState, z, R_meas) -> NavState:
    """Measurement update with H = I (Joseph form, gain by a linear solve)."""
    P = nav.P
    S = P + R_meas
    K = jnp.linalg.solve(S, P).T  # K = P S^-1 (P, S symmetric)
    x_hat = nav.x_hat + K @ (z - nav.x_hat)
    IK = jnp.eye(P.shape[-1], dtype=P.dtype) - K
    P_new = IK @ P @ IK.T + K @ R_meas @ K.T
    return NavState(x_hat=x_hat, P=0.5 * (P_new + P_new.T))


def nav_predict(nav: NavState, A, B, u_cmd, Qp) -> NavState:
    """Time update over one step: x_hat' = A x_hat + B u_cmd, P' = A P A^T + Qp."""
    x_hat = A @ nav.x_hat + B @ u_cmd
    P = A @ nav.P @ A.T + Qp
    return NavState(x_hat=x_hat, P=0.5 * (P + P.T))
