"""Parameter checks, written once: each raises ValueError naming the parameter, its unit and
the allowed range, before anything is compiled.

Values that are JAX tracers (inside jit, grad or vmap) are not checked: checks belong to the
boundary where plain numbers become traced parameters (a family's ``make_params``, the
command line), and run once there.
"""

from __future__ import annotations

import jax
import numpy as np

__all__ = [
    "is_tracer",
    "finite",
    "positive",
    "nonnegative",
    "in_range",
    "integer",
    "shape",
    "pos_def",
    "pos_semidef",
    "outside",
    "choice",
]


def is_tracer(x) -> bool:
    return isinstance(x, jax.core.Tracer)


def _unit(unit: str) -> str:
    return f" {unit}" if unit else ""


def finite(name: str, value, unit: str = "") -> np.ndarray | None:
    """``value`` as a float array; ValueError if any entry is NaN or inf."""
    if is_tracer(value):
        return None
    a = np.asarray(value, dtype=float)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}{_unit(unit)} must be finite (no NaN or inf), got {value!r}")
    return a


def positive(name: str, value, unit: str = "") -> None:
    """Every entry finite and > 0."""
    in_range(name, value, 0.0, None, unit=unit)


def nonnegative(name: str, value, unit: str = "") -> None:
    """Every entry finite and >= 0."""
    in_range(name, value, 0.0, None, lo_open=False, unit=unit)


def in_range(
    name: str, value, lo=None, hi=None, lo_open=True, hi_open=True, unit: str = ""
) -> None:
    """Every entry finite and within (lo, hi) (brackets set by ``lo_open``, ``hi_open``)."""
    if is_tracer(value):
        return
    a = np.asarray(value, dtype=float)
    ok = bool(np.all(np.isfinite(a)))
    if lo is not None:
        ok = ok and bool(np.all(a > lo if lo_open else a >= lo))
    if hi is not None:
        ok = ok and bool(np.all(a < hi if hi_open else a <= hi))
    if not ok:
        lb = "-inf" if lo is None else f"{lo:g}"
        ub = "inf" if hi is None else f"{hi:g}"
        rng = f"{'(' if lo_open else '['}{lb}, {ub}{')' if hi_open else ']'}"
        shown = a.tolist() if a.size <= 12 else f"array of shape {a.shape}"
        raise ValueError(f"{name} must be finite and in {rng}{_unit(unit)}, got {shown}")


def integer(name: str, value, lo: int = 1) -> None:
    """A Python / NumPy integer >= lo (a static configuration value)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < lo:
        raise ValueError(f"{name} must be an integer >= {lo}, got {value!r}")


def shape(name: str, value, expected: tuple) -> np.ndarray:
    """``value`` as a finite float array of the ``expected`` shape."""
    a = np.asarray(value, dtype=float)
    if a.shape != tuple(expected):
        raise ValueError(f"{name} must have shape {tuple(expected)}, got {a.shape}")
    finite(name, a)
    return a


def _sym_eigs(name: str, M) -> np.ndarray:
    M = np.asarray(M, dtype=float)
    if M.ndim < 2 or M.shape[-1] != M.shape[-2]:
        raise ValueError(f"{name} must be a square matrix, got shape {M.shape}")
    finite(name, M)
    if not np.allclose(M, np.swapaxes(M, -1, -2), rtol=1e-10, atol=1e-12):
        raise ValueError(f"{name} must be symmetric")
    return np.linalg.eigvalsh(M)


def pos_def(name: str, M) -> None:
    """Symmetric positive definite (smallest eigenvalue > 0)."""
    if is_tracer(M):
        return
    eig = _sym_eigs(name, M)
    if np.min(eig) <= 0:
        raise ValueError(
            f"{name} must be positive definite (smallest eigenvalue > 0), got {np.min(eig):.3g}"
        )


def pos_semidef(name: str, M) -> None:
    """Symmetric positive semidefinite (eigenvalues >= 0 up to rounding)."""
    if is_tracer(M):
        return
    eig = _sym_eigs(name, M)
    if np.min(eig) < -1e-10 * max(1.0, float(np.max(np.abs(eig)))):
        raise ValueError(
            f"{name} must be positive semidefinite (eigenvalues >= 0), got smallest "
            f"eigenvalue {np.min(eig):.3g}"
        )


def outside(what: str, position, centre, radius) -> None:
    """The point ``position`` lies outside the ball |p - centre| <= radius [m] (a start inside
    a keep-out zone). ``what`` names the zone."""
    p = np.asarray(position, dtype=float)
    c = np.asarray(centre, dtype=float)
    d = float(np.linalg.norm(p - c))
    if d <= float(radius):
        raise ValueError(
            f"x0 starts inside {what} ({d:.4g} m from its centre, radius {float(radius):.4g} m); "
            "the initial position must lie outside every keep-out zone"
        )


def choice(name: str, value, allowed) -> None:
    if value not in allowed:
        raise ValueError(f"{name} must be one of {tuple(allowed)}, got {value!r}")
