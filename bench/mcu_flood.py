"""A flood of forged authenticated packets on a Cortex-M0+ at 48 MHz, with and without the
core's tag-check budget (issue 16, defect 10): CPU share, the remote's packets that got
through, ESTOP_BRAKE's longest gap, how late the timeout stop came. Two attacks: forgeries from
new remote ids, and a sniffer's (issue 25: the remote's id and next counters, and the remote's
packets the unit did not take fed back): control packets taken after the remote fell silent,
the stop's time after its last packet. The M0+ -Os image runs
every call in the unicorn emulator (exact instruction counts) inside a simulated bare-metal
host (tools/mcu/mcuflood.py). Writes bench/out/mcu_flood.json as well.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tools" / "mcu"))

import mcubuild  # noqa: E402
import mcuflood  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rates", default="1000,6000,20000,50000",
                        help="forged datagrams a second, comma-separated")
    parser.add_argument("--seconds", type=float, default=0.5, help="flood with the remote on")
    parser.add_argument("--attacks", default="new_ids,sniffer",
                        help="comma-separated: new_ids, sniffer")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "out")
    args = parser.parse_args()
    try:
        (v,) = mcubuild.build(names=["m0plus-Os"])
    except mcubuild.McuError as exc:
        print(f"mcu_flood: error: {exc}", file=sys.stderr)
        return 1
    from estop.core import ffi, lib
    results = []
    for attack in args.attacks.split(","):
        for rate in (int(r) for r in args.rates.split(",")):
            for budget in (None, mcuflood.UNBOUNDED):
                results.append(mcuflood.run(v, ffi, lib, rate, args.seconds, budget,
                                            attack=attack))
                print(mcuflood.table(results[-1:])[-1], flush=True)
    print()
    print("\n".join(mcuflood.table(results)))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "mcu_flood.json").write_text(
        json.dumps([dataclasses.asdict(r) for r in results], indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
