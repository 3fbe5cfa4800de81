"""``estop link`` on estopd's log as the journal gives it (issue 17): plain ``journalctl``
lines with their prefix, ``-o cat`` and ``-o json`` all give the report the raw log gives;
what holds no estopd event is counted and its first line shown; ``--journal`` runs
journalctl itself.

This host runs no journald, so ``--journal`` is checked with a stand-in ``journalctl`` on PATH
that prints a recorded ``-o json`` output and checks the arguments it was given."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from estop.errors import EXIT_FILE
from link_util import arrivals_us, gilbert_lost, histogram_log

PREFIX = "Nov 25 10:00:{:02d} car estopd[812]: "
SYSTEMD = ["Nov 25 09:59:59 car systemd[1]: Starting estopd.service - estop unit...",
           "Nov 25 10:00:00 car systemd[1]: Started estopd.service - estop unit."]


def _raw_log() -> list[str]:
    lost = gilbert_lost(20_000, 0.05, 2.0, seed=3)
    return histogram_log([arrivals_us(lost)]).splitlines()


def _plain(lines: list[str]) -> str:
    body = [PREFIX.format(i % 60) + line for i, line in enumerate(lines)]
    return "\n".join([*SYSTEMD, *body, "-- Boot 0123456789abcdef --"]) + "\n"


def _cat(lines: list[str]) -> str:
    return "\n".join([SYSTEMD[1].split(": ", 1)[1], *lines]) + "\n"


def _json(lines: list[str]) -> str:
    def entry(msg: str, ident: str) -> str:
        return json.dumps({"__REALTIME_TIMESTAMP": "1764064800000000", "_PID": "812",
                           "SYSLOG_IDENTIFIER": ident, "MESSAGE": msg})
    out = [entry(SYSTEMD[0].split(": ", 1)[1], "systemd")]
    out += [entry(line, "estopd") for line in lines]
    # journald stores a message that is not valid UTF-8 as a list of byte values
    out.append(json.dumps({"_PID": "812", "MESSAGE": list(lines[-1].encode())}))
    return "\n".join(out) + "\n"


def _link(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "estop", "link", "--json", *args],
                          capture_output=True, text=True, timeout=120, check=False,
                          env={**os.environ, **(env or {})})


def _report(res: subprocess.CompletedProcess[str]) -> tuple[dict[str, object], list[str]]:
    assert res.returncode == 0, res.stderr
    rep = json.loads(res.stdout)
    notes = rep.pop("notes", [])
    rep.pop("source", None)
    return rep, notes


def test_every_journal_form_gives_the_report_of_the_raw_log(tmp_path: Path) -> None:
    lines = _raw_log()
    raw = tmp_path / "raw.log"
    raw.write_text("\n".join(lines) + "\n")
    want, notes = _report(_link(str(raw)))
    assert not any("skipped" in n for n in notes)
    for name, text, skipped in (("plain", _plain(lines), 2), ("cat", _cat(lines), 1),
                                ("json", _json(lines), 1)):
        path = tmp_path / f"{name}.log"
        path.write_text(text)
        got, notes = _report(_link(str(path)))
        assert got == want, name
        said = [n for n in notes if n.startswith("skipped")]
        assert len(said) == 1 and said[0].startswith(f"skipped {skipped} line(s)"), (name, notes)
        assert "line 1: " in said[0], said  # the first one, with its line number


def test_a_log_with_no_event_says_what_it_skipped(tmp_path: Path) -> None:
    path = tmp_path / "text.log"
    path.write_text("Nov 25 10:00:00 car estopd[812]: start udp=0.0.0.0:5700 tcp=0.0.0.0:5701\n"
                    "Nov 25 10:00:01 car estopd[812]: state STOPPED->ARMED reason=none\n")
    res = _link(str(path))
    assert res.returncode == EXIT_FILE  # the input holds nothing usable: a file error
    assert res.stderr.count("\n") == 1, res.stderr
    assert "no link_histogram event" in res.stderr and "skipped 2 line(s)" in res.stderr
    assert "line 1: 'Nov 25 10:00:00 car estopd[812]: start" in res.stderr


def test_journal_option_runs_journalctl(tmp_path: Path) -> None:
    lines = _raw_log()
    raw = tmp_path / "raw.log"
    raw.write_text("\n".join(lines) + "\n")
    want, _ = _report(_link(str(raw)))
    recorded = tmp_path / "journal.json"
    recorded.write_text(_json(lines))
    bindir = tmp_path / "bin"
    bindir.mkdir()
    fake = bindir / "journalctl"
    fake.write_text("#!/bin/sh\n"
                    f'[ "$*" = "-u estopd -o json --no-pager" ] || {{ echo "args: $*" >&2; '
                    "exit 1; }\n"
                    f"cat {recorded}\n")
    fake.chmod(0o755)
    env = {"PATH": f"{bindir}:{os.environ['PATH']}"}
    got, _ = _report(_link("--journal", env=env))
    assert got == want
    res = _link("--journal", "other", env=env)  # journalctl fails: its last line, exit 4
    assert res.returncode == EXIT_FILE and "journalctl -u other failed (exit 1): args: -u other" \
        in res.stderr, res.stderr
    res = _link("--journal", str(raw), env=env)  # a FILE after --journal is its unit name
    assert res.returncode == EXIT_FILE and f"journalctl -u {raw} failed" in res.stderr, \
        res.stderr
