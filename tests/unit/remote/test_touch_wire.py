"""The touch remote's messages and their MACs (estop.remote.touch.wire)."""

from __future__ import annotations

import json

import pytest

from estop.remote.touch.wire import (
    WireError,
    counter,
    decode_token,
    encode_token,
    new_nonce,
    new_token,
    parse,
    parse_held,
    seal,
)


def test_sealed_messages_verify_only_with_the_token_and_the_receivers_nonce() -> None:
    token, nonce = new_token(), new_nonce()
    text = seal({"t": "held", "n": 1, "at": 5.0, "steer": 0, "gas": 0}, token, nonce)
    msg = parse(text, token, nonce)
    assert msg.authentic and msg.kind == "held" and msg.fields["n"] == 1
    assert not parse(text, new_token(), nonce).authentic  # another token
    assert not parse(text, token, new_nonce()).authentic  # another connection's nonce
    assert not parse(text, None, nonce).authentic
    tag, body = text.split(" ", 1)
    assert not parse(f"{tag} {body.replace('0', '1', 1)}", token, nonce).authentic  # altered
    plain = parse(seal({"t": "stop"}), token, nonce)
    assert plain.kind == "stop" and not plain.authentic


@pytest.mark.parametrize("text", ["", "held", "- not json", "- [1, 2]", "- {\"x\": 1}",
                                  "abc {\"t\": \"stop\"}", "- " + "x" * 2000])
def test_malformed_messages_are_errors(text: str) -> None:
    with pytest.raises(WireError):
        parse(text, new_token(), new_nonce())


def test_held_frames_hold_numbers_in_range() -> None:
    assert parse_held({"at": 1.5, "steer": -1, "gas": 0.25}).gas == 0.25
    for bad in ({"at": 1, "steer": 1.01, "gas": 0}, {"at": 1, "steer": 0, "gas": True},
                {"at": 1, "steer": "0", "gas": 0}, {"at": -1, "steer": 0, "gas": 0},
                {"steer": 0, "gas": 0}, json.loads('{"at": 1, "steer": NaN, "gas": 0}')):
        with pytest.raises(WireError):
            parse_held(bad)
    assert counter({"n": 3}) == 3
    for bad_n in (0, -1, 1.5, True, "2", None):
        with pytest.raises(WireError):
            counter({"n": bad_n})


def test_the_token_in_the_fragment() -> None:
    token = new_token()
    text = encode_token(token)
    assert "=" not in text and len(text) == 22 and decode_token(text) == token
    for bad in ("", "AAAA", "!!!!", text + "AA"):
        with pytest.raises(WireError):
            decode_token(bad)
