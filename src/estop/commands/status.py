"""``estop status``: ask for the unit's state (STATUS, changes nothing), print the reply."""

from __future__ import annotations

import argparse

from estop.commands.request import add_request_parser, run_request

__all__ = ["add_parser", "run"]

HELP = "ask for the unit's state (STATUS, changes nothing) and print the reply"


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    add_request_parser(sub, "status", HELP).set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    return run_request(args)
