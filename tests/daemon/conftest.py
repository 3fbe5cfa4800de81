"""estopd's own tests: every one needs the binary (the session fixture skips them where it is
not built, and fails them in CI)."""

from __future__ import annotations

import pytest


@pytest.fixture(autouse=True)
def _estopd_built(estopd: str) -> None:
    """Asks for the estopd fixture, so that each test here is skipped or failed at once."""
