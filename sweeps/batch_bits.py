"""Do a batch's results depend on how many slots fly it? (docs/studies.md, "Bits and slots")

Flies the same runs (initial states perturbed by 5 %, disturbance keys from PRNGKey(1))
through the batch engine with ``m * chunk`` and ``2 m * chunk`` slots and counts the runs whose
delta-v differs in any bit.

    python sweeps/batch_bits.py thesis-vbar --disturbed --nav-filter --chunk 32 --runs 64
"""

from __future__ import annotations

import argparse

import jax
import numpy as np

import rvdjax  # noqa: F401  (float64)
from rvdjax.bench import perturbed_states
from rvdjax.loop.engine import EngineConfig, fly_batch
from rvdjax.scenarios import get_scenario


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario")
    ap.add_argument("--disturbed", action="store_true")
    ap.add_argument("--nav-filter", action="store_true")
    ap.add_argument("--n-steps", type=int, default=200)
    ap.add_argument("--chunk", type=int, default=32)
    ap.add_argument("--chunks", type=int, default=1, help="m: compare m and 2 m chunks")
    ap.add_argument("--runs", type=int, default=64)
    args = ap.parse_args(argv)
    sc = get_scenario(args.scenario)
    params, x0 = sc.build()
    loop = sc.loop(n_steps=args.n_steps, disturbed=args.disturbed, nav_filter=args.nav_filter)
    x0s = perturbed_states(x0, args.runs, rel=0.05)
    keys = jax.random.split(jax.random.PRNGKey(1), args.runs) if args.disturbed else None

    def fly(slots):
        cfg = EngineConfig(slots=slots, chunk=args.chunk, iterations=3)
        return fly_batch(loop, params, x0s, keys=keys, config=cfg)

    a = fly(args.chunks * args.chunk)
    b = fly(2 * args.chunks * args.chunk)
    da, db = np.asarray(a.delta_v_m_s), np.asarray(b.delta_v_m_s)
    steps_differ = int(np.sum(np.asarray(a.steps) != np.asarray(b.steps)))
    print(
        f"{args.scenario}: {args.runs} runs, slots {args.chunks * args.chunk} vs "
        f"{2 * args.chunks * args.chunk} (chunk {args.chunk}): delta-v differs in "
        f"{int(np.sum(da != db))} runs, by at most {float(np.max(np.abs(da - db))):.3g} m/s; "
        f"steps differ in {steps_differ}"
    )


if __name__ == "__main__":
    main()
