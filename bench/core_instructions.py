"""Instructions the core spends per input, plain and authenticated, counted by callgrind.

Builds bench/core_instructions.c with the core at -O2, runs it under
``valgrind --tool=callgrind --toggle-collect=FN`` once per entry point and divides the
collected instruction count by the number of calls. Counts are exact and repeatable (they do
not depend on machine load), so they suit a comparison across commits. Targets: an
authenticated control packet costs at most 2,000 instructions in all (issue 8); the link's
gap histogram costs the plain packet at most 30 more than before it (133, issue 12); with
protocol version 3 (LIFT, SLOWING) the plain packet costs at most 230 in all (issue 15).
``--strict`` exits 1 when a row is over its budget (tests/core/test_core_budget.py runs it).
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CORE = ROOT / "firmware" / "core"
DRIVER = Path(__file__).resolve().parent / "core_instructions.c"


# (row label, function whose instructions callgrind collects)
ROWS = [
    ("plain control packet (20 bytes, no key)", "plain_udp"),
    ("authenticated control packet (60 bytes, key)", "auth_udp"),
    ("plain TCP frame (16-byte STATUS)", "plain_tcp"),
    ("request frame (48-byte STATUS, tagged reply)", "request_tcp"),
    ("authenticated RELEASE (48 bytes, tag checked, tagged reply)", "release_tcp"),
    ("tick every 20 ms (2 ESTOP_BRAKE due)", "tick"),
    ("BLAKE2s MAC, 44-byte message", "mac44"),
]
# Instructions per call each row may cost at most (issues 8 and 15).
BUDGETS = {"plain_udp": 230, "auth_udp": 2000}


def build(workdir: Path) -> Path:
    exe = workdir / "core_instructions"
    subprocess.run(
        ["gcc", "-std=c99", "-O2", "-g", f"-I{CORE}", str(DRIVER),
         *(str(src) for src in sorted(CORE.glob("*.c"))), "-o", str(exe)],
        check=True,
    )
    return exe


def count(exe: Path, fn: str, calls: int, workdir: Path) -> int:
    outfile = workdir / f"callgrind.{fn}.out"
    subprocess.run(
        ["valgrind", "--tool=callgrind", f"--toggle-collect={fn}",
         f"--callgrind-out-file={outfile}", str(exe), str(calls)],
        check=True, capture_output=True,
    )  # a non-zero exit means an input was not what it claims (see the driver)
    match = re.search(r"^summary:\s+(\d+)", outfile.read_text(), re.MULTILINE)
    if match is None:
        raise RuntimeError(f"no summary line in {outfile}")
    return int(match.group(1))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=10000)
    parser.add_argument("--only", default="",
                        help="comma-separated functions to count (default: every row)")
    parser.add_argument("--strict", action="store_true",
                        help="exit 1 when a row is over its budget")
    args = parser.parse_args()
    wanted = {f for f in args.only.split(",") if f}
    unknown = wanted - {fn for _, fn in ROWS}
    if unknown:
        print(f"core_instructions: error: unknown --only {','.join(sorted(unknown))}",
              file=sys.stderr)
        return 2
    if shutil.which("valgrind") is None:
        print("core_instructions: error: valgrind is not installed", file=sys.stderr)
        return 1
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        exe = build(work)
        rows = [(label, fn, count(exe, fn, args.calls, work) / args.calls)
                for label, fn in ROWS if not wanted or fn in wanted]
    print(f"core instructions per call (callgrind, -O2, {args.calls} calls each)")
    print("| entry point | per call | budget |")
    print("| --- | ---: | ---: |")
    over = []
    for label, fn, per_call in rows:
        budget = BUDGETS.get(fn)
        mark = "" if budget is None else f"{budget}" + (" OVER" if per_call > budget else "")
        print(f"| {label} | {per_call:.1f} | {mark} |")
        if budget is not None and per_call > budget:
            over.append(fn)
    if over:
        print(f"over budget: {', '.join(over)}")
    return 1 if over and args.strict else 0


if __name__ == "__main__":
    sys.exit(main())
