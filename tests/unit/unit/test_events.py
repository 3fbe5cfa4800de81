"""estopd's event log read in one place (estop.unit.events): both forms of a line, the
journal's wrappings, and the typed views (state changes, the start, output_dropped)."""

from __future__ import annotations

import json

from estop.unit.events import (
    OutputDropped,
    StateChange,
    output_dropped,
    parse,
    start,
    state_change,
    state_changes,
)

STATE_TEXT = ("estopd 104.000000 state ARMED->STOPPED reason=lift src=127.0.0.1:5 "
              "cause=lift_datagram")
STATE_JSON = json.dumps({"t_mono": 104.0, "event": "state", "from": "ARMED", "to": "STOPPED",
                         "reason": "lift", "src": "127.0.0.1:5", "cause": "lift_datagram"})
LIFTED = StateChange(104.0, "ARMED", "STOPPED", "lift", "127.0.0.1:5", "lift_datagram")


def test_a_state_change_reads_the_same_in_either_form_and_the_journals() -> None:
    entry = {"MESSAGE": STATE_JSON, "_PID": "812"}
    as_bytes = {"MESSAGE": list(STATE_JSON.encode())}  # journalctl -o json, non-UTF-8 safe
    for line in (STATE_TEXT, STATE_JSON, f"Nov 25 10:00:00 car estopd[812]: {STATE_JSON}",
                 f"Nov 25 10:00:00 car estopd[812]: {STATE_TEXT}", json.dumps(entry),
                 json.dumps(as_bytes)):
        assert state_change(parse(line)) == LIFTED, line
    text, js = parse(STATE_TEXT), parse(STATE_JSON)
    assert text is not None and js is not None and not text.json and js.json
    assert LIFTED.text() == "ARMED->STOPPED reason=lift cause=lift_datagram"


def test_lines_that_hold_no_event() -> None:
    for line in ("", "not json at all", "[1, 2]", '{"no": "event"}', "{not json",
                 "estopd: error: invalid value", "-- Boot 1234 --",
                 "Nov 25 10:00:00 car systemd[1]: Started estopd.service - estop unit."):
        assert parse(line) is None, line
    assert state_change(parse('{"t_mono": 1.0, "event": "start"}')) is None


def test_state_changes_of_a_text_log() -> None:
    log = ["estopd 100.000000 start udp=127.0.0.1:1 tcp=127.0.0.1:2 session=0x1",
           "estopd 101.000000 state STOPPED->ARMED reason=none src=127.0.0.1:4 cause=release",
           "estopd 103.000000 client_open slot=1 src=127.0.0.1:9", STATE_TEXT]
    got = state_changes(log)
    assert [(c.frm, c.to, c.cause) for c in got] == [("STOPPED", "ARMED", "release"),
                                                    ("ARMED", "STOPPED", "lift_datagram")]
    assert got[0].t_mono == 101.0 and got[1] == LIFTED


def test_the_start_gives_the_ports_and_the_session() -> None:
    for line, want in [
            ("estopd 0.000001 start udp=127.0.0.1:5700 tcp=127.0.0.1:5701 session=0x00ab",
             (5700, 5701, 0xAB)),
            ('{"t_mono": 1.5, "event": "start", "udp": "[::1]:40000", "tcp": "[::1]:40001", '
             '"session": "0x0123456789abcdef"}', (40000, 40001, 0x0123456789ABCDEF)),
            ('{"t_mono": 1.5, "event": "start", "udp_port": 40000, "tcp_port": 40001}',
             (40000, 40001, 0)),  # a peer's (the asyncio baseline)
            ("estopd 1.0 start udp_port=1 tcp_port=2", (1, 2, 0)),
            ("start udp=53100 tcp=34747 auth=--no-auth", (53100, 34747, 0))]:  # a stand-in's
        s = start(parse(line))
        assert s is not None and (s.udp_port, s.tcp_port, s.session) == want, line
    assert start(parse("estopd 1.0 start udp=127.0.0.1:1")) is None  # no TCP port
    assert start(parse(STATE_TEXT)) is None


def test_output_dropped_in_either_form() -> None:
    text = "estopd 2690.173274 output_dropped stream=can_log dropped=12 total=40 err=EPIPE"
    assert output_dropped(parse(text)) == OutputDropped(2690.173274, "can_log", 12, 40, "EPIPE")
    js = ('{"t_mono":12.5,"event":"output_dropped","stream":"log","dropped":3,"total":3,'
          '"err":"full"}')
    assert output_dropped(parse(js)) == OutputDropped(12.5, "log", 3, 3, "full")
    assert output_dropped(parse(STATE_TEXT)) is None
    assert output_dropped(parse('{"t_mono":1.0,"event":"start","udp":"127.0.0.1:1"}')) is None
    assert output_dropped(parse("estopd 1.0 output_dropped stream=can_log")) is None  # no count
    assert output_dropped(parse("{not json output_dropped")) is None
