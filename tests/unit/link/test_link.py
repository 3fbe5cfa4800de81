"""``estop link`` against known answers.

Synthetic Gilbert traces (a seeded numpy generator in tests/link_util.py, independent of the
tool and of ``estop.model.wifi``) have known loss and mean burst; the tool must recover them from
arrival times, from the daemon's binned histogram (made there with an independent
implementation of the daemon's bin function) and from a pcap written here with dpkt. Its
false-stop rates must agree with the issue's closed form and with a count of stops made by the
deadline rule itself.
"""

from __future__ import annotations

import json
import socket
import struct
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import dpkt
import numpy as np
import pytest

import estop.link.fit as linkfit
from cli_util import run_cli
from estop import cli
from estop.link.fit import false_stops_per_hour, fit, lost_in_row
from estop.link.format import format_report
from estop.link.gaps import Histogram, daemon_bins, gaps_from_histogram, gaps_from_times
from estop.link.histogram import read_histogram_log
from estop.link.poisson import poisson_lower95, poisson_upper95
from estop.link.read import read_pcap_times
from estop.link.report import ENOUGH, TIMEOUTS_MS, report
from estop.model.wifi import WIFI, LinkConfig, LinkModel
from link_util import (
    EDGES_US,
    HOURS10,
    RATE,
    arrivals_us,
    gilbert_lost,
    histogram_log,
    loss_runs,
)

pytestmark = pytest.mark.timeout(120)


# --------------------------------------------------------------------------- generators


def test_the_daemons_bins_are_the_cores() -> None:
    # estop.link.gaps.daemon_bins against the core's own estop_gap_bin, at every edge and
    # around it; the edges are the lower ends of the bins (the event's example: 0, 1024,
    # 1536, 2048, 3072; bin 31 from 2^25 us)
    from estop.core import lib

    assert EDGES_US[:5] == [0, 1024, 1536, 2048, 3072] and EDGES_US[31] == 1 << 25
    probe = sorted({max(0, e + d) for e in EDGES_US for d in (-1, 0, 1)}
                   | {20_000, 40_000, 200_000, 2**32 - 1})
    vec = daemon_bins(np.array(probe, dtype=np.int64)).tolist()
    assert vec == [lib.estop_gap_bin(g) for g in probe]
    for g, b in zip(probe, vec, strict=True):
        assert EDGES_US[b] <= g and (b == 31 or g < EDGES_US[b + 1]), (g, b)
    assert daemon_bins(np.array([10**12])).tolist() == [31]  # beyond u32: still the last bin


@dataclass
class Trace:
    loss: float
    burst: float
    lost: np.ndarray
    t_us: np.ndarray

    @property
    def times(self) -> np.ndarray:
        return self.t_us / 1e6

    @property
    def hours(self) -> float:
        return self.lost.size / RATE / 3600.0


TRACE_PARAMS = {1.5: 11, 3.0: 12, 5.0: 13}


@pytest.fixture(scope="module", params=sorted(TRACE_PARAMS))
def trace10h(request: pytest.FixtureRequest) -> Trace:
    burst = float(request.param)
    lost = gilbert_lost(HOURS10, 0.09, burst, TRACE_PARAMS[burst])
    return Trace(0.09, burst, lost, arrivals_us(lost))


# --------------------------------------------------------------------------- the stop rule


def deadline_packets(timeout_ms: int, rate_hz: int) -> int:
    """Packets due strictly before the deadline t0 + D, counted one by one in exact rationals:
    the number that must all be lost for the stop to come (one due at the deadline is late)."""
    period = Fraction(1, rate_hz)
    deadline = Fraction(timeout_ms, 1000)
    j = 0
    while (j + 1) * period < deadline:
        j += 1
    return j


def test_lost_in_row_is_the_issue_example() -> None:
    assert lost_in_row(200, 50.0) == 9  # "9 losses in a row trip it"
    assert lost_in_row(210, 50.0) == 10
    assert lost_in_row(190, 50.0) == 9
    assert lost_in_row(50, 50.0) == 2
    assert lost_in_row(1000, 50.0) == 49
    assert lost_in_row(20, 50.0) == 0  # timeout of one period: every gap trips it


@pytest.mark.parametrize("rate_hz", [10, 20, 30, 50, 60, 100, 125])
def test_lost_in_row_counts_packets_due_before_the_deadline(rate_hz: int) -> None:
    for d in TIMEOUTS_MS:
        assert lost_in_row(d, float(rate_hz)) == deadline_packets(d, rate_hz), (d, rate_hz)


def test_closed_form_gives_the_issues_numbers() -> None:
    n = lost_in_row(200, 50.0)
    independent = false_stops_per_hour(0.09, 1.0 / 0.91, n, 50.0)  # burst of iid loss
    assert independent == pytest.approx(6.3e-5, rel=0.05)  # "about 6e-5"
    assert false_stops_per_hour(0.09, 3.0, n, 50.0) == pytest.approx(210, rel=0.01)
    assert false_stops_per_hour(0.09, 5.0, n, 50.0) == pytest.approx(540, rel=0.01)


def test_deadline_rule_counts_stops_like_the_closed_form(trace10h: Trace) -> None:
    # Monte Carlo: stops the deadline rule itself makes on the trace (gap >= D in exact
    # microseconds, a packet at the deadline is late) against the closed form at the TRUE
    # parameters, where the count is large enough (>= 400: Poisson error 5 %)
    gaps_us = np.diff(trace10h.t_us)
    runs = loss_runs(trace10h.lost)
    checked = 0
    for d in TIMEOUTS_MS:
        stops = int((gaps_us >= d * 1000).sum())
        n = lost_in_row(d, RATE)
        assert stops == int((runs >= n).sum())  # the stop rule is "n lost in a row"
        if stops >= 400:
            expected = false_stops_per_hour(trace10h.loss, trace10h.burst, n, RATE)
            assert stops / trace10h.hours == pytest.approx(expected, rel=0.10), d
            checked += 1
    assert checked >= 8


# --------------------------------------------------------------------------- the fit


def test_recovers_loss_and_burst_from_arrival_times(trace10h: Trace) -> None:
    f = fit(gaps_from_times(trace10h.times, RATE), RATE)
    assert f.loss == pytest.approx(trace10h.loss, rel=0.10)
    assert f.mean_burst == pytest.approx(trace10h.burst, rel=0.10)
    assert f.hours == pytest.approx(trace10h.hours, rel=0.001)
    # what the tool counts is the trace's truth
    runs = loss_runs(trace10h.lost)
    assert f.bursts == runs.size and f.lost == runs.sum()


def test_recovers_loss_and_burst_from_the_daemon_log(trace10h: Trace, tmp_path: Path) -> None:
    log = tmp_path / "estopd.jsonl"
    log.write_text(histogram_log([trace10h.t_us]))
    h = read_histogram_log(str(log))
    assert h.runs == 1 and sum(h.counts) == trace10h.t_us.size - 1
    fb = fit(gaps_from_histogram(h, RATE), RATE)
    assert fb.loss == pytest.approx(trace10h.loss, rel=0.10)
    assert fb.mean_burst == pytest.approx(trace10h.burst, rel=0.10)
    # The bins are coarse above 4 losses (100 ms) but the burst length is mostly decided by
    # the short, exactly binned gaps: at 50 Hz the binned fit stays within 1 % of the fit to
    # the exact times (measured: within 0.1 %), and the estimated length within 1 %.
    fe = fit(gaps_from_times(trace10h.times, RATE), RATE)
    assert fb.loss == pytest.approx(fe.loss, rel=0.01)
    assert fb.mean_burst == pytest.approx(fe.mean_burst, rel=0.01)
    assert fb.hours == pytest.approx(trace10h.hours, rel=0.01)


def test_model_rates_are_the_closed_form(trace10h: Trace) -> None:
    rep = report(gaps_from_times(trace10h.times, RATE), RATE)
    f = rep.fit
    assert f.mean_burst is not None
    for row in rep.rows:
        # the tool's rate is the closed form at its own fit ...
        at_fit = false_stops_per_hour(f.loss, f.mean_burst, row.lost_in_row, RATE)
        assert row.model == pytest.approx(at_fit, rel=1e-9)
        # ... and the closed form at the true parameters lies inside its 95 % range; within
        # 10 % up to 400 ms (n <= 19: the error of 1/burst grows by n - 1 with the timeout)
        truth = false_stops_per_hour(trace10h.loss, trace10h.burst, row.lost_in_row, RATE)
        assert row.model_low <= truth <= row.model_high, row
        if row.timeout_ms <= 400:
            assert row.model == pytest.approx(truth, rel=0.10), row


def test_model_agrees_with_the_counted_stops(trace10h: Trace) -> None:
    # the recording's own count (Monte Carlo) against the fitted model, where large enough
    rep = report(gaps_from_times(trace10h.times, RATE), RATE)
    checked = 0
    for row in rep.rows:
        assert row.gaps_sure == row.gaps_possible  # exact times: exact counts
        if row.gaps_sure >= 400:
            assert row.empirical is not None
            assert row.model == pytest.approx(row.empirical, rel=0.10), row
            checked += 1
        elif row.gaps_sure < ENOUGH:
            assert row.empirical is None and row.empirical_upper95 > 0
    assert checked >= 8


def test_binned_counts_bracket_the_true_counts(trace10h: Trace, tmp_path: Path) -> None:
    log = tmp_path / "estopd.jsonl"
    log.write_text(histogram_log([trace10h.t_us], every_s=600.0))
    rep = report(gaps_from_histogram(read_histogram_log(str(log)), RATE), RATE)
    runs = loss_runs(trace10h.lost)
    exact_rows = 0
    for row in rep.rows:
        true = int((runs >= row.lost_in_row).sum())
        assert row.gaps_sure <= true <= row.gaps_possible, row
        exact_rows += row.gaps_sure == row.gaps_possible
        if row.gaps_sure >= 400:
            assert row.model == pytest.approx(true / trace10h.hours, rel=0.10), row
    # at 50 Hz the timeouts whose n starts a bin are exact: 50, 60, 70, 80, 90, 130, ...
    assert exact_rows >= 6


def test_binned_likelihood_on_exact_cells_is_the_closed_form() -> None:
    lost = gilbert_lost(300_000, 0.09, 3.0, 5)
    g = gaps_from_times(arrivals_us(lost) / 1e6, RATE)
    closed = fit(g, RATE)
    assert g.exact
    mask = g.k_lo >= 1
    r = linkfit._argmax_r(g.k_lo[mask], g.k_hi[mask], g.counts[mask])
    assert r == pytest.approx(closed.p_bg, rel=1e-6)
    assert linkfit._se_numeric(r, g.k_lo[mask], g.k_hi[mask], g.counts[mask]) == \
        pytest.approx(closed.p_bg_se, rel=1e-3)


def test_restarted_daemon_runs_add_up(tmp_path: Path) -> None:
    lost = gilbert_lost(400_000, 0.09, 3.0, 21)
    t = arrivals_us(lost)
    half = t.size // 2
    whole = Histogram(tuple(EDGES_US), tuple(int(c) for c in np.bincount(
        daemon_bins(np.diff(t)), minlength=32)), 0, 0, 0, 0, 1, False)
    crossing = int(daemon_bins(np.array([t[half] - t[half - 1]]))[0])
    log = tmp_path / "two.jsonl"
    log.write_text(histogram_log([t[:half], t[half:]]))
    h = read_histogram_log(str(log))
    assert h.runs == 2
    expected = list(whole.counts)
    expected[crossing] -= 1  # the gap across the restart is in neither run
    assert list(h.counts) == expected
    assert h.valid == t.size
    # a restart whose `start` line is missing shows as counts going down: a new run too
    text = "\n".join(x for x in log.read_text().splitlines() if '"start"' not in x)
    log.write_text(text + "\n")
    h2 = read_histogram_log(str(log))
    assert h2.runs == 2 and h2.counts == h.counts


def test_jittered_arrivals_still_fit(tmp_path: Path) -> None:
    # +-1 ms of arrival jitter: the rounding of gaps to whole periods absorbs it; the bins
    # mostly too (the narrowest margin at 50 Hz is 1.7 ms, at the 98.3 ms edge)
    lost = gilbert_lost(720_000, 0.09, 3.0, 8)
    rng = np.random.default_rng(9)
    t = arrivals_us(lost) + rng.integers(-1000, 1001, size=int((~lost).sum()))
    t = np.maximum.accumulate(t)
    fe = fit(gaps_from_times(t / 1e6, RATE), RATE)
    log = tmp_path / "j.jsonl"
    log.write_text(histogram_log([t]))
    fb = fit(gaps_from_histogram(read_histogram_log(str(log)), RATE), RATE)
    for f in (fe, fb):
        assert f.loss == pytest.approx(0.09, rel=0.10)
        assert f.mean_burst == pytest.approx(3.0, rel=0.10)


def test_jitter_beyond_a_bin_is_credited_to_the_nearest_period() -> None:
    # gaps of 27 ms fall in [24.6, 32.8) ms, which holds no multiple of 20 ms: counted as k=0
    counts = [0] * 32
    counts[int(daemon_bins(np.array([20_000]))[0])] = 900
    counts[int(daemon_bins(np.array([27_000]))[0])] = 50
    counts[int(daemon_bins(np.array([40_000]))[0])] = 50
    g = gaps_from_histogram(Histogram(tuple(EDGES_US), tuple(counts), 1001, 0, 0,
                                          100_000, 1, False), RATE)
    assert int(g.counts[g.k_lo == 0][0]) == 950 and g.notes
    f = fit(g, RATE)
    assert f.bursts == 50 and f.mean_burst == pytest.approx(1.0)


def test_pauses_are_left_out(tmp_path: Path) -> None:
    lost = gilbert_lost(180_000, 0.09, 3.0, 4)
    t = arrivals_us(lost) / 1e6
    t2 = np.concatenate([t, t + t[-1] + 30.0])  # the finger lifted for 30 s
    g1, g2 = gaps_from_times(t, RATE), gaps_from_times(t2, RATE)
    assert g2.pauses == 1 and g1.pauses == 0
    f1, f2 = fit(g1, RATE), fit(g2, RATE)
    assert f2.hours == pytest.approx(2 * f1.hours, rel=1e-3)
    assert f2.mean_burst == pytest.approx(f1.mean_burst, rel=1e-9)
    g0 = gaps_from_times(t2, RATE, max_gap=0.0)  # no limit: the pause is one long burst
    assert g0.pauses == 0 and int(g0.k_lo.max()) >= 1499


# --------------------------------------------------------------------------- estop's remote


def test_remote_link_model_is_the_fitted_gilbert_model() -> None:
    # estop remote's LinkModel: P(bad->good) = 1/burst, P(good->bad) = loss/burst/(1 - loss),
    # the packet's fate is the state after the step: the model the tool fits
    cfg = LinkConfig(loss=0.09, burst=3.0)
    model = LinkModel(cfg, seed=3)
    lost = np.fromiter((model.lose_next() for _ in range(300_000)), dtype=bool, count=300_000)
    f = fit(gaps_from_times(arrivals_us(lost) / 1e6, RATE), RATE)
    assert f.loss == pytest.approx(cfg.loss, rel=0.10)
    assert f.mean_burst == pytest.approx(cfg.burst, rel=0.10)
    assert model.stats.lost == int(lost.sum())


def test_remote_link_model_with_delay_and_small_jitter() -> None:
    cfg = LinkConfig(loss=0.09, burst=5.0, delay=0.1, jitter=0.004)  # jitter < P/4
    model = LinkModel(cfg, seed=4)
    arrivals = [model.transmit(i / RATE) for i in range(300_000)]
    t = np.asarray([a for a in arrivals if a is not None])
    f = fit(gaps_from_times(t, RATE), RATE)
    assert f.loss == pytest.approx(cfg.loss, rel=0.10)
    assert f.mean_burst == pytest.approx(cfg.burst, rel=0.10)


def test_heavy_jitter_wifi_preset_fits_the_long_runs() -> None:
    # estop remote's WIFI preset: 9 % loss, bursts of 2, delay 100 ms + 0..50 ms jitter with
    # order kept. Jitter of 2.5 send periods makes late packets look like losses and bunched
    # ones like none: a fit to every run sees short bursts and is far too optimistic about
    # long gaps. The automatic fit uses the longer runs, which keep the burst law.
    model = LinkModel(WIFI, seed=5)
    arrivals = [model.transmit(i / RATE) for i in range(300_000)]
    t = np.asarray([a for a in arrivals if a is not None])
    t_us = np.rint(t * 1e6).astype(np.int64)
    gaps = gaps_from_times(t, RATE)
    assert gaps.extra["off_grid"] > 0.2 and gaps.notes
    auto = report(gaps, RATE)
    plain = report(gaps, RATE, tail_from=1)
    assert auto.fit.tail_from > 1
    assert auto.fit.mean_burst == pytest.approx(WIFI.burst, rel=0.10)
    assert plain.fit.mean_burst < 0.8 * WIFI.burst  # the misread short runs
    hours = auto.fit.hours
    checked = 0
    for row_a, row_p in zip(auto.rows, plain.rows, strict=True):
        stops = int((np.diff(t_us) >= row_a.timeout_ms * 1000).sum())  # the deadline rule
        if row_a.lost_in_row < auto.fit.tail_from:
            # below the fitted runs (marked ^): the recording itself has plenty there
            assert row_a.enough
        elif stops >= 30:
            assert row_a.model >= 0.9 * stops / hours, row_a  # not optimistic
            assert row_a.model <= 3.0 * stops / hours, row_a  # nor useless
            if row_a.timeout_ms >= 150:
                assert row_p.model < 0.2 * stops / hours, row_p
            checked += 1
    assert checked >= 6


def test_forced_tail_on_a_clean_trace_agrees(trace10h: Trace) -> None:
    # without jitter every tail follows the same law: k0 = 3 recovers the same link
    gaps = gaps_from_times(trace10h.times, RATE)
    f = fit(gaps, RATE, tail_from=3)
    assert f.tail_from == 3 and f.tail_bursts < f.bursts
    assert f.loss == pytest.approx(trace10h.loss, rel=0.10)
    assert f.mean_burst == pytest.approx(trace10h.burst, rel=0.10)
    assert fit(gaps, RATE).tail_from == 1  # and the automatic choice sees no jitter


def test_recommendation_never_contradicts_the_recording() -> None:
    # short bursts plus 20 one-second outages in 2 hours: the Gilbert model fitted to every
    # run calls 1 s safe, the recording says otherwise; the recommendation follows the data
    lost = gilbert_lost(360_000, 0.05, 1.5, 40)
    for start in range(10_000, 350_000, 17_000):
        lost[start:start + 50] = True
    t = arrivals_us(lost) / 1e6
    rep = report(gaps_from_times(t, RATE), RATE, tail_from=1)
    one_s = next(r for r in rep.rows if r.timeout_ms == 1000)
    assert one_s.model < 0.01 and one_s.gaps_sure == 20 and one_s.contradicted
    assert rep.recommended_ms is not None and rep.recommended_ms > 1000
    text = "\n".join(format_report(rep))
    assert "! the recording holds more such gaps" in text


# --------------------------------------------------------------------------- pcap


def _udp_frame(src: str, dst: str, dport: int, payload: bytes, v6: bool = False) -> bytes:
    udp = dpkt.udp.UDP(sport=40000, dport=dport, data=payload, ulen=8 + len(payload))
    ip: dpkt.Packet
    if v6:
        ip = dpkt.ip6.IP6(src=socket.inet_pton(socket.AF_INET6, src),
                          dst=socket.inet_pton(socket.AF_INET6, dst), nxt=dpkt.ip.IP_PROTO_UDP,
                          hlim=64, data=udp, plen=len(udp))
        etype = dpkt.ethernet.ETH_TYPE_IP6
    else:
        ip = dpkt.ip.IP(src=socket.inet_aton(src), dst=socket.inet_aton(dst),
                        p=dpkt.ip.IP_PROTO_UDP, data=udp, len=20 + len(udp))
        etype = dpkt.ethernet.ETH_TYPE_IP
    return bytes(dpkt.ethernet.Ethernet(src=b"\x02" * 6, dst=b"\x04" * 6, type=etype, data=ip))


BODY20 = bytes.fromhex("9A99993E000080BE080000000100000000000000")


def test_pcap_gives_the_same_arrival_times(tmp_path: Path) -> None:
    lost = gilbert_lost(3000, 0.09, 3.0, 6)
    t = arrivals_us(lost) / 1e6 + 1_700_000_000.0
    path = tmp_path / "control.pcap"
    with open(path, "wb") as f:
        w = dpkt.pcap.Writer(f, linktype=dpkt.pcap.DLT_EN10MB, nano=True)
        for i, ts in enumerate(t):
            v6 = i % 5 == 0
            body = (BODY20, BODY20[:16], b"E" * 60)[i % 3]
            w.writepkt(_udp_frame("::1" if v6 else "10.0.0.2", "::2" if v6 else "10.0.0.1",
                                  5700, body, v6), ts=ts)
            if i % 50 == 0:  # traffic that must not count
                w.writepkt(_udp_frame("10.0.0.2", "10.0.0.1", 5700, b"S" * 48), ts=ts + 1e-4)
                w.writepkt(_udp_frame("10.0.0.2", "10.0.0.1", 5701, BODY20), ts=ts + 2e-4)
                w.writepkt(_udp_frame("10.0.0.2", "10.0.0.1", 5700, BODY20 + b"x"),
                           ts=ts + 3e-4)
    times, other = read_pcap_times(str(path), 5700)
    assert times.size == t.size
    assert np.allclose(times, t, rtol=0, atol=1e-6)
    assert other == 2 * len(range(0, t.size, 50))
    a = fit(gaps_from_times(times, RATE), RATE)
    b = fit(gaps_from_times(t, RATE), RATE)
    assert (a.bursts, a.lost, a.gaps) == (b.bursts, b.lost, b.gaps)


@pytest.mark.parametrize("linktype", ["sll", "raw", "null"])
def test_pcap_link_types(tmp_path: Path, linktype: str) -> None:
    path = tmp_path / f"{linktype}.pcap"
    times = [10.0, 10.02, 10.08, 10.1]
    with open(path, "wb") as f:
        dlt = {"sll": dpkt.pcap.DLT_LINUX_SLL, "raw": dpkt.pcap.DLT_RAW,
               "null": dpkt.pcap.DLT_NULL}[linktype]
        w = dpkt.pcap.Writer(f, linktype=dlt)
        for ts in times:
            ip = dpkt.ethernet.Ethernet(_udp_frame("10.0.0.2", "10.0.0.1", 5700, BODY20)).data
            if linktype == "sll":
                frame = bytes(dpkt.sll.SLL(type=0x0800, data=ip))
            elif linktype == "null":
                frame = struct.pack("=I", socket.AF_INET) + bytes(ip)
            else:
                frame = bytes(ip)
            w.writepkt(frame, ts=ts)
    got, other = read_pcap_times(str(path), 5700)
    assert np.allclose(got, times, atol=1e-6) and other == 0


# --------------------------------------------------------------------------- the command


def run_link(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    return run_cli(capsys, "link", *args)


def test_cli_table_json_and_plot(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    lost = gilbert_lost(360_000, 0.09, 5.0, 31)  # 2 hours
    times = tmp_path / "times.txt"
    times.write_text("# arrival times\n" + "\n".join(f"{x:.6f}" for x in
                                                     arrivals_us(lost) / 1e6) + "\n")
    code, text, err = run_link([str(times)], capsys)
    assert code == 0 and err == ""
    for d in (100, 200, 300, 400, 500, 600, 700, 800, 900, 1000):
        assert any(line.split()[:2] == [str(d), "ms"] for line in text.splitlines()), d
    assert "ceil(D/P) - 1" in text and "recommendation:" in text

    png = tmp_path / "link.png"
    code, text, err = run_link([str(times), "--json", "--plot", str(png)], capsys)
    assert code == 0 and err == ""
    rep = json.loads(text)
    assert rep["loss"] == pytest.approx(0.09, rel=0.10)
    assert rep["mean_burst"] == pytest.approx(5.0, rel=0.10)
    assert rep["hours"] == pytest.approx(2.0, rel=0.01)
    ms = [r["timeout_ms"] for r in rep["rows"]]
    assert ms[0] == 50 and ms[-1] == 2000 and set(range(100, 1001, 100)) <= set(ms)
    for r in rep["rows"]:
        assert r["false_stops_per_hour"] == pytest.approx(false_stops_per_hour(
            rep["loss"], rep["mean_burst"], lost_in_row(r["timeout_ms"], 50.0), 50.0))
    rec = rep["recommended_timeout_ms"]
    first_below = next(r["timeout_ms"] for r in rep["rows"]
                       if r["false_stops_per_hour"] < 0.01)
    assert rec == first_below
    data = png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000

    # a stricter target moves the recommendation later; an impossible one finds none
    code, text, _ = run_link([str(times), "--json", "--target", "1e-6"], capsys)
    assert json.loads(text)["recommended_timeout_ms"] > rec
    code, text, _ = run_link([str(times), "--target", "1e-40"], capsys)
    assert code == 0 and "no timeout up to 2000 ms" in text


def test_cli_reads_the_daemon_log_and_pcap(tmp_path: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    lost = gilbert_lost(180_000, 0.09, 3.0, 32)
    t = arrivals_us(lost)
    log = tmp_path / "estopd.log"
    log.write_text(histogram_log([t]))
    code, text, err = run_link([str(log), "--json"], capsys)
    assert code == 0 and err == "", err
    rep = json.loads(text)
    assert rep["binned"] and rep["input"]["valid"] == t.size
    assert rep["mean_burst"] == pytest.approx(3.0, rel=0.10)
    code, text, _ = run_link([str(log)], capsys)
    assert "estimated from the binned gaps" in text and "valid" in text

    cap = tmp_path / "c.pcap"
    with open(cap, "wb") as f:
        w = dpkt.pcap.Writer(f)
        for ts in t[:2000] / 1e6:
            w.writepkt(_udp_frame("10.0.0.2", "10.0.0.1", 5700, BODY20), ts=float(ts))
    code, text, err = run_link([str(cap), "--json"], capsys)
    assert code == 0 and json.loads(text)["gaps"] == 1999
    code, text, err = run_link([str(cap), "--json", "--udp-port", "5800"], capsys)
    assert code == 4 and "fewer than 2 control packets" in err
    code, text, err = run_link([str(cap), "--json", "--port", "5800"], capsys)  # older name
    assert code == 4 and "fewer than 2 control packets" in err


def test_cli_no_loss(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    times = tmp_path / "clean.txt"
    times.write_text("\n".join(f"{i / 50:.6f}" for i in range(5000)) + "\n")
    code, text, _ = run_link([str(times), "--json"], capsys)
    rep = json.loads(text)
    assert code == 0 and rep["loss"] == 0 and rep["mean_burst"] is None
    assert rep["recommended_timeout_ms"] is None
    assert all(r["false_stops_per_hour"] == 0 for r in rep["rows"])
    code, text, _ = run_link([str(times)], capsys)
    assert "no packet lost" in text


def test_cli_slow_remote_timeout_below_one_period(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    lost = gilbert_lost(20_000, 0.05, 2.0, 33)
    times = tmp_path / "slow.txt"
    times.write_text("\n".join(f"{x:.6f}" for x in np.flatnonzero(~lost) / 10.0) + "\n")
    code, text, _ = run_link([str(times), "--json", "--rate-hz", "10"], capsys)
    rep = json.loads(text)
    first = rep["rows"][0]  # 50 ms at 10 Hz: every gap is longer than the timeout
    assert first["lost_in_row"] == 0
    assert first["false_stops_per_hour"] == pytest.approx(rep["gaps"] / rep["hours"])
    assert rep["recommended_timeout_ms"] > 100


@pytest.mark.parametrize("content, fmt, message", [
    (b"0.0\n0.02\nabc\n", "auto", ":3: not a time"),
    (b"0.0\n0.04\n0.02\n", "auto", ":3: time goes backwards"),
    (b"0.0\nnan\n", "auto", "not a finite time"),
    (b"5.0\n", "auto", "need at least 2 packets"),
    (b"", "auto", "empty file"),
    (b'{"t_mono": 1.0, "event": "start"}\n{"t_mono": 2.0, "event": "exit"}\n', "auto",
     "no link_histogram event"),
    (b'{"event": "link_histogram", "valid": 1, "invalid": 0, "silences": 0, "warn_us": 1, '
     b'"edges_us": [0, 1024], "counts": [1]}\n', "auto", "malformed link_histogram"),
    (b'{"event": "link_histogram", "valid": -1, "invalid": 0, "silences": 0, "warn_us": 1, '
     b'"edges_us": [0, 1024], "counts": [1, 2]}\n', "auto", "'valid' is not a count"),
    (b"\xd4\xc3\xb2\xa1\x02\x00\x04\x00", "auto", "not a pcap"),
    (b"\xff\xfe\x00garbage", "log", "not a text file"),
    (b"hello\n", "pcap", "not a pcap"),
])
def test_cli_bad_input_is_one_line_exit_4(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                          content: bytes, fmt: str, message: str) -> None:
    path = tmp_path / "bad"
    path.write_bytes(content)
    code, text, err = run_link([str(path), "--format", fmt], capsys)
    assert code == 4, (code, err)  # a file that cannot be understood (the exit-code table)
    assert text == "" and err.count("\n") == 1 and err.startswith("estop: error: ")
    assert message in err, err


def test_cli_bad_options_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    ok = tmp_path / "t.txt"
    ok.write_text("0\n0.02\n0.06\n")
    for args, want in (([str(tmp_path / "missing")], 4), ([str(ok), "--rate-hz", "0"], 2),
                       ([str(ok), "--target", "-1"], 2), ([str(ok), "--max-gap", "1"], 2),
                       ([str(ok), "--max-gap-s", "1"], 2),
                       ([str(ok), "--plot", str(tmp_path / "no" / "dir.png")], 4)):
        code, _, err = run_link(args, capsys)
        assert code == want and err.count("\n") == 1 and err.startswith("estop"), (args, err)


def test_poisson_bounds() -> None:
    # the usual tables (Garwood, one-sided 95 %)
    assert poisson_upper95(0) == pytest.approx(2.996, abs=1e-3)
    assert poisson_upper95(1) == pytest.approx(4.744, abs=1e-3)
    assert poisson_upper95(10) == pytest.approx(16.962, abs=1e-3)
    assert poisson_lower95(0) == 0.0
    assert poisson_lower95(1) == pytest.approx(0.0513, abs=1e-4)
    assert poisson_lower95(10) == pytest.approx(5.425, abs=1e-3)
    # past 100 events an approximation takes over without a jump
    for f in (poisson_lower95, poisson_upper95):
        assert f(101) == pytest.approx(f(100) * 101 / 100, rel=0.01)
        assert f(100) < f(101) < f(102)


def test_help_mentions_the_stop_rule(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["link", "--help"]) == 0
    assert "ceil(D/P) - 1" in capsys.readouterr().out.replace("\n", " ")


