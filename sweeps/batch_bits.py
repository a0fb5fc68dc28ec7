"""Do a batch's results depend on how the engine flies it? (docs/studies.md, "The same table
whatever the slots, devices and processes")

Flies the same runs (initial states perturbed by 5 %; with ``--disturbed`` keys from
PRNGKey(1)) through the batch engine under each configuration of ``--configs`` and counts, for
each against the first, the runs whose delta-v differs in any bit and the metrics' elements
that differ. A configuration is ``slots:refresh:assign`` (refresh masked or compacted, assign
lane or any; the chunk is ``--chunk``).

    python sweeps/batch_bits.py thesis-vbar [--chunk 32] [--runs 64]
        [--configs 32:masked:lane,64:masked:lane,128:masked:lane,64:compacted:lane]
        [--devices 2]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys

if "--devices" in sys.argv:  # host devices: before JAX starts
    n = sys.argv[sys.argv.index("--devices") + 1]
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={n}"
    ).strip()

import jax  # noqa: E402
import numpy as np  # noqa: E402

import rvdjax  # noqa: E402, F401  (float64)
from rvdjax.bench import perturbed_states  # noqa: E402
from rvdjax.loop.engine import EngineConfig, fly_batch  # noqa: E402
from rvdjax.scenarios import FlightOptions, get_scenario  # noqa: E402


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario")
    ap.add_argument("--disturbed", action="store_true")
    ap.add_argument("--nav-filter", action="store_true")
    ap.add_argument("--n-steps", type=int, default=200)
    ap.add_argument("--chunk", type=int, default=32)
    ap.add_argument("--runs", type=int, default=64)
    ap.add_argument(
        "--configs", default="32:masked:lane,64:masked:lane,128:masked:lane,64:compacted:lane"
    )
    ap.add_argument("--devices", type=int, default=1, help="also fly the first on N devices")
    args = ap.parse_args(argv)
    sc = get_scenario(args.scenario)
    flight = sc.flight(
        FlightOptions(n_steps=args.n_steps, disturbed=args.disturbed, nav_filter=args.nav_filter)
    )
    params, x0, loop = flight.params, flight.x0, flight.loop
    x0s = perturbed_states(x0, args.runs, rel=0.05)
    keys = jax.random.split(jax.random.PRNGKey(1), args.runs) if args.disturbed else None
    configs = []
    for text in args.configs.split(","):
        slots, refresh, assign = text.split(":")
        configs.append(
            (text, EngineConfig(slots=int(slots), chunk=args.chunk, refresh=refresh, assign=assign))
        )
    if args.devices > 1:
        first = configs[0][1]
        cfg = dataclasses.replace(first, slots=first.slots * args.devices, devices=args.devices)
        configs.append((f"{configs[0][0]} on each of {args.devices} devices", cfg))
    results = [(name, fly_batch(loop, params, x0s, keys=keys, config=cfg)) for name, cfg in configs]
    ref_name, ref = results[0]
    for name, m in results[1:]:
        da, db = np.asarray(ref.delta_v_m_s), np.asarray(m.delta_v_m_s)
        elements = sum(
            int(np.sum(np.asarray(a) != np.asarray(b)))
            for a, b in zip(jax.tree.leaves(ref), jax.tree.leaves(m), strict=True)
        )
        print(
            f"{args.scenario}, {args.runs} runs, chunk {args.chunk}: {ref_name} vs {name}: "
            f"delta-v differs in {int(np.sum(da != db))} runs (at most "
            f"{float(np.max(np.abs(da - db))):.3g} m/s), {elements} elements of the metrics "
            f"differ; steps differ in {int(np.sum(np.asarray(ref.steps) != np.asarray(m.steps)))}"
        )


if __name__ == "__main__":
    main()
