"""Helpers for tracing the package's loops: their abstract arguments, and their state's
batching under ``jax.vmap``."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def varying_like(tree, x):
    """``tree`` unchanged, each leaf a select on a predicate of ``x`` that is always true, so
    that under ``vmap`` every leaf is batched wherever ``x`` is.

    A ``lax.scan`` or ``lax.while_loop`` whose carry starts with constants (counters, flags,
    accumulators) that follow the batch after one iteration makes ``vmap`` batch the loop's
    body again until the carry's batching settles: a vmapped closed-loop flight of
    thesis-vbar batched its whole step three times and the solver's loop twice. A carry that
    starts as batched as ``x`` settles in one pass (measured in docs/history.md: such a
    flight traces in 35-45 % less time). The values are the leaves' bits (the select returns
    the leaf also where ``x`` is NaN), and XLA folds the selects away."""
    x = jnp.asarray(x).reshape(-1)[0]
    same = x == x
    return jax.tree.map(lambda a: jnp.where(same, a, a), tree)


def shapes_of(tree):
    """``tree`` with each leaf (an array, a tracer or a Python number) replaced by its shape
    and dtype (:class:`jax.ShapeDtypeStruct`): arguments for ``jax.eval_shape`` or a
    lowering that compute nothing, and hashable."""
    return jax.tree.map(lambda a: jax.ShapeDtypeStruct(jnp.shape(a), jnp.result_type(a)), tree)
