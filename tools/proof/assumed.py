"""What the proofs assume and no run proves: every axiom and every admitted clause ("admit
ensures") of the proof's files and of the core, each listed in prove/assumed.txt with why it is
assumed and the test that would fail were it false; and every function of the core that no WP
run proves and that is not inlined into one (listed as "function <name>"), whose contract, if it
has one, is then assumed where it is called. make prove prints the list in every run and fails
on an assumption that is not listed, a listed one that no longer exists, or a test that does
not exist."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

from . import wp
from .frama import CORE, PROVE, ROOT, core_functions

LIST = PROVE / "assumed.txt"


@dataclasses.dataclass
class Assumption:
    name: str
    why: str
    test: str  # path::function of the test that fails were the assumption false


def found(files: list[Path]) -> set[str]:
    """The names of the axioms and admitted clauses in files."""
    names: set[str] = set()
    for f in files:
        text = f.read_text()
        names |= set(re.findall(r"\baxiom\s+(\w+)\s*:", text))
        names |= set(re.findall(r"\badmit\s+(?:ensures|requires|assert|assigns)\s+(\w+)\s*:",
                                text))
        if re.search(r"\badmit\s+(?:ensures|requires|assert)\s+(?!\w+\s*:)", text):
            names.add(f"<an unnamed admitted clause in {f.name}>")
    return names


def outside_the_runs() -> set[str]:
    """The core's functions that no WP run of prove/wp_groups.txt names and that are not
    inlined into their callers (prove/wp_inline.txt), as "function <name>". Until issue 24's
    twenty-ninth round nothing checked this: estop__age_tag_window's contract, which the clock
    run relies on, was proved by no run."""
    in_runs = {f for _, fcts in wp.wp_groups() for f in fcts}
    inlined = set(wp.inline_list().split(","))
    return {f"function {f}" for f in core_functions(CORE) - in_runs - inlined}


def listed(path: Path = LIST) -> list[Assumption]:
    out = []
    for raw in path.read_text().splitlines():
        line = raw.split("#", 1)[0].strip()
        if line:
            name, why, test = (x.strip() for x in line.split("|"))
            out.append(Assumption(name, why, test))
    return out


def test_exists(test: str) -> bool:
    path, _, fn = test.partition("::")
    f = ROOT / path
    return f.is_file() and bool(fn) and re.search(rf"^def {re.escape(fn)}\(", f.read_text(),
                                                  re.M) is not None


def check() -> tuple[list[Assumption], list[str]]:
    """The listed assumptions, and what is wrong with the list (empty when nothing)."""
    files = sorted([*PROVE.glob("*.h"), *CORE.glob("*.c"), *CORE.glob("*.h")])
    have = found(files) | outside_the_runs()
    items = listed()
    names = {a.name for a in items}
    errors = [f"{n}: " + ("in no WP run and not inlined" if n.startswith("function ") else
                          "assumed in the proof's files") + ", but not in prove/assumed.txt"
              for n in sorted(have - names)]
    errors += [f"{n}: listed in prove/assumed.txt but no longer in the proof's files"
               for n in sorted(names - have)]
    errors += [f"{a.name}: its test {a.test} does not exist" for a in items
               if not test_exists(a.test)]
    return items, errors
