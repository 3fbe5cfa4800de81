"""The exit codes of every ``estop`` command and the errors that carry them.

One table for every command (``estop --help``, README "Exit codes"; tests/unit/test_cli_exit.py).
A :class:`CliError` anywhere below the command line ends the command with its one-line message
``estop: error: <message>`` and its code. This module imports nothing: every layer may use it.
"""

__all__ = [
    "EXIT_CODES",
    "EXIT_FILE",
    "EXIT_INTERNAL",
    "EXIT_INTERRUPTED",
    "EXIT_NOT_INSTALLED",
    "EXIT_OK",
    "EXIT_REFUSED",
    "EXIT_UNREACHABLE",
    "EXIT_USAGE",
    "CliError",
    "ConnectionFailure",
    "FileFailure",
    "NotInstalled",
    "UsageError",
]

EXIT_OK = 0  # done: ACK, report written, no problem found
EXIT_REFUSED = 1  # the answer is no: a NAK, a problem flagged, a script's `expect` failed
EXIT_USAGE = 2  # bad options, or a bad value from the environment or the configuration file
EXIT_UNREACHABLE = 3  # no (valid) answer: refused/closed connection, timeout, bad reply, no bus
EXIT_FILE = 4  # a file cannot be read, written or understood (key file, log, script, plot)
EXIT_NOT_INSTALLED = 5  # a part is not installed: an extra (pip install 'estop[...]'), estopd
EXIT_INTERNAL = 6  # a bug in estop: please report it with the command line
EXIT_INTERRUPTED = 130  # Ctrl-C

EXIT_CODES: tuple[tuple[int, str], ...] = (
    (EXIT_OK, "ok: ACK, report written, no problem found"),
    (EXIT_REFUSED, "refused: NAK, problems flagged, a script's expect failed"),
    (EXIT_USAGE, "usage: bad option, or bad value in the environment or config file"),
    (EXIT_UNREACHABLE, "unreachable: no valid answer (connection refused or closed, timeout, "
                       "malformed or unverified reply; stop: no answer by the deadline; "
                       "CAN bus cannot be opened)"),
    (EXIT_FILE, "file: a file cannot be read, written or understood (key file, log, "
                "script, pcap, plot)"),
    (EXIT_NOT_INSTALLED, "not installed: the command needs an extra (pip install "
                         "'estop[link]', 'estop[bus]') or estopd"),
    (EXIT_INTERNAL, "internal error: a bug in estop, please report it"),
    (EXIT_INTERRUPTED, "interrupted (Ctrl-C)"),
)


class CliError(Exception):
    """An error the CLI reports as one line ``estop: error: <message>``."""

    exit_code = EXIT_REFUSED


class UsageError(CliError):
    exit_code = EXIT_USAGE


class ConnectionFailure(CliError):
    exit_code = EXIT_UNREACHABLE


class FileFailure(CliError):
    exit_code = EXIT_FILE


class NotInstalled(CliError):
    exit_code = EXIT_NOT_INSTALLED
