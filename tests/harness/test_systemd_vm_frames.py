"""The systemd VM's record of ESTOP_BRAKE frames (tools/systemd_vm/guestlib.py) answers from
where it is asked, not by scanning everything kept.

At 100 frames a second the list grows by thousands while a check waits for a command, and a
check that scanned all of it at every poll took the guest's CPU from that command (a CI run:
estop remote's release not seen within 90 s, the guest busy 87 s of 91). The guest's own code
runs on its python3 with the standard library only, so it is imported here as it is there."""

from __future__ import annotations

import sys
from collections.abc import Iterator

import pytest

from repo import ROOT


@pytest.fixture()
def guestlib() -> Iterator[object]:
    sys.path.insert(0, str(ROOT / "tools" / "systemd_vm"))
    try:
        import guestlib as module
        yield module
    finally:
        sys.path.remove(str(ROOT / "tools" / "systemd_vm"))


def kept(guestlib: object, stamps: list[float]) -> object:
    frames = guestlib.BrakeFrames()  # type: ignore[attr-defined]
    for t in stamps:
        frames._add(guestlib.Frame(t, bytes([1, 100, 0, 1, 0, 0, 0, 0])))  # type: ignore[attr-defined]
    return frames


def stamps_of(frames: list[object]) -> list[float]:
    return [f.t for f in frames]  # type: ignore[attr-defined]


def test_since_and_first_since_start_at_the_time_asked(guestlib: object) -> None:
    frames = kept(guestlib, [float(i) for i in range(1000)])
    assert stamps_of(frames.since(998.5)) == [999.0]  # type: ignore[attr-defined]
    assert stamps_of(frames.since(500.0))[:2] == [500.0, 501.0]  # type: ignore[attr-defined]
    assert frames.first_since(200.5).t == 201.0  # type: ignore[attr-defined]
    assert frames.first_since(1000.5) is None  # type: ignore[attr-defined]


def test_a_cursor_returns_each_new_frame_once(guestlib: object) -> None:
    frames = kept(guestlib, [1.0, 2.0, 3.0])
    new = frames.cursor(1.5)  # type: ignore[attr-defined]
    assert stamps_of(new()) == [2.0, 3.0]
    assert new() == []
    frames._add(guestlib.Frame(4.0, b"\0" * 8))  # type: ignore[attr-defined]
    assert stamps_of(new()) == [4.0]
    assert new() == []


def test_a_stamp_out_of_order_is_kept_in_its_place(guestlib: object) -> None:
    frames = kept(guestlib, [1.0, 3.0, 2.0, 4.0])
    assert stamps_of(frames.frames) == [1.0, 2.0, 3.0, 4.0]  # type: ignore[attr-defined]
    assert stamps_of(frames.since(1.5)) == [2.0, 3.0, 4.0]  # type: ignore[attr-defined]
