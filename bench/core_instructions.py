"""Instructions the core spends per valid UDP packet and per TCP frame, counted by callgrind.

Builds bench/core_instructions.c with the core at -O2, runs it under
``valgrind --tool=callgrind --toggle-collect=FN`` once per entry point and divides the
collected instruction count by the number of calls. Counts are exact and repeatable (they do
not depend on machine load), so they suit a comparison across commits; no target is set yet.
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


def build(workdir: Path) -> Path:
    exe = workdir / "core_instructions"
    subprocess.run(
        ["gcc", "-std=c99", "-O2", "-g", f"-I{CORE}", str(DRIVER), str(CORE / "estop_core.c"),
         str(CORE / "estop_crc.c"), "-o", str(exe)],
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
        rows = [(fn, count(exe, fn, args.calls, work) / args.calls)
                for fn in ("estop_udp_rx", "estop_tcp_rx", "estop_tick")]
    print(f"core instructions per call (callgrind, -O2, {args.calls} calls each)")
    print("| entry point | per call |")
    print("| --- | ---: |")
    for fn, per_call in rows:
        print(f"| {fn} | {per_call:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
