"""The touch page's WebSocket messages and their pairing: pure code, no I/O.

The page is served over plain HTTP (a tablet on the car's Wi-Fi; no certificate to install),
so anyone on that network reads every byte of it. The pairing token therefore never travels:
it is in the URL's fragment (``http://host:8081/#k=TOKEN``), which a browser keeps to itself,
and each side proves it with a MAC instead (keyed BLAKE2s, 16 bytes, over the receiver's
nonce and the message). The page computes it in ``static/blake2s.js``: ``crypto.subtle`` is
missing outside a secure context (``http://192.168...``).

A message is one WebSocket text frame, ``MAC JSON``: MAC is 32 hex digits, or ``-`` for an
unauthenticated one, and JSON an object with ``t`` (its type) and, when authenticated, ``n``
(the sender's message counter, rising by at least 1 each message, so nothing replays within a
connection; the nonces keep a message of one connection from counting in another).

The exchange: the server says ``hello`` (its nonce, the control period); the page answers
``pair`` (its own nonce) authenticated with the server's nonce; from then on every message
of the page is authenticated with the server's nonce and every message of the server with the
page's. A page without the token (or with another one) is not paired: it sees the unit's state
and may press STOP (anyone may stop), nothing else.
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import hmac
import json
import math
import secrets
from dataclasses import dataclass
from typing import Any

__all__ = [
    "MAC_HEX",
    "NONCE_BYTES",
    "TOKEN_BYTES",
    "UNAUTHENTICATED",
    "HeldFrame",
    "Message",
    "WireError",
    "counter",
    "decode_token",
    "encode_token",
    "mac",
    "new_nonce",
    "new_token",
    "parse",
    "parse_held",
    "seal",
]

TOKEN_BYTES = 16  # the pairing token: 128 random bits
NONCE_BYTES = 16
MAC_BYTES = 16
MAC_HEX = 2 * MAC_BYTES
UNAUTHENTICATED = "-"
MAX_MESSAGE = 1024  # characters: every message the page sends is far shorter


class WireError(ValueError):
    """A message that is not one: bad framing, bad JSON, a field out of range."""


def new_token() -> bytes:
    return secrets.token_bytes(TOKEN_BYTES)


def new_nonce() -> bytes:
    return secrets.token_bytes(NONCE_BYTES)


def encode_token(token: bytes) -> str:
    """The token as it goes into the URL's fragment: base64url without padding."""
    return base64.urlsafe_b64encode(token).rstrip(b"=").decode("ascii")


def decode_token(text: str) -> bytes:
    try:
        raw = base64.urlsafe_b64decode(text + "=" * (-len(text) % 4))
    except (binascii.Error, ValueError):
        raise WireError("the pairing token is not base64url") from None
    if len(raw) != TOKEN_BYTES:
        raise WireError(f"the pairing token must be {TOKEN_BYTES} bytes, got {len(raw)}")
    return raw


def mac(token: bytes, nonce: bytes, body: bytes) -> str:
    """Keyed BLAKE2s-128 of the receiver's nonce and the message's JSON text, as hex."""
    return hashlib.blake2s(nonce + body, key=token, digest_size=MAC_BYTES).hexdigest()


def seal(msg: dict[str, Any], token: bytes | None = None, nonce: bytes | None = None) -> str:
    """``msg`` as one text frame: authenticated for ``nonce`` (the receiver's) when a token
    and a nonce are given, else with ``-`` in place of the MAC."""
    body = json.dumps(msg, separators=(",", ":"), allow_nan=False)
    if token is None or nonce is None:
        return f"{UNAUTHENTICATED} {body}"
    return f"{mac(token, nonce, body.encode())} {body}"


@dataclass(frozen=True, slots=True)
class Message:
    kind: str  # the ``t`` field
    fields: dict[str, Any]
    authentic: bool  # its MAC verified with the token and the receiver's nonce


def parse(text: str, token: bytes | None, nonce: bytes | None) -> Message:
    """One text frame from the other side. A MAC that does not verify (or no token to check
    it with) gives an unauthenticated message, never an error: what it may do is the
    receiver's call. Malformed frames raise :class:`WireError`."""
    if len(text) > MAX_MESSAGE:
        raise WireError(f"message longer than {MAX_MESSAGE} characters")
    tag, sep, body = text.partition(" ")
    if not sep or not (tag == UNAUTHENTICATED or len(tag) == MAC_HEX):
        raise WireError("not 'MAC JSON'")
    try:
        fields = json.loads(body)
    except ValueError:
        raise WireError("not JSON") from None
    if not isinstance(fields, dict) or not isinstance(fields.get("t"), str):
        raise WireError("not an object with a type 't'")
    authentic = (tag != UNAUTHENTICATED and token is not None and nonce is not None
                 and hmac.compare_digest(tag, mac(token, nonce, body.encode())))
    return Message(fields["t"], fields, authentic)


def _number(fields: dict[str, Any], name: str, lo: float, hi: float) -> float:
    value = fields.get(name)
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise WireError(f"{name}: not a number")
    value = float(value)
    if not math.isfinite(value) or not lo <= value <= hi:
        raise WireError(f"{name}: {value!r} outside {lo:g}..{hi:g}")
    return value


@dataclass(frozen=True, slots=True)
class HeldFrame:
    """"A finger is on the drive area": sent by the page every control period."""

    at_ms: float  # the page's clock (performance.now()) when it was sent
    steer: float  # -1 left .. 1 right
    gas: float  # -1 full brake .. 1 full gas


def parse_held(fields: dict[str, Any]) -> HeldFrame:
    return HeldFrame(_number(fields, "at", 0.0, 1e12), _number(fields, "steer", -1.0, 1.0),
                     _number(fields, "gas", -1.0, 1.0))


def counter(fields: dict[str, Any]) -> int:
    """The ``n`` of an authenticated message (a whole number >= 1)."""
    n = fields.get("n")
    if isinstance(n, bool) or not isinstance(n, int) or n < 1 or n > 2**53:
        raise WireError("n: not a counter")
    return n
