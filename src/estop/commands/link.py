"""``estop link``: which slow time S and timeout T fit this link?

Reads a recording of the control link (estopd's ``--log-json`` log, a file of arrival times,
or a pcap of the control port), fits a two-state Gilbert loss model at the known send rate and
prints, for times from 50 ms to 2 s, the gaps seen in the recording and the model's silences
per hour that reach each time: read as the timeout T, false emergency stops; read as the slow
time S (PROTOCOL.md 3, version 3), brief slow-downs. It recommends T, the shortest time that
meets ``--target``, and S, the shortest not above T nor ``--react-ms`` that meets
``--slow-target``. The analysis
lives in :mod:`estop.link` (imported only when the command runs: it needs numpy).
Documentation: docs/LINK.md.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import tempfile

from estop.commands.options import non_negative_float, positive_float
from estop.commands.output import SUB_EPILOG, out
from estop.commands.settings import add_settings
from estop.errors import EXIT_OK, UsageError
from estop.extras import require_extra

__all__ = ["DESCRIPTION", "EPILOG", "add_parser", "read_journal", "run"]

DESCRIPTION = ("Estimate the control link's loss and burst structure (two-state Gilbert model) "
               "from estopd's --log-json log, a file of arrival times or a pcap of the control "
               "port, and report, for times from 50 ms to 2 s, false emergency stops per hour "
               "(read as the timeout T) and brief slow-downs per hour (read as the slow time "
               "S); recommend S and T.")
EPILOG = ("A stop comes at the deadline: with send period P and a time D (the slow time S or "
          "the timeout T) it takes n = ceil(D/P) - 1 packets lost in a row (50 Hz, 200 ms: 9). "
          "Needs the link extra: pip install 'estop[link]'. Exit codes: 0 report written, "
          "2 usage, 4 FILE cannot be read or understood, 5 the link extra is missing.")



def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = sub.add_parser("link", help="false stops per hour per timeout from a recording "
                            "of the control link (estopd log, arrival times or pcap)",
                            description=DESCRIPTION,
                            epilog=f"{EPILOG} {SUB_EPILOG}")
    parser.set_defaults(handler=run)
    parser.add_argument("file", metavar="FILE", nargs="?",
                        help="estopd --log-json log (as written, or journalctl's plain, cat "
                             "or json output), arrival times (s, one per line) or pcap")
    parser.add_argument("--journal", nargs="?", const="estopd", metavar="UNIT",
                        help="read the log from the systemd journal instead of FILE: "
                             "journalctl -u UNIT -o json (default unit estopd)")
    parser.add_argument("--format", choices=("auto", "log", "times", "pcap"), default="auto",
                        help="kind of FILE (default: recognised from its first bytes)")
    add_settings(parser, "rate_hz", "udp_port",
                 help={"rate_hz": "the remote's send rate",
                       "udp_port": "pcap: the unit's UDP control port"},
                 aliases={"udp_port": ["--port"]})
    parser.add_argument("--target", type=positive_float, default=0.01,
                        help="false emergency stops per hour to stay below: chooses the "
                             "timeout T (default 0.01)")
    # the defaults are estop.link.report's DEFAULT_TARGET, DEFAULT_SLOW_TARGET and
    # DEFAULT_REACT_MS (that module needs numpy)
    parser.add_argument("--react-ms", type=positive_float, default=200.0, metavar="MS",
                        help="the longest acceptable slow time S: braking begins at most this "
                             "long after the last packet (default 200)")
    parser.add_argument("--slow-target", type=positive_float, default=1000.0,
                        help="brief slow-downs per hour to stay below: chooses the slow time "
                             "S <= T and <= --react-ms (default 1000, one every 3.6 s)")
    parser.add_argument("--max-gap-s", dest="max_gap", type=non_negative_float, default=5.0,
                        metavar="S", help="gaps of this many seconds or more are the sender "
                        "pausing (finger lifted), left out of the fit (default 5; 0: none)")
    parser.add_argument("--max-gap", dest="max_gap", type=non_negative_float,
                        default=argparse.SUPPRESS, help=argparse.SUPPRESS)
    parser.add_argument("--tail-from", type=int, default=None, metavar="K",
                        help="fit the burst law to runs of at least K losses (default: the "
                             "shortest runs that follow one geometric law; 1: every run)")
    parser.add_argument("--json", action="store_true", help="print the report as JSON")
    parser.add_argument("--plot", metavar="PATH",
                        help="write a PNG: false stops per hour against timeout")


def read_journal(unit: str, path: str) -> str:
    """Write ``journalctl -u UNIT -o json`` (every boot the journal keeps) to ``path``; a
    one-line error when journalctl is missing or fails."""
    from estop.link.gaps import LinkInputError

    exe = shutil.which("journalctl")
    if exe is None:
        raise UsageError("--journal: journalctl not found (record with estopd --log-json and "
                         "give the file instead)")
    with open(path, "wb") as f:
        try:
            res = subprocess.run([exe, "-u", unit, "-o", "json", "--no-pager"], stdout=f,
                                 stderr=subprocess.PIPE, stdin=subprocess.DEVNULL,
                                 timeout=300, check=False)
        except subprocess.TimeoutExpired:
            raise LinkInputError("--journal: journalctl took more than 300 s") from None
    if res.returncode != 0:
        why = res.stderr.decode(errors="replace").strip().splitlines()
        raise LinkInputError(f"--journal: journalctl -u {unit} failed (exit {res.returncode})"
                             f"{': ' + why[-1] if why else ''}")
    return path


def run(args: argparse.Namespace) -> int:
    if args.max_gap and args.max_gap < 2.0:
        raise UsageError("--max-gap-s must be 0 or at least 2 s (the longest timeout)")
    require_extra("link", "numpy", "dpkt")  # dpkt: a pcap is recognised by its first bytes
    if args.plot:
        require_extra("link", "matplotlib")
    from estop.link.format import format_report, report_json
    from estop.link.plot import write_plot
    from estop.link.read import load
    from estop.link.report import report

    if (args.file is None) == (args.journal is None):
        raise UsageError("give FILE or --journal (not both)")
    if args.journal is not None:
        with tempfile.TemporaryDirectory(prefix="estop-link-") as tmp:
            path = read_journal(args.journal, os.path.join(tmp, "journal.json"))
            gaps = load(path, "log", args.rate_hz, args.max_gap, args.udp_port)
    else:
        gaps = load(args.file, args.format, args.rate_hz, args.max_gap, args.udp_port)
    rep = report(gaps, args.rate_hz, args.target, tail_from=args.tail_from,
                 slow_target=args.slow_target, react_ms=args.react_ms)
    if args.plot:
        write_plot(rep, args.plot)
    if args.json:
        out(json.dumps(report_json(rep), indent=1))
    else:
        for line in format_report(rep):
            out(line)
    return EXIT_OK
