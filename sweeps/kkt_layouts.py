"""The structured KKT solve (one Riccati factorisation, two right-hand sides: a primal-dual
iteration's predictor and corrector) in its array formulations, timed per problem at several
batch sizes on random stage data of ``fastmpc-3d``'s size (N = 30, nx = 6, nu = 3).

* ``dot``: matrix products (``dot_general``), the batch first under ``vmap``;
* ``elementwise``: every product a broadcast multiply and a sum over the contracted axis, the
  batch first under ``vmap``;
* ``rvdjax``: :func:`rvdjax.solver.riccati.riccati_factor` / ``riccati_apply`` as the solver
  calls them: the elementwise form unbatched and, under ``vmap``, with the batch moved last
  (up to ``BATCH_LAST_MAX`` problems) or the elementwise form with the batch first (more).

Usage (one core; results in docs/benchmark.md)::

    taskset -c 0 python sweeps/kkt_layouts.py --batch 1,32,64,128,256,512,1024
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from rvdjax.solver import riccati as R


def _form(products):
    def solve(A, B, Phi_u, Phi_x, g_u, g_x, rp):
        f = R._factor(A, B, Phi_u, Phi_x, products)
        s1 = R._apply(f, g_u, g_x, rp, products)
        return R._apply(f, g_u + s1.du, g_x, rp, products)

    return solve


def rvdjax_form(A, B, Phi_u, Phi_x, g_u, g_x, rp):
    f = R.riccati_factor(A, B, Phi_u, Phi_x)
    s1 = R.riccati_apply(f, g_u, g_x, rp)
    return R.riccati_apply(f, g_u + s1.du, g_x, rp)


FORMS = {"dot": _form(R._DOT), "elementwise": _form(R._ELEMENTWISE), "rvdjax": rvdjax_form}


def problems(batch: int, N=30, nx=6, nu=3, seed=0):
    rng = np.random.default_rng(seed)

    def spd(n):
        X = rng.standard_normal((batch, N, n, n))
        return X @ np.swapaxes(X, -1, -2) + n * np.eye(n)

    A = np.eye(nx) + 0.1 * rng.standard_normal((batch, N, nx, nx))
    B = rng.standard_normal((batch, N, nx, nu))
    vec = lambda n: rng.standard_normal((batch, N, n))  # noqa: E731
    return tuple(jnp.asarray(a) for a in (A, B, spd(nu), spd(nx), vec(nu), vec(nx), vec(nx)))


def main(argv=None):
    jax.config.update("jax_enable_x64", True)
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--batch", default="1,32,256")
    ap.add_argument("--repeats", type=int, default=100)
    args = ap.parse_args(argv)
    print(f"{'form':12s} {'B':>5s} {'us/call':>10s} {'us/problem':>11s} {'max diff':>9s}")
    for b in (int(v) for v in args.batch.split(",")):
        data = problems(b)
        ref = None
        for name, fn in FORMS.items():
            f = jax.jit(jax.vmap(fn))
            out = jax.block_until_ready(f(*data))
            ref = out if ref is None else ref
            diff = max(float(jnp.max(jnp.abs(x - y))) for x, y in zip(out, ref, strict=True))
            t = time.perf_counter()
            for _ in range(args.repeats):
                out = f(*data)
            jax.block_until_ready(out)
            us = (time.perf_counter() - t) / args.repeats * 1e6
            print(f"{name:12s} {b:5d} {us:10.1f} {us / b:11.2f} {diff:9.1e}")


if __name__ == "__main__":
    main()
