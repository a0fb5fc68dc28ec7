"""rvdjax: model predictive control guidance for spacecraft rendezvous and docking in JAX."""

import jax as _jax

# float64 by default: the RVD problems span ~1e7 in cost and ~1e-3 in docking speed.
_jax.config.update("jax_enable_x64", True)

from rvdjax.ocp import OCP, make_ocp, validate_ocp  # noqa: E402

__all__ = ["OCP", "make_ocp", "validate_ocp"]
