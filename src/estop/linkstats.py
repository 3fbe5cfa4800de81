"""The analysis behind ``estop link`` (:mod:`estop.link`): a recording of the control link
turned into false stops per hour per timeout.

This module is the public face of the analysis; the work is done in small modules with
one-way dependencies: :mod:`estop.linkgaps` (gap cells) <- :mod:`estop.linklog` (estopd's
log) <- :mod:`estop.linkread` (the other input files, the choice of reader);
:mod:`estop.linkgaps` <- :mod:`estop.linkfit` (the stop rule and the fit) <-
:mod:`estop.linkunit` (the unit's own counts against the model, with :mod:`estop.linkpoisson`)
<- :mod:`estop.linkreport` (rows, the recommended S and T) <- :mod:`estop.linkformat` (text,
JSON) and :mod:`estop.linkplot`.

Inputs (one file; the kind is recognised from its first bytes, or named with ``--format``):

- ``log``: estopd's ``--log-json`` log. Its ``link_histogram`` events hold the gaps between
  consecutive valid control packets, binned in half-octaves (cumulative since the daemon
  started); each ``start`` event begins a new run and the runs are added up.
- ``times``: arrival times, one float (seconds) per line; blank lines and ``#`` comments skipped.
- ``pcap``: a capture (pcap or pcapng) of the control port: UDP datagrams to ``--port`` of a
  control packet's length (20, 16 or 60 bytes) are the packets.

The model is a two-state Gilbert channel at the known send rate: every packet the remote sends
is either received (good state) or lost (bad state); ``p_gb`` = P(good -> bad), ``p_bg`` =
P(bad -> good). A gap between two received packets of (k+1) send periods means k lost in a row.
Loss = p_gb / (p_gb + p_bg), mean burst = 1 / p_bg.

A stop comes at the deadline: with send period P and timeout D, after a packet at t0 the next
ones are due at t0 + P, t0 + 2P, ...; only those due strictly before t0 + D can keep the unit
alive, and there are n = ceil(D / P) - 1 of them. The unit stops when those n are all lost
(50 Hz, 200 ms: packets due at 20 .. 180 ms, n = 9; the 10th is due at the deadline itself,
when the stop has already come). False stops per hour = bursts of n or more losses per hour =
packets per hour x (1 - loss) x p_gb x (1 - p_bg)^(n - 1).
"""

from __future__ import annotations

from estop.linkfit import Fit, false_stops_per_hour, fit, lost_in_row
from estop.linkformat import format_report, report_json
from estop.linkgaps import (
    Gaps,
    Histogram,
    LinkInputError,
    UnitRecord,
    gaps_from_histogram,
    gaps_from_times,
)
from estop.linklog import read_histogram_log
from estop.linkplot import write_plot
from estop.linkpoisson import poisson_lower95, poisson_upper95
from estop.linkread import detect_format, load, read_pcap_times, read_times
from estop.linkreport import (
    DEFAULT_SLOW_TARGET,
    DEFAULT_TARGET,
    ENOUGH,
    TIMEOUTS_MS,
    Report,
    Row,
    recommend_slow,
    report,
)
from estop.linkunit import Check, UnitCheck, check_unit

__all__ = [
    "DEFAULT_SLOW_TARGET",
    "DEFAULT_TARGET",
    "ENOUGH",
    "Check",
    "Fit",
    "Gaps",
    "Histogram",
    "LinkInputError",
    "Report",
    "Row",
    "TIMEOUTS_MS",
    "UnitCheck",
    "UnitRecord",
    "check_unit",
    "detect_format",
    "false_stops_per_hour",
    "fit",
    "format_report",
    "gaps_from_histogram",
    "gaps_from_times",
    "load",
    "lost_in_row",
    "poisson_lower95",
    "poisson_upper95",
    "read_histogram_log",
    "read_pcap_times",
    "read_times",
    "recommend_slow",
    "report",
    "report_json",
    "write_plot",
]
