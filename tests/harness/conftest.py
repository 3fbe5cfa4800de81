"""The harness's tests import hil/'s modules as the harness runs them: hil/ on the path."""

from __future__ import annotations

import sys

from repo import ROOT

sys.path.insert(0, str(ROOT / "hil"))
