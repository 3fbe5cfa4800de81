"""make mcu: builds the core for Cortex-M0+ and M4 at -Os and -O2, prints the footprint, the
worst-case stack per entry point and the instructions per call (counted in the emulator), and
fails when the build breaks the budget of issue 10. ``--markdown`` prints the tables for
docs/MCU.md instead."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import mcubuild  # noqa: E402
import mcuinsns  # noqa: E402
from mcubuild import (  # noqa: E402
    BUDGET_FLASH,
    BUDGET_STACK,
    BUDGET_STACK_VARIANTS,
    BUDGET_STATE,
    VARIANTS,
    McuError,
)


def table(rows: list[list[str]], markdown: bool) -> str:
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = []
    for n, row in enumerate(rows):
        cells = [c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths,
                                                                                      strict=True))]
        lines.append(("| " + " | ".join(cells) + " |") if markdown else "  ".join(cells))
        if markdown and n == 0:
            lines.append("|" + "|".join("-" * (w + 1) + ("-" if i == 0 else ":")
                                        for i, w in enumerate(widths)) + "|")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--markdown", action="store_true", help="tables for docs/MCU.md")
    parser.add_argument("--no-build", action="store_true", help="use the images as built")
    args = parser.parse_args()
    try:
        if not args.no_build:
            mcubuild.build()
            mcubuild.make("baremetal")
        from estop.core import ffi, lib
        return report(ffi, lib, args.markdown)
    except McuError as exc:
        print(f"make mcu: error: {exc}", file=sys.stderr)
        return 1


def report(ffi: object, lib: object, markdown: bool) -> int:
    heads = [v.label for v in VARIANTS]
    fps = {v.name: mcubuild.footprint(v) for v in VARIANTS}
    stacks = {v.name: mcubuild.stack_per_entry(v) for v in VARIANTS}
    state = {v.name: mcubuild.dwarf_layouts(v.elf, ["estop_core_t"])["estop_core_t"][0][2]
             for v in VARIANTS}
    sources = " ".join(p.name for p in mcubuild.core_sources())
    title = "##" if markdown else ""
    print(f"{title} Footprint (bytes) of {sources}".strip())
    print()
    rows = [["", *heads]]
    for label, get in (("text (core)", lambda f: f.text), ("rodata (core)", lambda f: f.rodata),
                       ("libgcc helpers", lambda f: f.helpers),
                       ("flash total", lambda f: f.flash), (".data + .bss", lambda f: f.data)):
        rows.append([label, *[str(get(fps[v.name])) for v in VARIANTS]])
    rows.append(["sizeof(estop_core_t)", *[str(state[v.name]) for v in VARIANTS]])
    print(table(rows, markdown))
    print()
    print(f"{title} Worst-case stack (bytes) per entry point, frames summed along the deepest "
          "call path".strip())
    print()
    rows = [["entry point", *heads]]
    for fn in mcubuild.prototypes():
        rows.append([fn, *[str(stacks[v.name][fn][0]) for v in VARIANTS]])
    print(table(rows, markdown))
    print()
    print(f"{title} Instructions per call (emulated; in brackets the stack the call used)"
          .strip())
    print()
    for keyed in mcuinsns.modes(ffi):
        counts = {v.name: mcuinsns.scenario(v, ffi, lib, keyed) for v in VARIANTS}
        first = counts[VARIANTS[0].name]
        rows = [["unit with a key" if keyed else "unit without a key", *heads]]
        for i, c in enumerate(first):
            rows.append([f"{c.fn}: {c.label}",
                         *[f"{counts[v.name][i].instructions} ({counts[v.name][i].stack})"
                           for v in VARIANTS]])
        print(table(rows, markdown))
        print()
    budgeted = [v for v in VARIANTS if v.name in BUDGET_STACK_VARIANTS]
    flash = fps["m0plus-Os"].flash
    deepest = max((stacks[v.name][fn][0], v.name, fn) for v in budgeted for fn in stacks[v.name])
    checks = [
        (flash <= BUDGET_FLASH, f"flash of the core on M0+ -Os: {flash} of {BUDGET_FLASH}"),
        (max(state.values()) <= BUDGET_STATE,
         f"sizeof(estop_core_t): {max(state.values())} of {BUDGET_STATE}"),
        (all(f.data == 0 for f in fps.values()), "no .data or .bss in any image"),
        (deepest[0] <= BUDGET_STACK,
         f"deepest stack on {deepest[1]}: {deepest[0]} of {BUDGET_STACK} ({deepest[2]})"),
    ]
    image = mcubuild.OUT_DIR / "baremetal" / "estop-an385.elf"
    if image.exists():
        shown = image.relative_to(mcubuild.ROOT) if image.is_relative_to(mcubuild.ROOT) else image
        print(f"Bare-metal image for mps2-an385: {shown}")
        print("  qemu-system-arm -M mps2-an385 -display none -monitor none -serial none "
              "-semihosting-config enable=on,target=native -kernel <image>")
        print()
    print(f"{title} Budget".strip())
    print()
    for ok, text in checks:
        print(f"- {'ok  ' if ok else 'OVER'} {text}")
    for v in VARIANTS:
        if v.target == "m0plus" and v.name not in BUDGET_STACK_VARIANTS:
            depth, fn = max((stacks[v.name][f][0], f) for f in stacks[v.name])
            if depth > BUDGET_STACK:
                print(f"- note {v.name} (not budgeted): deepest stack {depth} ({fn})")
    return 0 if all(ok for ok, _ in checks) else 1


if __name__ == "__main__":
    sys.exit(main())
