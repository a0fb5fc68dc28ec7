"""How long the Newton step's Pallas kernels take to compile, and to run, against the same
sweeps as XLA loops (:mod:`rvdjax.solver.unrolled`), one kernel per process.

    PYTHONPATH=. timeout 90 python sweeps/pallas_compile.py
        apply|apply_refined|factor|factor_solve|pd_rows|pd_step_rows|pd_blocks
        [--batch 65536] [--block 128] [--warps 4] [--block-io] [--tabled] [--out FILE]

On a CUDA GPU the kernel is compiled by Triton (bounded only by the caller's ``timeout``:
on an H100, 2026-11-26, the solver's programs with the kernels did not finish compiling in
165 s). Elsewhere it is lowered for CUDA only (no compile). The inputs are one fastmpc-3d
shaped stage-wise system (N = 30, nx = 6, nu = 3) per problem, well conditioned: the figures
are times, not answers. A JSON line per measurement goes to ``--out`` as it is taken.
``apply_refined`` (a step and its refinement in one kernel) is compared with XLA's
elementwise form of the same two solves and residual, one problem per ``vmap`` lane (there is
no unrolled form of it). The default GPU form (``"pallas-block-rows"``) is ``factor_solve``
and ``apply_refined`` with ``--block-io``, and the row work of an accurate iteration,
``pd_blocks``, ``pd_rows`` and ``pd_step_rows`` (:mod:`rvdjax.solver.rows_kernel`, always
with block loads and stores), compared with XLA's form of the same work
(``pd_algebra._newton_blocks``, ``_corrector_rhs`` and ``_step_xla`` under ``vmap``; the
cost shared by the batch in ``pd_blocks``) on random interior iterates of thesis-vbar's shapes
(12 soft rows and 6 input rows a stage). With ``--tabled`` the Riccati kernels read each problem's
model from a table of three, at the problem's index (as they read thesis-vbar's phase models
in the batch engine), and XLA's form reads the copies of the models that the table stands
for.
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import rvdjax  # noqa: F401  (float64)
from rvdjax.provenance import benchmark_block
from rvdjax.solver import lanes, riccati, unrolled

N, NX, NU = 30, 6, 3


def _inputs(b: int):
    rng = np.random.default_rng(0)
    A = np.eye(NX) + 0.05 * rng.standard_normal((N, NX, NX))
    B = 0.1 * rng.standard_normal((N, NX, NU))
    M = jnp.asarray(np.concatenate([B, A], axis=2))  # shared model, as in a scenario's OCP
    d_u = 1.0 + rng.random((N, NU, 1))
    d_x = 1.0 + rng.random((N, NX, 1))
    Phi_u = jnp.asarray(np.eye(NU)[None, :, :, None] * d_u[:, :, None] * np.ones(b))
    Phi_x = jnp.asarray(np.eye(NX)[None, :, :, None] * d_x[:, :, None] * np.ones(b))
    g_u = jnp.asarray(rng.standard_normal((N, NU, b)))
    g_x = jnp.asarray(rng.standard_normal((N, NX, b)))
    rp = jnp.asarray(rng.standard_normal((N, NX, b)))
    return M, Phi_u, Phi_x, g_u, g_x, rp


def _tabled(args, b: int):
    """(table, index, copies, ...) from _inputs' (M, ...): three models (M and two
    perturbations), problem i running model i mod 3, and the batch-last copies of each
    problem's model."""
    M, rest = args[0], args[1:]
    table = jnp.stack([M, 1.01 * M, 0.99 * M])
    index = jnp.arange(b, dtype=jnp.int32) % 3
    return (table, index, jnp.moveaxis(table[index], 0, -1), *rest)


def _fns(part: str, cfg, tabled: bool = False):
    """(kernel, XLA) forms of ``part``: functions of _inputs' arrays, or (``tabled``) of
    _tabled's."""
    kernel, xla = _plain_fns(part, cfg)
    if not tabled:
        return kernel, xla
    return (
        lambda T, i, C, *a: kernel(T, *a, index=i, copy=C),
        lambda T, i, C, *a: xla(C, *a),
    )


def _tri(a):
    """A Hessian block's lower triangles, as the kernels read them (lanes.tri_pack)."""
    return lanes.tri_pack(a, 1)


def _unpacked(out):
    """lanes.factor_solve's (factorisation, step) with the factorisation's matrices whole."""
    f, s = out
    return lanes.unpack(*f), s


def _no_gain(f):
    """(L, P) of the unrolled loops' (L, K, P): what the kernels store."""
    return f[0], f[2]


def _no_gain_solve(out):
    return _no_gain(out[0]), out[1]


def _plain_fns(part: str, cfg):
    """(kernel, XLA) forms, each f(M, Pu, Px, gu, gx, r); the kernel's also takes a table's
    ``index`` (M is then the table) and ``copy``, the copies of the problems' models."""
    if part == "factor":
        return (
            lambda M, Pu, Px, gu, gx, r, index=None, copy=None: lanes.unpack(
                *lanes.factor(M, _tri(Pu), _tri(Px), cfg=cfg, index=index)
            ),
            lambda M, Pu, Px, gu, gx, r: _no_gain(unrolled.factor(M, Pu, Px)),
        )
    if part == "factor_solve":
        return (
            lambda M, Pu, Px, gu, gx, r, index=None, copy=None: _unpacked(
                lanes.factor_solve(M, _tri(Pu), _tri(Px), gu, gx, r, cfg=cfg, index=index)
            ),
            lambda M, Pu, Px, gu, gx, r: _no_gain_solve(
                unrolled.factor_solve(M, Pu, Px, gu, gx, r)
            ),
        )

    def stored(M, Pu, Px, copy=None):  # the apply kernels take a factorisation made before
        return unrolled.factor(M if copy is None else copy, Pu, Px)

    def packed(M, Pu, Px, copy=None):  # ... in the kernels' storage (lanes.pack: L and P)
        L, _, P = stored(M, Pu, Px, copy)
        return lanes.pack(L, P)

    if part == "apply_refined":

        def xla_refined(M, Pu, Px, gu, gx, r):
            rec = riccati.recursion  # XLA's form of the step with its refinement
            f = riccati.RiccatiFactor(M, *stored(M, Pu, Px))
            m_axis = -1 if M.ndim == 4 else None  # copies per problem, or one shared model
            one = jax.vmap(  # batch-last arrays: one problem a lane
                lambda f, *a: rec._apply_refined(f, *a, rec._ELEMENTWISE),
                in_axes=(riccati.RiccatiFactor(m_axis, -1, -1, -1), -1, -1, -1, -1, -1),
                out_axes=-1,
            )
            return one(f, Pu, Px, gu, gx, r)

        return (
            lambda M, Pu, Px, gu, gx, r, index=None, copy=None: lanes.apply_refined(
                M, *packed(M, Pu, Px, copy), _tri(Pu), _tri(Px), gu, gx, r, cfg=cfg, index=index
            ),
            xla_refined,
        )

    return (
        lambda M, Pu, Px, gu, gx, r, index=None, copy=None: lanes.apply(
            M, *packed(M, Pu, Px, copy), gu, gx, r, cfg=cfg, index=index
        ),
        lambda M, Pu, Px, gu, gx, r: unrolled.apply(M, *stored(M, Pu, Px), gu, gx, r),
    )


def _row_inputs(b: int):
    """Batch-first inputs of the row kernels' wrappers in rvdjax.solver.pd_kernels: random
    interior iterates of thesis-vbar's shapes (N = 30, 12 soft rows and 6 input rows a stage),
    rows with a fifth of their entries masked, a random step, the predictor's row products."""
    from rvdjax.ocp import OCP
    from rvdjax.solver.barrier import Rows
    from rvdjax.solver.pd_algebra import PDState, _row_steps, _soft_h, _targets

    mx, mu = 12, 6
    rng = np.random.default_rng(0)

    def normal(*shape):
        return jnp.asarray(rng.standard_normal((b, *shape)))

    def positive(*shape):
        return jnp.exp(normal(*shape))

    def mask(*shape):
        return jnp.asarray((rng.random((b, *shape)) > 0.2).astype(float))

    rows = Rows(normal(N, mu, NU), positive(N, mu), mask(N, mu), normal(N, mx, NX),
                positive(N, mx), mask(N, mx), 10.0 * positive(N, mx))  # fmt: skip
    s, su = positive(N, mx), positive(N, mu)
    g = s - positive(N, mx)
    one = jnp.ones((b,))
    st = PDState(normal(N, NU), normal(N, NX), normal(N, NX), s, positive(N, mu),
                 positive(N, mx), positive(N, mx), 3 * one.astype(int), one < 0,
                 one.astype(int), 5.0 * one, 20.0 * one, su, g)  # fmt: skip
    sx = s - g
    step = riccati.NewtonStep(normal(N, NU), normal(N, NX), normal(N, NX))
    h = 0.0 / sx + 0.0 / s - rows.rho
    m_eff = jnp.sum(rows.wu, (1, 2)) + 2.0 * jnp.sum(rows.wx, (1, 2))
    pred = (rows, st, normal(N, NU), normal(N, NX), su, sx, step, h, m_eff)
    # the corrector's inputs: the predictor's row products, step length and weight
    Fdu_a, Fdx_a, alpha_a, kappa = normal(N, mu), normal(N, mx), 0.7 * one, 0.05 * one
    zu, zx = jnp.zeros_like(su), jnp.zeros_like(sx)
    aff = jax.vmap(_row_steps)(rows, st, Fdu_a, Fdx_a, su, sx, zu, zx, zx, h)
    taus = jax.vmap(_targets)(aff, alpha_a, kappa)
    h_c = jax.vmap(_soft_h)(rows, st, sx, taus[1], taus[2])
    # the stopping test's cost and model: each problem's (XLA's form reads the copies)
    Q = jnp.broadcast_to(2.0 * jnp.eye(NX), (b, N, NX, NX))
    R = jnp.broadcast_to(jnp.eye(NU), (b, N, NU, NU))
    A, B, none = normal(N, NX, NX), normal(N, NX, NU), (None,) * 7
    cost = OCP(A, B, None, None, Q, R, normal(N, NX), normal(N, NX), normal(N, NU), *none)
    corr = (cost, rows, st, su, sx, step, taus, h_c, one < 0, (Fdu_a, Fdx_a, alpha_a, kappa))
    blocks = (rows, st, su, sx)
    return {"pd_rows": pred, "pd_step_rows": corr, "pd_blocks": blocks}


def _row_fns(part: str):
    """(kernel, XLA) forms of a row kernel's work, vmapped over batch-first inputs."""
    from rvdjax.solver import pd_algebra as pa
    from rvdjax.solver import pd_kernels as pk

    if part == "pd_blocks":  # one cost for the batch (closed over: unbatched)
        from rvdjax.ocp import OCP

        Q, R = 2.0 * jnp.eye(NX)[None].repeat(N, 0), jnp.eye(NU)[None].repeat(N, 0)
        q, r, x_ref = jnp.zeros((N, NX)), jnp.zeros((N, NU)), jnp.ones((N, NX))
        A, B = jnp.eye(NX)[None].repeat(N, 0), jnp.ones((N, NX, NU))
        x0, c = jnp.ones(NX), jnp.zeros((N, NX))
        cost = OCP(A, B, c, x0, Q, R, x_ref, q, r, *(None,) * 7)

        def blocks(fn, **kw):
            return jax.vmap(lambda r, st, su, sx: fn(cost, r, st, su, sx, **kw))

        return blocks(pk._blocks_in_kernel, interpret=False), blocks(pa._newton_blocks)

    if part == "pd_rows":
        kernel = functools.partial(pk._rows_in_kernel, interpret=False)
        return jax.vmap(kernel), jax.vmap(pa._corrector_rhs)

    def kernel(*a):
        return pk._step_in_kernel(*a[:-1], aff=a[-1], interpret=False)

    return jax.vmap(kernel), jax.vmap(lambda *a: pa._step_xla(*a[:-1]))


def _best(fn, args, repeats=5):
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - t0)
    return best


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "part",
        choices=(
            "apply",
            "apply_refined",
            "factor",
            "factor_solve",
            "pd_rows",
            "pd_step_rows",
            "pd_blocks",
        ),
    )
    ap.add_argument("--batch", type=int, default=65536)
    ap.add_argument("--block", type=int, default=128)
    ap.add_argument("--warps", type=int, default=4)
    ap.add_argument("--block-io", action="store_true", help="KernelConfig.block_io")
    ap.add_argument(
        "--tabled",
        action="store_true",
        help="the Riccati kernels read each problem's model from a table of three",
    )
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    gpu = jax.default_backend() == "gpu"
    cfg = lanes.KernelConfig(
        block=args.block, num_warps=args.warps, interpret=False, block_io=args.block_io
    )
    if args.part.startswith("pd_"):  # the row kernels: always block loads and stores
        args_ = _row_inputs(args.batch)[args.part]
        pallas_fn, xla_fn = _row_fns(args.part)
    else:
        args_ = _inputs(args.batch)
        if args.tabled:
            args_ = _tabled(args_, args.batch)
        pallas_fn, xla_fn = _fns(args.part, cfg, args.tabled)
    prov = benchmark_block("sweeps/pallas_compile.py", vars(args))

    def emit(**row):
        row = dict(
            part=args.part,
            batch=args.batch,
            block=args.block,
            warps=args.warps,
            block_io=args.block_io,
            tabled=args.tabled,
            **row,
        )
        print(json.dumps(row), flush=True)
        row["provenance"] = prov
        if args.out:
            with open(args.out, "a", encoding="utf-8") as f:
                f.write(json.dumps(row) + "\n")

    t0 = time.perf_counter()
    xla = jax.jit(xla_fn).lower(*args_).compile()
    xla_form = "unrolled (XLA loops)"
    if args.part == "apply_refined" or args.part.startswith("pd_"):
        xla_form = "XLA"
    emit(form=xla_form, compile_s=time.perf_counter() - t0)
    if gpu:
        emit(form=xla_form, ms=1e3 * _best(xla, args_))
    t0 = time.perf_counter()
    lowered = jax.jit(pallas_fn).trace(*args_).lower(lowering_platforms=("cuda",))
    emit(form="pallas", lower_s=time.perf_counter() - t0, hlo_kb=len(lowered.as_text()) / 1e3)
    if not gpu:
        return 0
    t0 = time.perf_counter()
    compiled = jax.jit(pallas_fn).lower(*args_).compile()
    emit(form="pallas", compile_s=time.perf_counter() - t0)
    emit(form="pallas", ms=1e3 * _best(compiled, args_))
    a, b = jax.tree.leaves(compiled(*args_)), jax.tree.leaves(xla(*args_))
    a, b = ([jnp.asarray(x, jnp.float64) for x in v] for v in (a, b))  # flags as 0 / 1
    err = max(
        float(jnp.max(jnp.abs(x - y)) / (jnp.max(jnp.abs(y)) + 1e-300))
        for x, y in zip(a, b, strict=True)
    )
    emit(form="pallas", max_rel_difference_to_unrolled=err)
    return 0


if __name__ == "__main__":
    sys.exit(main())
