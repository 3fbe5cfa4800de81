"""``estop release``: ask the unit to leave the stopped state (RELEASE), print the reply. With
a key, STATUS first on the same connection, to learn the unit's session (a RELEASE with
another session is not authenticated)."""

from __future__ import annotations

import argparse

from estop.commands.request import add_request_parser, run_request

__all__ = ["add_parser", "run"]

HELP = "ask the unit to leave the stopped state (RELEASE) and print the reply"


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    add_request_parser(sub, "release", HELP).set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    return run_request(args)
