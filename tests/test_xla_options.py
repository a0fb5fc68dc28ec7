"""XLA CPU options set at import (rvdjax.xla_options): which are added, that they reach the
compiler (no YNNPACK fusion in a chunk's Riccati factorisation), the opt-out, and the
warning when JAX started before rvdjax was imported. Each check that depends on XLA_FLAGS
runs in a fresh interpreter, since XLA reads them once per process."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import jaxlib.version
import pytest

from rvdjax import xla_options

YNN = "--xla_cpu_experimental_ynn_fusion_type="
EMITTERS = "--xla_cpu_use_fusion_emitters=false"
HOIST = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=100000000"
WIDE = "--xla_cpu_prefer_vector_width=512"

# A chunk of 32 slots factorising with the model they share (the engine's case, N = 30):
# XLA 0.9+ turns the stage product [B A]' P [B A] into a YNNPACK fusion unless told not to.
PROGRAM = textwrap.dedent(
    """
    import os
    import rvdjax
    import jax, jax.numpy as jnp
    from rvdjax.solver.kkt import riccati_factor
    N, nx, nu, b = 30, 6, 3, 32
    A = jnp.eye(nx)[None].repeat(N, 0) * 1.01
    B = jnp.ones((N, nx, nu))
    Pu = jnp.broadcast_to(jnp.eye(nu), (b, N, nu, nu))
    Px = jnp.broadcast_to(jnp.eye(nx), (b, N, nx, nx))
    f = jax.jit(jax.vmap(riccati_factor, in_axes=(None, None, 0, 0)))
    txt = f.lower(A, B, Pu, Px).compile().as_text()
    print(os.environ.get("XLA_FLAGS", ""))
    print(sum("__ynn_fusion" in line for line in txt.splitlines()))
    print(txt.count("xla_cpu_small_call"))  # a while loop compiled into one function
    """
)


def _run(code: str, **env) -> subprocess.CompletedProcess:
    base = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", xla_options.OPT_OUT)}
    return subprocess.run(
        [sys.executable, "-c", code],
        env={**base, **env},
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_wanted_respects_versions_and_the_users_flags():
    assert xla_options.wanted("", "0.10.2") == [YNN, HOIST]
    assert xla_options.wanted("", "0.9.0") == [YNN]  # hoisting only from the version checked
    assert xla_options.wanted("", "0.8.3") == []  # no YNN option before 0.9
    # other flags are kept beside them
    assert xla_options.wanted(EMITTERS, "0.10.2") == [YNN, HOIST]
    # a value the user chose is kept, whatever it is
    assert xla_options.wanted(f"{YNN}individual_dot", "0.10.2") == [HOIST]
    assert xla_options.wanted("--xla_backend_extra_options=a=1", "0.10.2") == [YNN]
    # 512-bit vectors only where the CPU has them
    assert xla_options.wanted("", "0.10.2", avx512=True) == [YNN, HOIST, WIDE]
    assert xla_options.wanted(f"{WIDE[:-3]}256", "0.10.2", avx512=True) == [YNN, HOIST]


@pytest.mark.skipif(
    xla_options._version(jaxlib.version.__version__) < (0, 9), reason="no YNNPACK fusions"
)
def test_import_sets_the_options_and_the_opt_out_keeps_xlas_defaults():
    on = _run(PROGRAM)
    assert on.returncode == 0, on.stderr[-2000:]
    flags, fusions, hoisted = on.stdout.split("\n")[:3]
    want = xla_options.wanted("", jaxlib.version.__version__, xla_options.has_avx512())
    assert flags.split() == want
    assert int(fusions) == 0
    assert (int(hoisted) >= 1) == (HOIST in want)  # the Riccati scan compiled as one function
    off = _run(PROGRAM, **{xla_options.OPT_OUT: "0"})
    assert off.returncode == 0, off.stderr[-2000:]
    flags, fusions, hoisted = off.stdout.split("\n")[:3]
    assert flags == ""
    assert int(fusions) >= 1  # XLA's default: the reason for the option
    assert int(hoisted) == 0


def test_options_go_before_a_token_xla_would_stop_at():
    assert xla_options.stray_tokens("--a=1 intra_op_parallelism_threads=1 --b") == [
        "intra_op_parallelism_threads=1"
    ]
    assert xla_options.stray_tokens("--xla_cpu_multi_thread_eigen=false") == []
    r = _run(PROGRAM, XLA_FLAGS="--xla_cpu_multi_thread_eigen=false stray=1")
    assert r.returncode == 0, r.stderr[-2000:]
    flags, fusions, hoisted = r.stdout.split("\n")[:3]
    want = xla_options.wanted("", jaxlib.version.__version__, xla_options.has_avx512())
    assert flags.split()[: len(want)] == want  # in front of the stray token
    if want:
        assert int(fusions) == 0  # and they reached the compiler
    assert "stray=1" in r.stderr and "not an XLA option" in r.stderr


def test_warns_when_jax_started_first():
    late = _run("import jax; jax.numpy.ones(1).block_until_ready(); import rvdjax")
    assert late.returncode == 0, late.stderr[-2000:]
    assert "not in effect" in late.stderr and xla_options.OPT_OUT in late.stderr
    quiet = _run(
        "import jax; jax.numpy.ones(1).block_until_ready(); import rvdjax",
        **{xla_options.OPT_OUT: "0"},
    )
    assert "not in effect" not in quiet.stderr


FLY = textwrap.dedent(
    """
    import jax
    import rvdjax
    from rvdjax.loop import fly
    from rvdjax.scenarios import get_scenario
    sc = get_scenario("fastmpc-3d")
    params, x0 = sc.build()
    loop = sc.loop()
    _, m = jax.jit(lambda p, x: fly(loop, p, x))(params, x0)
    print(repr(float(m.effort_l1_N_s)), repr(float(m.time_to_dock_s)), int(m.steps))
    """
)


def test_the_suites_optimisation_level_flies_what_users_fly():
    """The suite compiles at XLA's backend optimisation level 0 and, with jaxlib 0.10, with
    XLA's older CPU loop emitters (tests/conftest.py); a user's program compiles at the default
    level with the default emitters. The default scenario flown with the users' options in a
    fresh interpreter equals the same flight in this process."""
    child = _run(FLY)  # XLA_FLAGS cleared: rvdjax's options at XLA's default optimisation
    assert child.returncode == 0, child.stderr[-2000:]
    effort, time_s, steps = child.stdout.split()
    here = {}
    exec(FLY.replace("print(", "here['out'] = ("), {"here": here})
    mine_effort, mine_time, mine_steps = (float(v) for v in here["out"])
    assert "--xla_backend_optimization_level=0" in os.environ.get("XLA_FLAGS", "") or (
        os.environ.get("RVDJAX_TEST_XLA_OPT") == "default"
    )
    assert int(steps) == mine_steps and float(time_s) == mine_time
    assert abs(float(effort) - mine_effort) <= 1e-9 * mine_effort


@pytest.mark.users_compiler
def test_a_users_compiler_test_runs_with_xlas_default_emitters():
    """A ``users_compiler`` test runs where XLA compiles with its default CPU emitters (a child
    interpreter when the suite uses the older ones, tests/conftest.py) and the suite's other
    options kept."""
    flags = os.environ.get("XLA_FLAGS", "")
    assert "--xla_cpu_use_fusion_emitters" not in flags
    if os.environ.get("RVDJAX_TEST_XLA_OPT") != "default":
        assert "--xla_backend_optimization_level=0" in flags
