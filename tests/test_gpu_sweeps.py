"""The GPU benchmarks' own logic, checked without a GPU: the engine-settings variants of
sweeps/gpu_study_benchmark.py and the comparison table of sweeps/gpu_xla_flags.py."""

import importlib
import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "sweeps"))


def _import(name):
    """Import a sweep script without keeping the XLA_FLAGS it sets for its own process (one
    host device per core), which this process's children would inherit."""
    saved = os.environ.get("XLA_FLAGS")
    try:
        return importlib.import_module(name)
    finally:
        if saved is None:
            os.environ.pop("XLA_FLAGS", None)
        else:
            os.environ["XLA_FLAGS"] = saved


def test_settings_variants_parse_into_engine_fields():
    gsb = _import("gpu_study_benchmark")
    got = gsb.parse_settings("slots=4096/slots=16384,iterations=8,refresh=masked")
    assert got == [
        ({"slots": 4096}, 1.0),
        ({"slots": 16384, "iterations": 8, "refresh": "masked"}, 1.0),
    ]
    assert gsb.parse_settings(None) == list(gsb.SETTINGS)
    assert "settings" not in gsb.DEFAULT_PARTS  # only when asked for
    from rvdjax.loop.engine import EngineConfig

    fields = set(EngineConfig.__dataclass_fields__)
    assert all(set(values) <= fields for values, _ in gsb.SETTINGS)


def test_xla_flags_table_compares_variants_and_their_answers(tmp_path):
    gxf = _import("gpu_xla_flags")
    n = gxf.QP_BATCH
    rows = []
    for v, us, rate in (("default", 3.31, 893.0), ("while", 3.30, 876.0)):
        rows += [
            dict(variant=v, part="throughput", maneuvers_per_s=rate, compile_s=29.0),
            dict(variant=v, part="qp", mode="accurate", batch=n, us_per_qp=us, compile_s=15.0),
            dict(variant=v, part="qp", mode="accurate", batch=1, us_per_qp=13700.0),
        ]
    rows.append(dict(variant="while", part="error", what="maneuver", error="boom"))
    J = np.linspace(1.0, 2.0, 8)
    its = np.arange(8)
    np.savez(tmp_path / "answers_default.npz", accurate_8_objective=J, accurate_8_iterations=its)
    np.savez(tmp_path / "answers_while.npz", accurate_8_objective=J, accurate_8_iterations=its)
    np.savez(
        tmp_path / "answers_other.npz",
        accurate_8_objective=J * (1 + 1e-9),
        accurate_8_iterations=its + (its == 3),
    )
    table = gxf.format_table(rows, ["default", "while"], str(tmp_path))
    lines = table.splitlines()
    assert lines[0] == "| measure | default | while |"
    assert "| thesis-vbar maneuvers/s, engine | 893 | 876 |" in lines
    assert "| µs per QP, 65 536, accurate | 3.31 | 3.3 |" in lines
    assert "| ms for one QP alone, accurate | 13.7 | 13.7 |" in lines
    assert "| QP answers against the first variant's | bits | bits |" in lines
    assert "while: error maneuver: boom" in lines
    diff = gxf._same_answers(str(tmp_path), "default", "other")
    assert diff.startswith("objective 1.0e-09") and "1 iteration counts differ" in diff
    assert gxf._same_answers(str(tmp_path), "default", "missing") == "n/a"


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--variants", "default,bogus"], "--variants: unknown 'bogus'"),
        (["--budget-s", "10"], "--budget-s: must be over 30 s"),
    ],
)
def test_xla_flags_bad_input_is_one_line_and_status_2(argv, message, capsys, tmp_path):
    gxf = _import("gpu_xla_flags")
    assert gxf.main(argv + ["--out", str(tmp_path / "out")]) == 2
    out = capsys.readouterr().out
    assert out.startswith(message) and out.count("\n") == 1
    assert not (tmp_path / "out").exists()  # nothing written, no variant started


_HLO = """HloModule m, is_scheduled=true

FileNames
1 "/x/rvdjax/solver/primal_dual.py"
2 "/x/rvdjax/solver/stagewise.py"

FunctionNames
1 "pd_iteration"
2 "mv"

FileLocations
1 {file_name_id=1 function_name_id=1 line=10 end_line=10 column=1 end_column=2}
2 {file_name_id=2 function_name_id=2 line=24 end_line=24 column=1 end_column=2}

StackFrames
1 {file_location_id=1 parent_frame_id=1}
2 {file_location_id=2 parent_frame_id=1}

%fused_a (p0: f64[4,8]) -> f64[4,8] {
  %p0 = f64[4,8]{1,0} parameter(0)
  ROOT %m = f64[4,8]{1,0} multiply(%p0, %p0), metadata={op_name="mul" stack_frame_id=2}
}

%body (t: (s64[], f64[4,8])) -> (s64[], f64[4,8]) {
  %t = (s64[], f64[4,8]{1,0}) parameter(0)
  %i = s64[] get-tuple-element(%t), index=0
  %v = f64[4,8]{1,0} get-tuple-element(%t), index=1
  %f = f64[4,8]{1,0} fusion(%v), kind=kLoop, calls=%fused_a
  ROOT %r = (s64[], f64[4,8]{1,0}) tuple(%i, %f)
}

ENTRY %main (x: f64[4,8]) -> f64[4,8] {
  %x = f64[4,8]{1,0} parameter(0)
  %pallas_call.1 = f32[4,8]{1,0} custom-call(%x), custom_call_target="__gpu$xla.gpu.triton", metadata={op_name="k" stack_frame_id=1}
  %init = (s64[], f64[4,8]{1,0}) tuple(%c, %pallas_call.1)
  %w = (s64[], f64[4,8]{1,0}) while(%init), condition=%cond, body=%body, backend_config={"known_trip_count":{"n":"3"}}
  ROOT %out = f64[4,8]{1,0} get-tuple-element(%w), index=1
}
"""  # noqa: E501


def test_gpu_traffic_counts_launches_bytes_and_sources():
    """sweeps/gpu_traffic.py's count on a hand-written program: a Pallas kernel reading 256
    bytes and writing 128, then a loop of 3 trips whose fused body reads and writes 256; both
    attributed to the solver's line that called them (through the small-product helper). The
    ``solve`` part's count of a loop's body alone: one trip."""
    saved = os.environ.get("JAX_SKIP_CUDA_CONSTRAINTS_CHECK")
    gt = _import("gpu_traffic")
    if saved is None:
        os.environ.pop("JAX_SKIP_CUDA_CONSTRAINTS_CHECK", None)
    t = gt.traffic(_HLO)
    assert (t["launches"], t["read"], t["written"], t["loops"]) == (4, 4 * 256, 128 + 3 * 256, 1)
    assert t["pallas"] == [1, 256, 128]
    assert t["by_source"] == {"primal_dual.py:10 pd_iteration": [4, 4 * 256 + 128 + 3 * 256]}
    assert gt.nbytes("(s64[], f64[4,8]{1,0}, pred[3])") == 8 + 256 + 3
    # the solve part's loop: the first while's body, counted once (one iteration)
    body = gt._outer_loop(*gt._computations(_HLO))
    assert body == "body"
    once = gt.traffic(_HLO, body)
    assert (once["launches"], once["read"], once["written"]) == (1, 256, 256)
    # the maneuver part's loops: each body with its known trip count, or None
    assert gt._loops(gt._computations(_HLO)[0]) == [("body", 3)]
    open_ended = _HLO.replace(', backend_config={"known_trip_count":{"n":"3"}}', "")
    assert gt._loops(gt._computations(open_ended)[0]) == [("body", None)]


def test_kernel_sweeps_count_a_kernels_loads_once_a_sweep():
    """sweeps/gpu_traffic.py's sweep count on a hand-written kernel of two sweeps over N = 5
    stages: the first reads a stage of x (3 entries, as two overlapping blocks of 2) and of y
    (1 entry) and writes one of z; the second reads two of x's entries again and its sum is
    written to w. Per problem: x (3 + 2) x 5 x 8 bytes, y 5 x 8 read, z 5 x 8 and w 8
    written; the operands-once count would read x once."""
    import jax
    import jax.numpy as jnp
    from jax.experimental import pallas as pl

    gt = _import("gpu_traffic")
    N, lanes, b = 5, 8, 16

    def kernel(x_ref, y_ref, z_ref, w_ref):
        def first(t, c):
            x = x_ref[t, 0:2] + x_ref[t, 1:3]
            z_ref[t, 0:1] = x[0:1] + y_ref[t, 0:1]
            return c

        def second(t, c):
            return c + x_ref[t, 0:2][0:1]

        jax.lax.fori_loop(0, N, first, 0)
        w_ref[0, 0:1] = jax.lax.fori_loop(0, N, second, jnp.zeros((1, lanes)))

    def spec(n, m):
        return pl.BlockSpec((n, m, lanes), lambda i: (0, 0, i))

    def run(x, y):
        return pl.pallas_call(
            kernel,
            out_shape=[jax.ShapeDtypeStruct(s, jnp.float64) for s in ((N, 1, b), (1, 1, b))],
            grid=(b // lanes,),
            in_specs=[spec(N, 3), spec(N, 1)],
            out_specs=[spec(N, 1), spec(1, 1)],
            interpret=True,
            name="two_sweeps",
        )(x, y)

    x, y = jnp.ones((N, 3, b)), jnp.ones((N, 1, b))
    z, w = run(x, y)
    np.testing.assert_array_equal(np.asarray(w), np.full((1, 1, b), float(N)))
    sweeps = gt.kernel_sweeps(jax.make_jaxpr(run)(x, y).jaxpr)
    assert sweeps == {"two_sweeps": (((3 + 2) * N * 8 + N * 8) * b, (N * 8 + 8) * b)}


def test_kernel_sweeps_count_a_gathered_table_once_a_tile():
    """A kernel that reads, at each stage, two entries of the lanes' models from a table of
    K = 3 (a gather by each lane's index, as the Riccati kernels read the phase models) is
    charged the table's K rows of those entries once a tile's sweep, not once a lane, and its
    tile of indices once: per tile N x 2 x K x 8 bytes + lanes x 4."""
    import jax
    import jax.numpy as jnp
    from jax.experimental import pallas as pl

    gt = _import("gpu_traffic")
    N, K, lanes, b = 4, 3, 8, 16

    def kernel(table_ref, index_ref, z_ref):
        index = index_ref[...]

        def stage(t, c):
            z_ref[t, 0:2] = table_ref[index, t, 0:2].T
            return c

        jax.lax.fori_loop(0, N, stage, 0)

    def run(table, index):
        return pl.pallas_call(
            kernel,
            out_shape=jax.ShapeDtypeStruct((N, 2, b), jnp.float64),
            grid=(b // lanes,),
            in_specs=[
                pl.BlockSpec((K, N, 5), lambda i: (0, 0, 0)),
                pl.BlockSpec((lanes,), lambda i: (i,)),
            ],
            out_specs=pl.BlockSpec((N, 2, lanes), lambda i: (0, 0, i)),
            interpret=True,
            name="gathered",
        )(table, index)

    table = jnp.arange(K * N * 5, dtype=jnp.float64).reshape(K, N, 5)
    index = jnp.arange(b, dtype=jnp.int32) % K
    z = run(table, index)
    np.testing.assert_array_equal(
        np.asarray(z), np.moveaxis(np.asarray(table)[index, :, :2], 0, -1)
    )
    sweeps = gt.kernel_sweeps(jax.make_jaxpr(run)(table, index).jaxpr)
    tiles = b // lanes
    assert sweeps == {"gathered": ((N * 2 * K * 8 + lanes * 4) * tiles, N * 2 * 8 * b)}


def test_gpu_traffic_bad_input_and_no_cuda_plugin(tmp_path, capsys):
    gt = _import("gpu_traffic")
    assert gt.main(["--kernels", "xla,bogus", "--out", str(tmp_path)]) == 2
    assert "--kernels" in capsys.readouterr().out
    assert gt.main(["--batch", "0", "--out", str(tmp_path)]) == 2
    assert "--batch must be >= 1" in capsys.readouterr().out
    assert gt.main(["solve", "--batch", "0", "--out", str(tmp_path)]) == 2
    assert "--batch must be >= 1" in capsys.readouterr().out
    assert gt.main(["engine", "--slots", "0", "--out", str(tmp_path)]) == 2
    assert "--slots must be >= 1" in capsys.readouterr().out
    assert gt.main(["engine", "--scenario", "nowhere", "--out", str(tmp_path)]) == 2
    assert "--scenario" in capsys.readouterr().out
    assert gt.main(["maneuver", "--scenario", "nowhere", "--out", str(tmp_path)]) == 2
    assert "--scenario" in capsys.readouterr().out
    if gt._cuda_missing() is None:
        pytest.skip("a CUDA plugin is installed here")
    assert gt.main(["--out", str(tmp_path)]) == 2
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and "jax[cuda13]" in out[0]


_HLO_IN_PLACE = """HloModule m, is_scheduled=true

%fused_dus (p0: f64[30,8], p1: f64[8], p2: s32[]) -> f64[30,8] {
  %p0 = f64[30,8]{1,0} parameter(0)
  %p1 = f64[8]{0} parameter(1)
  %p2 = s32[] parameter(2)
  %b = f64[1,8]{1,0} bitcast(%p1)
  %z = s32[] constant(0)
  ROOT %d = f64[30,8]{1,0} dynamic-update-slice(%p0, %b, %p2, %z)
}

%fused_ds (q0: f64[30,8], q1: s32[]) -> f64[1,8] {
  %q0 = f64[30,8]{1,0} parameter(0)
  %q1 = s32[] parameter(1)
  %z2 = s32[] constant(0)
  ROOT %s = f64[1,8]{1,0} dynamic-slice(%q0, %q1, %z2), dynamic_slice_sizes={1,8}
}

ENTRY %main (x: f64[30,8], v: f64[8], i: s32[]) -> f64[1,8] {
  %x = f64[30,8]{1,0} parameter(0)
  %v = f64[8]{0} parameter(1)
  %i = s32[] parameter(2)
  %u = f64[30,8]{1,0} fusion(%x, %v, %i), kind=kLoop, calls=%fused_dus
  ROOT %r = f64[1,8]{1,0} fusion(%u, %i), kind=kLoop, calls=%fused_ds
}
"""


def test_gpu_traffic_counts_in_place_updates_and_slices_by_their_size():
    """A fusion that writes one row of a (30, 8) array in place reads the row's 64 bytes and
    the index, and writes 64; one that reads a row through a dynamic slice reads 64 + 4."""
    gt = _import("gpu_traffic")
    t = gt.traffic(_HLO_IN_PLACE)
    assert (t["launches"], t["read"], t["written"]) == (2, 68 + 68, 64 + 64)


_HLO_SCATTER = """HloModule m, is_scheduled=true

%add (a: f64[], b: f64[]) -> f64[] {
  %a = f64[] parameter(0)
  %b = f64[] parameter(1)
  ROOT %c = f64[] add(%a, %b)
}

%fused_scatter (p0: f64[30,8], p1: s32[2,1], p2: f64[8,2]) -> f64[30,8] {
  %p0 = f64[30,8]{1,0} parameter(0)
  %p1 = s32[2,1]{1,0} parameter(1)
  %p2 = f64[8,2]{1,0} parameter(2)
  %t = f64[2,8]{1,0} transpose(%p2), dimensions={1,0}
  ROOT %s = f64[30,8]{1,0} scatter(%p0, %p1, %t), update_window_dims={1}, \
inserted_window_dims={0}, scatter_dims_to_operand_dims={0}, index_vector_dim=1, to_apply=%add
}

ENTRY %main (x: f64[30,8], i: s32[2,1], v: f64[8,2], w: f64[2,8]) -> f64[30,8] {
  %x = f64[30,8]{1,0} parameter(0)
  %i = s32[2,1]{1,0} parameter(1)
  %v = f64[8,2]{1,0} parameter(2)
  %w = f64[2,8]{1,0} parameter(3)
  %u = f64[30,8]{1,0} fusion(%x, %i, %v), kind=kInput, calls=%fused_scatter
  ROOT %r = f64[30,8]{1,0} scatter(%u, %i, %w), update_window_dims={1}, \
inserted_window_dims={0}, scatter_dims_to_operand_dims={0}, index_vector_dim=1, to_apply=%add
}
"""


def test_gpu_traffic_counts_scatters_in_place():
    """A scatter of two rows into a (30, 8) array, fused or alone, updates its operand's buffer
    in place (as XLA's GPU backend does): it reads the 8 bytes of indices and the 128 bytes of
    rows and writes the 128, not the whole 1 920-byte array."""
    gt = _import("gpu_traffic")
    t = gt.traffic(_HLO_SCATTER)
    assert (t["launches"], t["read"], t["written"]) == (2, 2 * (8 + 128), 2 * 128)


_HLO_COND = """HloModule m, is_scheduled=true

%fused_m (p0: f64[4,8]) -> f64[4,8] {
  %p0 = f64[4,8]{1,0} parameter(0)
  ROOT %m = f64[4,8]{1,0} multiply(%p0, %p0)
}

%work (a: (f64[4,8], f64[4,8])) -> (f64[4,8], f64[4,8]) {
  %a = (f64[4,8]{1,0}, f64[4,8]{1,0}) parameter(0)
  %x = f64[4,8]{1,0} get-tuple-element(%a), index=0
  %y = f64[4,8]{1,0} get-tuple-element(%a), index=1
  %f = f64[4,8]{1,0} fusion(%x), kind=kLoop, calls=%fused_m
  %g = f64[4,8]{1,0} fusion(%y), kind=kLoop, calls=%fused_m
  %h = f64[4,8]{1,0} fusion(%f), kind=kLoop, calls=%fused_m
  ROOT %r = (f64[4,8]{1,0}, f64[4,8]{1,0}) tuple(%h, %g)
}

%skip (b: (f64[4,8], f64[4,8])) -> (f64[4,8], f64[4,8]) {
  %b = (f64[4,8]{1,0}, f64[4,8]{1,0}) parameter(0)
  %x = f64[4,8]{1,0} get-tuple-element(%b), index=0
  %y = f64[4,8]{1,0} get-tuple-element(%b), index=1
  %cx = f64[4,8]{1,0} copy(%x)
  %cy = f64[4,8]{1,0} copy(%y)
  ROOT %r = (f64[4,8]{1,0}, f64[4,8]{1,0}) tuple(%cx, %cy)
}

ENTRY %main (p: pred[], x: f64[4,8], y: f64[4,8]) -> (f64[4,8], f64[4,8]) {
  %p = pred[] parameter(0)
  %x = f64[4,8]{1,0} parameter(1)
  %y = f64[4,8]{1,0} parameter(2)
  %t = (f64[4,8]{1,0}, f64[4,8]{1,0}) tuple(%x, %y)
  ROOT %c = (f64[4,8]{1,0}, f64[4,8]{1,0}) conditional(%p, %t, %t), true_computation=%work, false_computation=%skip
}
"""  # noqa: E501


def test_gpu_traffic_counts_one_branch_of_a_conditional():
    """Only one branch of a conditional runs: the count takes the branch that works (three
    fusions, each reading and writing 256 bytes) and leaves out one that only copies its
    operands out (two copies), whichever order the branches are listed in; with no working
    branch, the heaviest copy branch."""
    gt = _import("gpu_traffic")
    swapped = _HLO_COND.replace(
        "true_computation=%work, false_computation=%skip",
        "true_computation=%skip, false_computation=%work",
    )
    for hlo in (_HLO_COND, swapped):
        t = gt.traffic(hlo)
        assert (t["launches"], t["read"], t["written"]) == (3, 3 * 256, 3 * 256)
    # a working branch lighter than the copies (one fusion: 512 bytes against 1 024) is
    # still the one counted
    light = _HLO_COND.replace("  %g = f64[4,8]{1,0} fusion(%y), kind=kLoop, calls=%fused_m\n", "")
    light = light.replace("  %h = f64[4,8]{1,0} fusion(%f), kind=kLoop, calls=%fused_m\n", "")
    light = light.replace("tuple(%h, %g)", "tuple(%f, %y)")
    t = gt.traffic(light)
    assert (t["launches"], t["read"], t["written"]) == (1, 256, 256)
    only_copies = _HLO_COND.replace("true_computation=%work", "true_computation=%skip")
    t = gt.traffic(only_copies)
    assert (t["launches"], t["read"], t["written"]) == (2, 2 * 256, 2 * 256)


@pytest.mark.users_compiler  # bit for bit: XLA's default emitters (tests/conftest.py)
def test_shared_model_rows_solve_the_same_qps():
    """gpu_benchmark's --shared-model rows: one copy of the fastmpc-3d model (A, B, c, Q, R)
    under vmap, the rest per problem, gives vmap(solve)'s solutions, with the model left
    unbatched (not broadcast back to one copy per problem). Bit for bit where XLA contracts
    multiplies and adds into FMAs (x86-64 CPUs with FMA). Without FMA the two programs round
    differently, and a converged solve's last, ill-conditioned Newton steps carry that into
    the plan: with ``XLA_FLAGS=--xla_cpu_max_isa=SSE4_2`` (2026-12-07) the plans were 3.4e-10
    apart relative to the largest input, the states 1.7e-11, the objectives 1.6e-14, with the
    same statuses and iterations, while each plan was 1.4e-4 from the optimum (a solve to a
    tolerance of 1e-13). There the two must agree to a thousandth of the solver's own
    distance to the optimum (a fixed 1e-10, set from an earlier 8e-12, failed)."""
    import jax

    from rvdjax.solver import SolverParams, SolverSettings, Status, solve

    gb = _import("gpu_benchmark")
    ocps = gb._ocps(3)
    one, axes = gb._shared(ocps)
    assert one.A.shape == ocps.A.shape[1:] and one.x0.shape == ocps.x0.shape
    assert axes.A is None and axes.Fx == 0
    settings = SolverSettings()
    want = jax.jit(jax.vmap(lambda o: solve(o, settings)))(ocps)
    fn = jax.jit(jax.vmap(lambda o: gb._solve_shared(o, settings), in_axes=(axes,)))
    copies = [
        line
        for line in str(fn.trace(one).jaxpr).splitlines()
        if "f64[3,30,6,6] = broadcast_in_dim" in line or "f64[3,30,6,6] = select_n" in line
    ]
    assert not copies  # no per-problem copy of A (the model stays unbatched)
    got = fn(one)
    for name in ("status", "iterations"):
        np.testing.assert_array_equal(np.asarray(getattr(got, name)), getattr(want, name))
    if _xla_cpu_contracts_fma():
        for name in ("u", "x", "nu", "objective"):
            np.testing.assert_array_equal(
                np.asarray(getattr(got, name)), np.asarray(getattr(want, name))
            )
        return
    tight = jax.jit(jax.vmap(lambda o: solve(o, settings, SolverParams(tol=1e-13))))(ocps)
    assert np.all(np.asarray(tight.status) == int(Status.CONVERGED))
    for name in ("u", "x", "nu", "objective"):
        a, b, c = (np.asarray(getattr(r, name)) for r in (got, want, tight))
        apart, off = np.max(np.abs(a - b)), np.max(np.abs(b - c))
        assert apart <= 1e-3 * off, f"{name}: {apart:.3e} apart, {off:.3e} from the optimum"


def _xla_cpu_contracts_fma() -> bool:
    """Whether XLA's CPU code here can contract multiplies and adds into FMAs: the CPU has FMA
    and XLA_FLAGS does not cap the instruction set below AVX2 (Linux's /proc/cpuinfo; False
    where it cannot tell)."""
    import re

    cap = re.search(r"--xla_cpu_max_isa=(\w+)", os.environ.get("XLA_FLAGS", ""))
    if cap and cap.group(1).upper() in ("SSE4_2", "AVX"):
        return False
    try:
        with open("/proc/cpuinfo") as f:
            info = f.read()
    except OSError:
        return False
    return re.search(r"^flags\s*:.*\bfma\b", info, re.M) is not None


@pytest.mark.parametrize(
    "argv, message",
    [
        (["qp", "--sizes", "0,64"], "--sizes must be integers >= 1"),
        (["qp", "--sizes", "1,abc"], "--sizes must be integers >= 1"),
        (["qp", "--unrolls", "-2"], "--unrolls must be integers >= 1"),
        (["qp", "--budget-s", "0"], "--budget-s must be > 0"),
        (["qp", "--kernels", "cuda"], "--kernels: unknown cuda"),
        # sweeps/gpu_registers.py
        (["engine", "--slots", "4096,0"], "gpu_registers: --slots must be"),
        (["qp", "--batch", "x"], "gpu_registers: --batch must be"),
        (["engine", "--scenario", "bogus"], "gpu_registers: --scenario must be"),
        (["qp", "--kernels", "bogus"], "gpu_registers: --kernels must be"),
    ],
)
def test_gpu_benchmark_refuses_bad_input_in_one_line(argv, message, tmp_path, capsys):
    gb = _import("gpu_registers" if message.startswith("gpu_registers") else "gpu_benchmark")
    assert gb.main([*argv, "--out", str(tmp_path / "out")]) == 2
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and message in out[0]
    assert not (tmp_path / "out").exists()  # refused before anything is written


_PTXAS = """ptxas info    : 0 bytes gmem
ptxas info    : Compiling entry function 'rvdjax_pd_step_rows' for 'sm_90a'
ptxas info    : Function properties for rvdjax_pd_step_rows
    6144 bytes stack frame, 22560 bytes spill stores, 32640 bytes spill loads
ptxas info    : Used 32 registers, used 1 barriers, 6144 bytes cumulative stack size
ptxas info    : Compile time = 1534.448 ms
ptxas info    : Compiling entry function 'rvdjax_pd_rows' for 'sm_90a'
ptxas info    : Function properties for rvdjax_pd_rows
    72 bytes stack frame, 88 bytes spill stores, 92 bytes spill loads
ptxas info    : Used 255 registers, used 1 barriers, 72 bytes cumulative stack size
"""


def test_registers_report_reads_ptxas_and_the_occupancy_follows(tmp_path):
    """sweeps/gpu_registers.py: ptxas' report parsed kernel by kernel, and the programs a
    Hopper multiprocessor holds from the registers (65 536 a multiprocessor, allocated 256 a
    warp: 255 registers and 4 warps a program give 2 programs, as NVIDIA's occupancy
    calculator does; 168 give 3; 32 are held to 16 by the 64-warp limit; one-warp programs to
    32 by the program limit)."""
    gr = _import("gpu_registers")
    got = gr.parse_ptxas(_PTXAS)
    step = dict(registers=32, stack=6144, spill_stores=22560, spill_loads=32640)
    rows_ = dict(registers=255, stack=72, spill_stores=88, spill_loads=92)
    assert got == {"rvdjax_pd_step_rows": step, "rvdjax_pd_rows": rows_}
    assert [gr.programs_per_sm(r, 128) for r in (255, 168, 128, 32)] == [2, 3, 4, 16]
    assert gr.programs_per_sm(64, 32) == 32
    # 4 096 problems in programs of 128: 32 programs over 132 multiprocessors
    assert gr.warps_at(4096, 128, 128, 2) == pytest.approx(4 * 32 / 132)
    assert gr.warps_at(65536, 128, 128, 2) == 8  # 512 programs: 2 a multiprocessor at once
    rows = [dict(kernel="k", registers=255, stack=72, spill_stores=88, spill_loads=92,
                 barriers=3, shared=8, programs_per_sm=2,
                 warps_per_sm={4096: 0.97, 32768: 7.76})]  # fmt: skip
    table = gr.format_table(rows, [4096, 32768]).splitlines()
    assert table[2] == "| k | 255 | 72 | 88 / 92 | 3 | 8 | 2 | 1.0 | 7.8 |"
    ptx = tmp_path / "k.ptx"
    ptx.write_text(".reqntid 64, 1, 1\n\tbar.sync \t0;\n\tst.shared.b64 [%r1], %rd2;\n"
                   "\tld.shared.v2.b64 {%rd3, %rd4}, [%r5];\n\tbar.sync \t0;\n")  # fmt: skip
    assert gr.ptx_counts(str(ptx)) == dict(barriers=2, shared=2)
    assert gr.threads_of(str(ptx)) == 64


def test_gpu_session_plans_the_issues_figures_in_five_minutes(capsys, tmp_path):
    """sweeps/gpu_session.py: the GPU run's steps within 5 minutes in all, each with flags its
    script takes (the sweeps' argparse calls), and an unwritable --out is one line and status
    2 before any step starts; gpu_benchmark.py's --modes refuses a mode it does not know."""
    import re

    gs = _import("gpu_session")
    plan = gs.steps(str(tmp_path), smoke=False)
    assert [name for name, _, _ in plan] == ["qp", "qp-before", "engine"]
    assert sum(limit for _, _, limit in plan) <= 300
    argv = {name: " ".join(a) for name, a, _ in plan}
    assert "--kernels auto " in argv["qp"] and "--sizes 1,16384,65536" in argv["qp"]
    assert "--kernels pallas-block-factor " in argv["qp-before"]
    assert all(
        "--shared-model" in argv[n] and "--modes accurate" in argv[n] for n in ("qp", "qp-before")
    )
    for name, step_argv, _ in plan:
        source = open(step_argv[0]).read()
        taken = set(re.findall(r'add_argument\(\s*"(--[\w-]+)"', source))
        flags = {a for a in step_argv if a.startswith("--")}
        assert flags <= taken, (name, flags - taken)
    (tmp_path / "a-file").write_text("")
    assert gs.main(["--out", str(tmp_path / "a-file" / "out")]) == 2  # not a directory
    err = capsys.readouterr().err
    assert err.startswith("--out: cannot write") and err.count("\n") == 1
    gb = _import("gpu_benchmark")
    assert gb.main(["qp", "--modes", "accurate,fast", "--out", str(tmp_path / "o")]) == 2
    out = capsys.readouterr().out
    assert out.startswith("--modes: accurate and/or paper") and out.count("\n") == 1
    assert not (tmp_path / "o").exists()
