"""Command line: ``rvdjax run`` (a scenario in closed loop), ``list``, ``scenario``, ``tune``,
``compare``, ``demo`` (one QP), ``bench``, ``study`` and ``verify``; one module per command,
each with ``add_parser(sub)`` and ``cmd(args)``."""

from __future__ import annotations

import argparse
import os
import re
import sys

from rvdjax.cli import bench, compare, demo, run, scenarios, study, tune, verify
from rvdjax.cli.options import add_device_option

__all__ = ["main", "build_parser"]

COMMANDS = (scenarios, run, tune, compare, demo, bench, study, verify)
# Where each command's work runs under --device auto (rvdjax.devices): one maneuver at a time
# on the CPU, batches on JAX's default device (a GPU where there is one).
COMMAND_WORK = {"study": "batch", "verify": "batch"}


class _Parser(argparse.ArgumentParser):
    """argparse's parser, whose errors are one line (argparse prints its usage block first):
    the command, the parameter, what it allows, as every other refusal of bad input. The
    subcommands' parsers are of this class too (``add_subparsers`` makes its parent's)."""

    def error(self, message: str):
        for kind, wanted in (("int", "an integer"), ("float", "a number")):
            message = message.replace(f"invalid {kind} value: ", f"expected {wanted}, got ")
        for action in self._actions:  # a subcommand is "command", not its dest
            if isinstance(action, argparse._SubParsersAction):
                message = message.replace(f"argument {action.dest}: ", "command: ")
                if message.startswith("the following arguments are required:"):
                    choices = "command {" + ",".join(action.choices) + "}"
                    message = re.sub(rf"\b{action.dest}\b", choices, message)
        self.exit(2, f"{self.prog}: error: {message} (`{self.prog} -h` lists the options)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="rvdjax",
        description="MPC guidance for spacecraft rendezvous and docking (Fast MPC in JAX).",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        command.add_parser(sub)
    add_device_option(parser)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from rvdjax import devices, distributed, xla_options

    if getattr(args, "threads", 1) == 1:
        xla_options.one_thread()
    xla_options.host_devices(getattr(args, "devices", 1))  # before JAX starts
    try:
        # jax.distributed must start before anything else touches JAX (the device choice does)
        coordinator = getattr(args, "coordinator", None)
        args.processes = distributed.initialize(
            coordinator, getattr(args, "num_processes", None), getattr(args, "process_id", None)
        )
        with devices.placed(args.device, COMMAND_WORK.get(args.command, "single")) as dev:
            args.device_used = devices.describe(dev)
            from rvdjax.solver.platform import kernel_on

            form = kernel_on(dev)  # the scenarios' default Newton step on this device
            if form != "xla":
                args.device_used += f", Newton step {form}"
            return args.func(args)
    except ValueError as err:  # bad user input: say what and stop, no traceback
        print(f"rvdjax {args.command}: error: {err}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # the reader stopped early (`rvdjax run | head`): no traceback, and no second error
        # when Python flushes stdout at exit (the recipe of Python's signal documentation)
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141


if __name__ == "__main__":
    sys.exit(main())
