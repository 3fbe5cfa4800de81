"""tools/proof/frama.py counts the CPU time of a Frama-C run with everything it started. Frama-C
runs its solvers through why3server; a run stopped at its first failure (a self-test mutant)
is ended by killing its process group, and the why3server it left was reaped by init with the
solvers it had reaped: the mutants' runs counted 3 of their 17 s (issue 24's fifty-first
round)."""

from __future__ import annotations

import ctypes
import os
import re
import sys
from pathlib import Path

from test_prove_tool import prove  # noqa: F401 - puts tools/ on the path

PR_GET_CHILD_SUBREAPER = 37

# A frama-c stand-in: a why3server stand-in (a subshell) runs a solver of a second of CPU,
# reaps it and waits on; then the first failure, at which the run is stopped.
FAKE = """#!/bin/sh
echo "pid $$"
( "{python}" -c 'import time
t = time.process_time()
while time.process_time() - t < 1.0:
    pass'
  touch "$DONE"; exec sleep 60 ) &
while [ ! -e "$DONE" ]; do sleep 0.02; done
echo "[wp] [Failed] Goal typed_g"
exec sleep 60
"""


def subreaper() -> int:
    flag = ctypes.c_int(-1)
    libc = ctypes.CDLL(None, use_errno=True)
    assert libc.prctl(PR_GET_CHILD_SUBREAPER, ctypes.byref(flag), 0, 0, 0) == 0
    return flag.value


def test_a_run_stopped_at_its_first_failure_counts_what_its_server_reaped(
        tmp_path: Path) -> None:
    from proof import frama  # tools/ is on the path (test_prove_tool's load_prove)

    fake = tmp_path / "bin" / "frama-c"
    fake.parent.mkdir()
    fake.write_text(FAKE.format(python=sys.executable))
    fake.chmod(0o755)
    env = {**os.environ, "PATH": f"{fake.parent}:{os.environ['PATH']}",
           "DONE": str(tmp_path / "done")}
    log = tmp_path / "wp-mutant.log"
    rc, out, stopped = frama.frama_c_until([], log, 60, env, re.compile(r"\[Failed\]"))
    assert stopped, out
    assert frama.cpu_time(log) >= 0.9, out  # the solver's second, through its server
    pid = int(out.split("pid ", 1)[1].split()[0])
    assert frama._group(pid) == []  # the server and its sleep reaped, no zombie left
    assert subreaper() == 0  # this process adopts nothing once the run is over
