"""The candump cross-check of the HIL harness (pure logic): the independent observer's record
(``candump -L``) against what python-can saw.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from estop.protocol.canlog import CanLogError, parse_line
from hilemu import Frame

# --------------------------------------------------------------------------- candump check

def read_candump(lines: Iterable[str]) -> tuple[list[Frame], list[str]]:
    """Frames of a ``candump -L`` log, and the lines that are not frames (reported, not fatal:
    candump also prints e.g. ``interface down`` notices on stderr, never on stdout)."""
    frames: list[Frame] = []
    bad: list[str] = []
    for line in lines:
        if not line.strip():
            continue
        try:
            rec = parse_line(line)
        except CanLogError:
            bad.append(line.rstrip("\n"))
            continue
        frames.append(Frame(rec.timestamp_us / 1e6, rec.can_id, rec.data))
    return frames, bad


@dataclass
class CrossCheck:
    window: tuple[float, float] | None
    matched: int = 0
    only_candump: list[Frame] = field(default_factory=list)
    only_pycan: list[Frame] = field(default_factory=list)
    data_mismatch: list[tuple[Frame, Frame]] = field(default_factory=list)
    candump_total: int = 0
    pycan_total: int = 0

    @property
    def ok(self) -> bool:
        return (self.window is not None and self.matched > 0 and not self.only_candump
                and not self.only_pycan and not self.data_mismatch)

    def figures(self) -> dict[str, object]:
        return {
            "candump_frames": self.candump_total,
            "pycan_frames": self.pycan_total,
            "matched_in_window": self.matched,
            "only_candump": len(self.only_candump),
            "only_pycan": len(self.only_pycan),
            "data_mismatch": len(self.data_mismatch),
        }


def crosscheck(candump: Sequence[Frame], pycan: Sequence[Frame],
               window: tuple[float, float] | None = None,
               tol_s: float = 2e-6) -> CrossCheck:
    """Same frames, in the same order? Both receivers read the kernel timestamp of the same
    skb, so a frame has the same time (to the microsecond candump prints) in both records.

    The order is compared CAN ID by CAN ID: frames of different senders (the daemon's, the
    harness's markers) that came within microseconds of each other on two CPUs may reach two
    sockets in either order (seen: a marker 155 us after a stop frame, read before it by
    candump and after it by python-can). Frames of one ID come from one sender, one at a time.

    Only frames inside ``window`` are compared (default: the span both receivers covered), so
    frames at the start/stop edges, seen by one receiver only, do not count.
    """
    res = CrossCheck(None, candump_total=len(candump), pycan_total=len(pycan))
    if not candump or not pycan:
        return res
    if window is None:
        window = (max(candump[0].ts, pycan[0].ts), min(candump[-1].ts, pycan[-1].ts))
    res.window = window
    lo, hi = window[0] - tol_s, window[1] + tol_s
    a = [f for f in candump if lo <= f.ts <= hi]
    b = [f for f in pycan if lo <= f.ts <= hi]
    for can_id in sorted({f.can_id for f in a} | {f.can_id for f in b}):
        _walk(res, [f for f in a if f.can_id == can_id], [f for f in b if f.can_id == can_id],
              tol_s)
    return res


def _walk(res: CrossCheck, a: list[Frame], b: list[Frame], tol_s: float) -> None:
    """Match two records of one CAN ID in order, by timestamp."""
    i = j = 0
    while i < len(a) and j < len(b):
        fa, fb = a[i], b[j]
        if abs(fa.ts - fb.ts) <= tol_s:
            if fa.data == fb.data:
                res.matched += 1
            else:
                res.data_mismatch.append((fa, fb))
            i += 1
            j += 1
        elif fa.ts < fb.ts:
            res.only_candump.append(fa)
            i += 1
        else:
            res.only_pycan.append(fb)
            j += 1
    res.only_candump.extend(a[i:])
    res.only_pycan.extend(b[j:])
