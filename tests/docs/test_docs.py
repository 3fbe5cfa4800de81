"""docs/PROTOCOL.md is the project's own account of the shared wire contract: every byte
example of the contract must appear in it unchanged (the fuzz seeds and readers rely on it)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from repo import ROOT

HEX = re.compile(r"`((?:[0-9A-F]{2} ){7,}[0-9A-F]{2})`")


def examples(text: str) -> list[str]:
    """Every hex example; one split over consecutive lines is one example."""
    out: list[str] = []
    current = ""
    for line in text.splitlines():
        whole = re.fullmatch(r"`((?:[0-9A-F]{2} )*[0-9A-F]{2})`", line.strip())
        if whole:
            current += (" " if current else "") + whole.group(1)
            continue
        if current:
            out.append(current)
            current = ""
        out += HEX.findall(line)
    return [*out, current] if current else out


def shared_spec() -> Path | None:
    for parent in ROOT.parents:
        candidate = parent / "shared" / "spec" / "PROTOCOL.md"
        if candidate.is_file():
            return candidate
    return None


def test_every_example_of_the_contract_is_in_docs_protocol() -> None:
    spec = shared_spec()
    if spec is None:
        pytest.skip("the shared contract is not beside this checkout")
    ours = examples((ROOT / "docs" / "PROTOCOL.md").read_text())
    theirs = examples(spec.read_text())
    assert len(theirs) >= 11
    assert sorted(ours) == sorted(theirs)


def test_docs_protocol_is_version_3() -> None:
    text = (ROOT / "docs" / "PROTOCOL.md").read_text()
    assert text.startswith("# The estop protocol, version 3")
    assert len(examples(text)) >= 15
