"""cantools reading src/estop/dbc/estop.dbc decodes the same values as estop.protocol.can."""

from __future__ import annotations

import cantools
import pytest
from cantools.database.can import Database
from hypothesis import given
from hypothesis import strategies as st

from estop.protocol import can
from estop.protocol.can import BrakeFrame, StatusFrame

SPEC_CAN_BRAKE = ["01 64 00 01 00 00 00 9C", "00 00 01 00 00 00 07 18", "01 64 00 03 00 00 0E 1D",
                  "02 1E 02 00 01 00 05 3E", "01 64 00 05 00 00 09 27"]


@pytest.fixture(scope="module")
def db() -> Database:
    database = cantools.database.load_file(str(can.dbc_path()))
    assert isinstance(database, Database)
    return database


def brake_as_dbc(frame: BrakeFrame, data: bytes) -> dict[str, int]:
    return {
        "brake_request": frame.brake_request, "brake_level": frame.brake_level,
        "state": frame.state, "reason": frame.reason, "flags": frame.flags,
        "reserved": frame.reserved, "alive_counter": frame.counter,
        "counter_reserved": data[6] >> 4, "crc": data[7],
    }


def status_as_dbc(frame: StatusFrame, data: bytes) -> dict[str, int]:
    return {
        "valid_packets": frame.valid_packets, "invalid_packets": frame.invalid_packets,
        "auth_failures": frame.auth_failures, "stops": frame.stops,
        "slowdowns": frame.slowdowns, "link_age": frame.link_age_ms,
        "alive_counter": frame.counter, "counter_reserved": data[6] >> 4, "crc": data[7],
    }


def test_messages(db: Database) -> None:
    brake = db.get_message_by_name("ESTOP_BRAKE")
    status = db.get_message_by_name("ESTOP_STATUS")
    assert (brake.frame_id, status.frame_id) == (can.BRAKE_ID, can.STATUS_ID)
    assert brake.length == status.length == 8
    assert not brake.is_extended_frame and not status.is_extended_frame
    assert brake.cycle_time == 10 and status.cycle_time == 100
    assert brake.senders == status.senders == ["ESTOP"]
    for msg in (brake, status):
        assert all(s.byte_order == "little_endian" and not s.is_signed for s in msg.signals)
        # every bit of the 8 bytes belongs to exactly one signal
        assert sum(s.length for s in msg.signals) == 64


def test_value_tables_use_the_project_names(db: Database) -> None:
    brake = db.get_message_by_name("ESTOP_BRAKE")
    assert {int(k): str(v) for k, v in brake.get_signal_by_name("state").choices.items()} == \
        can.STATE_NAMES
    assert {int(k): str(v) for k, v in brake.get_signal_by_name("reason").choices.items()} == \
        can.REASON_NAMES
    assert {int(k): str(v) for k, v in
            brake.get_signal_by_name("brake_request").choices.items()} == can.BRAKE_REQUEST_NAMES
    status = db.get_message_by_name("ESTOP_STATUS")
    assert str(status.get_signal_by_name("link_age").choices[0xFFFF]) == "none"


@pytest.mark.parametrize("text", SPEC_CAN_BRAKE)
def test_spec_examples(db: Database, text: str) -> None:
    data = bytes.fromhex(text)
    frame = BrakeFrame.decode(data)
    assert db.decode_message(can.BRAKE_ID, data, decode_choices=False) == \
        brake_as_dbc(frame, data)
    named = db.decode_message("ESTOP_BRAKE", data)
    assert str(named["state"]) == can.state_name(frame.state)
    assert str(named["reason"]) == can.reason_name(frame.reason)
    assert str(named["brake_request"]) == can.brake_request_name(frame.brake_request)
    # and cantools encodes the same bytes back
    assert db.encode_message(can.BRAKE_ID, brake_as_dbc(frame, data)) == data


def test_spec_boot_example_names(db: Database) -> None:
    named = db.decode_message(can.BRAKE_ID, bytes.fromhex(SPEC_CAN_BRAKE[0]))
    assert str(named["state"]) == "STOPPED" and str(named["reason"]) == "boot"
    assert named["brake_level"] == 100 and named["alive_counter"] == 0


@given(st.binary(min_size=8, max_size=8))
def test_random_brake_bytes(db: Database, data: bytes) -> None:
    # the DBC and the lenient parser read every bit pattern the same way, good frame or not
    frame = BrakeFrame.parse(data)
    assert db.decode_message(can.BRAKE_ID, data, decode_choices=False,
                             scaling=False) == brake_as_dbc(frame, data)


@given(st.sampled_from([BrakeFrame.for_state(0, r, 0, c) for r in range(1, 6) for c in range(15)]
                       + [BrakeFrame.for_state(s, 0, f, c, slow_level=level)
                          for s in (1, 2) for f in (0, 1) for c in range(15)
                          for level in (1, 30, 99)]))
def test_random_valid_brake_frames(db: Database, frame: BrakeFrame) -> None:
    data = frame.encode()
    assert db.decode_message(can.BRAKE_ID, data, decode_choices=False) == \
        brake_as_dbc(frame, data)
    assert db.encode_message(can.BRAKE_ID, brake_as_dbc(frame, data)) == data


@given(st.builds(StatusFrame, st.integers(0, 255), st.integers(0, 255), st.integers(0, 255),
                 st.integers(0, 15), st.integers(0, 0xFFFF), st.integers(0, 14),
                 st.integers(0, 15)))
def test_random_status_frames(db: Database, frame: StatusFrame) -> None:
    data = frame.encode()
    assert db.decode_message(can.STATUS_ID, data, decode_choices=False) == \
        status_as_dbc(frame, data)
    assert db.encode_message(can.STATUS_ID, status_as_dbc(frame, data)) == data


@given(st.binary(min_size=8, max_size=8))
def test_random_status_bytes(db: Database, data: bytes) -> None:
    assert db.decode_message(can.STATUS_ID, data, decode_choices=False,
                             scaling=False) == status_as_dbc(StatusFrame.parse(data), data)
