"""estop.errors is the floor every layer may stand on: it imports nothing at all (the layers
above it are checked by import-linter, `make check`; this checks the rest, the standard
library and third parties too)."""

from __future__ import annotations

import ast

import estop.errors
from estop.errors import EXIT_CODES, CliError


def test_errors_imports_nothing() -> None:
    tree = ast.parse(open(estop.errors.__file__, encoding="utf-8").read())
    imports = [ast.unparse(n) for n in ast.walk(tree) if isinstance(n, ast.Import | ast.ImportFrom)]
    assert imports == []


def test_every_error_class_has_a_code_of_the_table() -> None:
    codes = {code for code, _ in EXIT_CODES}
    classes = [CliError, *CliError.__subclasses__()]
    assert len(classes) == 5 and all(c.exit_code in codes for c in classes)
