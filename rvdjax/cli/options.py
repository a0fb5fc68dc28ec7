"""The options every command shares, spelled once: the scenario argument, the flight
(:class:`~rvdjax.scenarios.flight.FlightOptions`), ``--json``, ``--device``."""

from __future__ import annotations

import argparse
import re

from rvdjax.scenarios.flight import MODES, TRUTHS, FlightOptions

__all__ = [
    "PLOT_FORMATS",
    "SCENARIO_HELP",
    "add_scenario",
    "add_flight_options",
    "flight_options",
    "add_json",
    "add_device_option",
    "ints",
]

PLOT_FORMATS = (".png", ".pdf", ".svg", ".jpg", ".jpeg")
SCENARIO_HELP = "scenario name (rvdjax list) or scenario file (.toml, rvdjax scenario show)"

# FlightOptions field -> (flag, argparse keywords); the order is the help's
_FLIGHT = {
    "mode": (
        "--mode",
        dict(choices=MODES, default="accurate", help="solver mode (default accurate)"),
    ),
    "truth": (
        "--truth",
        dict(
            choices=TRUTHS,
            default="linear",
            help="truth propagation: the model (default) or nonlinear (model mismatch; what "
            "each family supports: rvdjax list)",
        ),
    ),
    "disturbed": (
        "--disturbed",
        dict(
            action="store_true",
            help="navigation noise, Gauss-Markov thrust error and minimum impulse bit "
            "(paper 003 Ch. 5)",
        ),
    ),
    "nav_filter": (
        "--nav-filter",
        dict(
            action="store_true",
            help="with --disturbed: a Kalman filter on the measurements feeds the guidance",
        ),
    ),
    "thrusters": (
        "--thrusters",
        dict(
            action="store_true",
            help="fly the vehicle's thrusters (allocation, pulse modulation, valve pulses in "
            "the truth) instead of ideal forces",
        ),
    ),
    "n_steps": (
        "--n-steps",
        dict(type=int, metavar="K", help="MPC steps at most (default: the scenario's)"),
    ),
    "time_limit_s": (
        "--time-limit-s",
        dict(type=float, metavar="T", help="a run not docked by then ends as a timeout [s]"),
    ),
    "seed": ("--seed", dict(type=int, default=0, help="PRNG seed (default 0)")),
}


def add_scenario(parser: argparse.ArgumentParser, default: str | None = None) -> None:
    """The positional scenario (a name or a .toml file)."""
    if default is None:
        parser.add_argument("scenario", help=SCENARIO_HELP)
    else:
        parser.add_argument("scenario", nargs="?", default=default, help=SCENARIO_HELP)


def add_flight_options(
    parser: argparse.ArgumentParser, fixed: tuple[str, ...] = (), help: dict | None = None
) -> None:
    """The flight options (:data:`_FLIGHT`), in the same words on every command. ``fixed``:
    options the command sets itself (e.g. ``compare`` flies every solver mode), left out;
    ``help``: a command's own help text for an option (e.g. what its seed seeds)."""
    for field, (flag, kwargs) in _FLIGHT.items():
        if field in fixed:
            continue
        if help and field in help:
            kwargs = {**kwargs, "help": help[field]}
        parser.add_argument(flag, **kwargs)


def flight_options(args, **changes) -> FlightOptions:
    """The :class:`FlightOptions` of parsed arguments (ValueError naming the option)."""
    try:
        return FlightOptions.of(args, **changes)
    except ValueError as err:  # name the flags the user typed, not the fields
        text = str(err)
        for field, (flag, _) in _FLIGHT.items():
            text = re.sub(rf"\b{field}\b", flag, text)
        raise ValueError(text) from None


def add_json(parser: argparse.ArgumentParser, what: str = "print one JSON object") -> None:
    parser.add_argument("--json", action="store_true", help=what)


def ints(text: str) -> list[int]:
    """argparse type: comma-separated integers >= 1."""
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated integers, got {text!r}"
        ) from None
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f"expected integers >= 1, got {text!r}")
    return values


def add_device_option(parser: argparse.ArgumentParser) -> None:
    """``--device auto|cpu|gpu`` on every command (the leaves of the sub-command tree)."""
    from rvdjax import devices

    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        parser.add_argument(
            "--device",
            choices=devices.CHOICES,
            default="auto",
            help="where to compute: auto (default: one maneuver on the CPU, batches on a GPU "
            "if there is one), cpu or gpu",
        )
        return
    for action in subs:
        for child in set(action.choices.values()):
            add_device_option(child)
