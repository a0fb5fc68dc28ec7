"""The recursion under ``vmap`` on XLA's loops: a small batch moved last, a large one
first, and which of the factor's fields carry the batch."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from rvdjax.solver.riccati.recursion import (
    _ELEMENTWISE,
    NewtonStep,
    RiccatiFactor,
    _apply,
    _apply_refined,
    _factor,
    whole,
)

# ------------------------------------------------------------- batching and differentiation
#
# Unbatched, the elementwise form runs (fewer, fused operations on 6x6 blocks). Under
# ``vmap`` (custom_vmap) a batch of at most BATCH_LAST_MAX problems moves its batch axis last
# and runs the elementwise form; a larger batch runs the elementwise form with the batch first
# (an ordinary vmap): past a few hundred problems the batch-last working set leaves the cache.
# With XLA's loops compiled whole (rvdjax.xla_options) the elementwise form beats the dot form
# at every batch size measured (sweeps/kkt_layouts.py, docs/benchmark.md). Derivatives
# (custom_jvp) are those of the dot form: custom_vmap has no reverse-mode rule, and both
# forms compute the same function.

BATCH_LAST_MAX = 512


def _full(axis_size, a, batched):
    """``a`` with the batch axis first, broadcast if it had none."""
    return a if batched else jnp.broadcast_to(a, (axis_size, *a.shape))


def _to_last(a, batched=True):
    if not batched:
        return a[..., None]  # broadcasts against the batch inside the elementwise form
    return jnp.moveaxis(a, 0, -1)


def _to_first(a):
    return jnp.moveaxis(a, -1, 0)


def _first_vmap(fn, in_batched, args, out_batched):
    """The elementwise form under an ordinary ``vmap`` (batches above BATCH_LAST_MAX)."""
    axes = jax.tree.map(lambda b: 0 if b else None, in_batched)
    return jax.vmap(lambda *a: fn(*a, _ELEMENTWISE), in_axes=axes)(*args), out_batched


def _xla_factor_rule(axis_size, in_batched, A, B, Phi_u, Phi_x):
    if axis_size > BATCH_LAST_MAX:
        flags = _factor_flags(in_batched)
        f, _ = _first_vmap(_factor, in_batched, (A, B, Phi_u, Phi_x), flags)
        if not flags.M:  # a shared model stays shared (the vmapped copy is dead code)
            f = f._replace(M=jnp.concatenate([B, A], axis=-1))
        return f, flags
    bA, bB, bPu, bPx = in_batched
    f = _factor(
        _to_last(A, bA),
        _to_last(B, bB),
        _to_last(_full(axis_size, whole(Phi_u), whole(bPu))),
        _to_last(_full(axis_size, whole(Phi_x), whole(bPx))),
        _ELEMENTWISE,
    )
    m_batched = bool(bA or bB)
    M = _to_first(f.M) if m_batched else f.M[..., 0]
    out = RiccatiFactor(M, *(_to_first(a) for a in f[1:4]))
    return out, RiccatiFactor(m_batched, True, True, True)


def _xla_apply_rule(axis_size, in_batched, f, g_u, g_x, rp):
    if axis_size > BATCH_LAST_MAX:
        return _first_vmap(_apply, in_batched, (f, g_u, g_x, rp), NewtonStep(True, True, True))
    fb, bu, bx, br = in_batched
    # every operand but M carries the batch
    f = RiccatiFactor(
        _to_last(f.M, fb.M),
        *(_to_last(_full(axis_size, a, b)) for a, b in zip(f[1:4], fb[1:4], strict=True)),
    )
    g_u, g_x, rp = (_to_last(_full(axis_size, a, b)) for a, b in ((g_u, bu), (g_x, bx), (rp, br)))
    out = _apply(f, g_u, g_x, rp, _ELEMENTWISE)
    return NewtonStep(*(_to_first(a) for a in out)), NewtonStep(True, True, True)


def _factor_flags(in_batched) -> RiccatiFactor:
    """Which factor fields carry the batch (the same for both forms): all but the model
    M = [B, A], which is shared when A and B are (the batch engine's slots share one model,
    and the kernels then read it once per tile instead of a copy per problem)."""
    bA, bB = in_batched[:2]
    return RiccatiFactor(bool(bA or bB), True, True, True)


def _packed_flags(flags: RiccatiFactor) -> RiccatiFactor:
    return flags._replace(Lp=True, Pp=True)


def _xla_apply_refined_rule(axis_size, in_batched, *args):
    out, _ = _first_vmap(_apply_refined, in_batched, args, NewtonStep(True, True, True))
    return out, NewtonStep(True, True, True)


def _xla_factor_solve_rule(axis_size, in_batched, A, B, Phi_u, Phi_x, g_u, g_x, rp):
    f, fb = _xla_factor_rule(axis_size, in_batched[:4], A, B, Phi_u, Phi_x)
    s, sb = _xla_apply_rule(axis_size, (fb, *in_batched[4:]), f, g_u, g_x, rp)
    return (f, s), (fb, sb)


def _factor_solve(A, B, Phi_u, Phi_x, g_u, g_x, rp, ops):
    f = _factor(A, B, Phi_u, Phi_x, ops)
    return f, _apply(f, g_u, g_x, rp, ops)
