"""The command line is built from its table of command modules: each has ``add_parser`` and
runs through ``run`` (the demo through ``main``, which parses its own options), and every one
of them is a sub-command of ``estop``."""

from __future__ import annotations

import argparse
import subprocess
import sys

from estop import cli
from estop.commands import demo


def test_every_command_module_adds_its_parser_and_runs() -> None:
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name in cli.COMMANDS:
        module = cli.command_module(name)
        assert callable(module.add_parser), name
        assert callable(demo.main if module is demo else module.run), name
        assert name in sub.choices, name
        if module is not demo:
            assert sub.choices[name].get_default("handler") is module.run, name


# What the stop button must not wait for: the dashboard's server (asyncio), the demo, the
# gamepad's maps.
HEAVY = ("estop.commands.dashboard", "estop.commands.demo", "estop.demo", "asyncio",
         "estop.remote.gamepad")


def loaded_by(*argv: str) -> list[str]:
    code = ("import sys\nfrom estop.cli import main\nmain(sys.argv[1:])\n"
            f"print('loaded:', *(m for m in {HEAVY!r} if m in sys.modules), file=sys.stderr)")
    run = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True,
                         timeout=60)
    line = next(x for x in run.stderr.splitlines() if x.startswith("loaded:"))
    return line.split()[1:]


def test_a_command_imports_its_own_module_only() -> None:
    assert loaded_by("stop", "--help") == []
    assert loaded_by("status", "--host", "") == []  # a usage error, parsed all the same
    assert loaded_by("link", "--help") == []
    assert loaded_by("remote", "--help") == []  # its modes' modules load when one runs
    # --help names every command, so it imports them all (as a wrong name does)
    assert set(loaded_by("--help")) >= {"estop.commands.dashboard", "estop.commands.demo"}
    assert "estop.commands.dashboard" in loaded_by("no-such-command")
