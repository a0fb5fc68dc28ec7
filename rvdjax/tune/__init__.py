"""Differentiable tuning (DESIGN §7): gradients of a smooth closed-loop surrogate through the
batched loop tune a family's weights with optax, against the hand tuning and a random search,
judged on held-out maneuvers with the exact metrics.

:mod:`.parameters` (what is tuned and how it stays valid), :mod:`.loss` (the surrogate),
:mod:`.tuner` (the spec, the sets, the compiled loss and gradient), :mod:`.trainer` (the
optimiser loop, the baseline, the judgement), :mod:`.files` (the tuned parameters file that
``rvdjax run --params`` flies), :mod:`.figures` (the plots).
"""

from rvdjax.tune.files import apply_params_file, read_params
from rvdjax.tune.loss import LossWeights, parse_loss, run_terms
from rvdjax.tune.parameters import ParameterSpace, parse_names, tunables_of
from rvdjax.tune.trainer import tune
from rvdjax.tune.tuner import Tuner, TuneSpec, heldout_summary, tuner_for

__all__ = [
    "LossWeights",
    "ParameterSpace",
    "TuneSpec",
    "Tuner",
    "apply_params_file",
    "heldout_summary",
    "parse_loss",
    "parse_names",
    "read_params",
    "run_terms",
    "tunables_of",
    "tuner_for",
    "tune",
]
