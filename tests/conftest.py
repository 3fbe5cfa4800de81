"""Shared pytest set-up: tests import helpers that live beside them (reference_model, ...)."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
