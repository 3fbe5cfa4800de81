"""Instructions the Cortex-M builds of the core execute per call, counted in the unicorn
emulator: a plain control packet, a TCP request, ticks with and without frames due, on
Cortex-M0+ and Cortex-M4 at -Os and -O2 (the scenario is tools/mcu/mcuinsns.py).

Counts are exact and repeatable (they do not depend on machine load). Cycles are not counted:
the emulator has no timing model; on an M0+ most instructions take one cycle, loads, stores
and taken branches two. Writes bench/out/mcu_instructions.json as well.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tools" / "mcu"))

import mcubuild  # noqa: E402
import mcuinsns  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "out",
                        help="directory for mcu_instructions.json")
    args = parser.parse_args()
    try:
        mcubuild.build()
    except mcubuild.McuError as exc:
        print(f"mcu_instructions: error: {exc}", file=sys.stderr)
        return 1
    from estop.core import ffi, lib
    print("Cortex-M instructions per call (unicorn, exact counts)")
    data: dict[str, list[dict[str, object]]] = {v.name: [] for v in mcubuild.VARIANTS}
    for keyed in mcuinsns.modes(ffi):
        results = {v.name: mcuinsns.scenario(v, ffi, lib, keyed) for v in mcubuild.VARIANTS}
        first = results[mcubuild.VARIANTS[0].name]
        unit = "unit with a key" if keyed else "unit without a key"
        print(f"| {unit} | " + " | ".join(v.label for v in mcubuild.VARIANTS) + " |")
        print("| --- |" + " ---: |" * len(mcubuild.VARIANTS))
        for i, c in enumerate(first):
            cells = " | ".join(str(results[v.name][i].instructions) for v in mcubuild.VARIANTS)
            print(f"| {c.fn}: {c.label} | {cells} |")
        print()
        for name, counts in results.items():
            data[name] += [{"keyed": keyed, "fn": c.fn, "call": c.label,
                            "instructions": c.instructions, "stack_bytes": c.stack}
                           for c in counts]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "mcu_instructions.json").write_text(json.dumps(data, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
