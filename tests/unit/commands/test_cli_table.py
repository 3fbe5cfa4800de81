"""The command line is built from its table of command modules: each has ``add_parser`` and
runs through ``run`` (the demo through ``main``, which parses its own options), and every one
of them is a sub-command of ``estop``."""

from __future__ import annotations

import argparse

from estop import cli
from estop.commands import demo


def test_every_command_module_adds_its_parser_and_runs() -> None:
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for module in cli.COMMANDS:
        name = module.__name__.rsplit(".", 1)[1]
        assert callable(module.add_parser), name
        assert callable(demo.main if module is demo else module.run), name
        assert name in sub.choices, name
        if module is not demo:
            assert sub.choices[name].get_default("handler") is module.run, name
