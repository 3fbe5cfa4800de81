"""``estop keygen PATH``: write a fresh random key file, mode 0600 (:mod:`estop.client.keyfile`)."""

from __future__ import annotations

import argparse

from estop.client.keyfile import KeyFileError, write_key_file
from estop.commands.output import SUB_EPILOG, out
from estop.errors import EXIT_OK, FileFailure

__all__ = ["add_parser", "run"]

DESCRIPTION = ("Write a fresh random key (32 bytes from the system's cryptographic source) to "
               "PATH as 64 hex digits and a newline, mode 0600. The unit (estopd --key-file) "
               "and its remotes share it.")




def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("keygen", help="write a fresh random key file (mode 0600)",
                       description=DESCRIPTION, epilog=SUB_EPILOG)
    p.add_argument("path", metavar="PATH", help="the key file to create (must not exist)")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    try:
        write_key_file(args.path)
    except KeyFileError as exc:
        raise FileFailure(str(exc)) from None
    out(f"wrote a new key to {args.path} (mode 0600); give it to the unit with "
        f"estopd --key-file and keep it secret")
    return EXIT_OK
