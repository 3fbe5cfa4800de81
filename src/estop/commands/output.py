"""What the ``estop`` commands write: their output lines, their error lines, and the exit-code
table of ``estop --help``."""

from __future__ import annotations

import sys
import textwrap

from estop.errors import EXIT_CODES

__all__ = ["SUB_EPILOG", "err", "exit_code_table", "out"]

# the epilog of a sub-command's --help: its exit codes are those of every command
SUB_EPILOG = "exit codes: as for every estop command (estop --help)"


def out(line: str = "") -> None:
    """Write one line to standard output and flush (the CLI's output, not debugging)."""
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def err(line: str) -> None:
    sys.stderr.write(line + "\n")
    sys.stderr.flush()


def exit_code_table() -> str:
    """The exit codes, one per entry, wrapped to 88 columns (``estop --help``)."""
    return "\n".join(textwrap.fill(text, 88, initial_indent=f"  {code:>3}  ",
                                   subsequent_indent=" " * 7) for code, text in EXIT_CODES)
