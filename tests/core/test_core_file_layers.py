"""The core's files call one another one way only: no two files call each other, directly or
round a longer circle (the house rule; import-linter checks the Python side). A function
counts as called from another file when its name, defined there with external linkage,
stands before a '(' in this file's code (comments and ACSL left out)."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

from repo import ROOT

CORE = ROOT / "firmware" / "core"
DEFINITION = re.compile(r"^(?!static\b)(?:const\s+)?[A-Za-z_][\w ]*?[\s*]([A-Za-z_]\w*)\([^;]*$",
                        re.M)
COMMENT = re.compile(r"/\*.*?\*/|//[^\n]*", re.S)


def calls_between_files(core: Path) -> dict[str, set[str]]:
    """file -> the other files whose functions it calls."""
    code = {p.name: COMMENT.sub(" ", p.read_text()) for p in sorted(core.glob("*.c"))}
    owner = {name: f for f, text in code.items() for name in DEFINITION.findall(text)}
    return {f: {owner[n] for n in re.findall(r"\b([A-Za-z_]\w*)\s*\(", text)
                if n in owner and owner[n] != f}
            for f, text in code.items()}


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every circle of calls, each as the files along it (first file again at the end)."""
    found: list[list[str]] = []

    def walk(path: list[str]) -> None:
        for nxt in sorted(graph[path[-1]]):
            if nxt == path[0]:
                found.append([*path, nxt])
            elif nxt not in path and nxt > path[0]:  # each circle once, from its least file
                walk([*path, nxt])

    for start in sorted(graph):
        walk([start])
    return found


def test_no_two_files_of_the_core_call_each_other() -> None:
    graph = calls_between_files(CORE)
    assert graph["estop_udp.c"] >= {"estop_clock.c", "estop_core.c", "estop_auth.c"}
    assert circles(graph) == []


def test_a_call_back_up_makes_a_circle(tmp_path: Path) -> None:
    # the clock calling a function of estop_core.c, which calls the clock: the check must see it
    core = tmp_path / "core"
    shutil.copytree(CORE, core)
    clock = core / "estop_clock.c"
    text = clock.read_text()
    anchor = "    estop_err_t err = estop__begin(core, now_us, out);\n"
    assert text.count(anchor) == 1
    clock.write_text(text.replace(
        anchor, anchor + "    (void)estop__stop_reason(core, 0u);\n"))
    assert circles(calls_between_files(core)) == [["estop_clock.c", "estop_core.c",
                                                    "estop_clock.c"]]
