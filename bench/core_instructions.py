"""Instructions the core spends per valid UDP packet, per TCP frame and per message tag,
counted by callgrind.

Builds bench/core_instructions.c with the core at -O2, runs it under
``valgrind --tool=callgrind --toggle-collect=FN`` once per entry point and divides the
collected instruction count by the number of calls. Counts are exact and repeatable (they do
not depend on machine load), so they suit a comparison across commits. The one target so far:
authenticating a control packet takes at most 2,000 instructions in total, so the BLAKE2s tag
of its 44 bytes (from the precomputed key state) should stay at about 1,700 or below.
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
    ("estop_udp_rx", "estop_udp_rx"),
    ("estop_tcp_rx", "estop_tcp_rx"),
    ("estop_tick", "estop_tick"),
    ("BLAKE2s MAC, 44-byte message", "estop_b2s_mac"),
]


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
    )
    match = re.search(r"^summary:\s+(\d+)", outfile.read_text(), re.MULTILINE)
    if match is None:
        raise RuntimeError(f"no summary line in {outfile}")
    return int(match.group(1))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=10000)
    args = parser.parse_args()
    if shutil.which("valgrind") is None:
        print("core_instructions: error: valgrind is not installed", file=sys.stderr)
        return 1
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        exe = build(work)
        rows = [(label, count(exe, fn, args.calls, work) / args.calls)
                for label, fn in ROWS]
    print(f"core instructions per call (callgrind, -O2, {args.calls} calls each)")
    print("| entry point | per call |")
    print("| --- | ---: |")
    for label, per_call in rows:
        print(f"| {label} | {per_call:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
