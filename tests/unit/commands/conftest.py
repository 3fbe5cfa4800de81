"""A fake unit on loopback for each command-line test that asks for one."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from fake_unit import FakeUnit


@pytest.fixture
def unit() -> Iterator[FakeUnit]:
    u = FakeUnit()
    yield u
    u.close()
