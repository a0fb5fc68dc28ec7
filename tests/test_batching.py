"""rvdjax.batching.varying_like: the loop state starts as batched as x0 under vmap, so that
vmap batches a loop's body once instead of until its carry's batching settles."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

from rvdjax.batching import varying_like


def test_varying_like_keeps_the_bits_and_follows_the_batch():
    tree = {"n": jnp.asarray(3, jnp.int32), "flag": jnp.asarray(True), "a": jnp.arange(3.0)}
    x = jnp.asarray([[np.nan, 1.0], [2.0, 3.0]])  # a NaN first entry: the leaf all the same
    for xi in x:
        out = varying_like(tree, xi)
        for k in tree:
            assert out[k].dtype == tree[k].dtype
            np.testing.assert_array_equal(out[k], tree[k])
    # under vmap over x every leaf is batched (out_axes=None refuses a batched output)
    batched = jax.vmap(lambda xi: varying_like(tree, xi))(x)
    assert jax.tree.map(jnp.shape, batched) == {"n": (2,), "flag": (2,), "a": (2, 3)}
    jax.vmap(lambda xi: tree, out_axes=None)(x)  # the tree alone: not batched
    with pytest.raises(ValueError):
        jax.vmap(lambda xi: varying_like(tree, xi), out_axes=None)(x)


def _batching_passes(tie: bool) -> int:
    """vmap of a scan whose counter starts as a constant: how many times vmap batches the
    body (a custom_vmap rule in the body runs once per pass)."""
    passes = []

    @jax.custom_batching.custom_vmap
    def mark(v):
        return v

    @mark.def_vmap
    def _rule(axis_size, in_batched, v):
        passes.append(1)
        return v, in_batched[0]

    def fly(x0):
        carry = (x0, jnp.asarray(0.0))  # the state and a counter that follows it
        if tie:
            carry = varying_like(carry, x0)

        def body(c, _):
            x, n = c
            return (mark(0.5 * x), n + x), None

        return lax.scan(body, carry, None, length=3)[0]

    out = jax.vmap(fly)(jnp.asarray([1.0, 2.0]))
    np.testing.assert_allclose(out[1], [1.75, 3.5])
    return len(passes)


def test_a_tied_carry_is_batched_in_one_pass():
    assert _batching_passes(False) == 2
    assert _batching_passes(True) == 1
