"""A small model of the remote's Wi-Fi link: bursty loss, delay and jitter.

Loss follows a two-state Gilbert model: in the *good* state packets get through, in the *bad*
state they are lost. ``loss`` is the long-run fraction lost and ``burst`` the mean number of
packets lost in a row (1.0: losses are isolated). Each delivered packet is delayed by
``delay`` plus a uniform random ``0..jitter``; delivery order is kept (a packet never
overtakes the one sent before it), as on a Wi-Fi link with link-layer retries.

The original system saw about 9 % loss and 100-150 ms delay: :data:`WIFI`.
All randomness comes from one seeded :class:`random.Random`, so runs can be repeated.
"""

from __future__ import annotations

import random
from dataclasses import dataclass

__all__ = ["IDEAL", "WIFI", "LinkConfig", "LinkModel", "LinkStats"]


@dataclass(frozen=True, slots=True)
class LinkConfig:
    loss: float = 0.0  # long-run fraction of packets lost, 0.0 .. 1.0
    burst: float = 1.0  # mean length of a run of lost packets, >= 1.0
    delay: float = 0.0  # one-way base delay, seconds
    jitter: float = 0.0  # extra delay, uniform 0 .. jitter seconds

    def validate(self) -> None:
        """Raise ValueError (one-line message) unless the parameters make a link."""
        if not 0.0 <= self.loss <= 1.0:
            raise ValueError(f"loss must be 0..100 %, got {self.loss * 100:g} %")
        if not self.burst >= 1.0:
            raise ValueError(f"burst must be >= 1 packet, got {self.burst:g}")
        if not self.delay >= 0.0 or not self.jitter >= 0.0:
            raise ValueError("delay and jitter must be >= 0")
        if 0.0 < self.loss < 1.0 and self._enter_bad() > 1.0:
            most = self.burst / (self.burst + 1.0) * 100
            raise ValueError(f"loss {self.loss * 100:g} % is impossible with mean burst "
                             f"{self.burst:g} (at most {most:.4g} %; raise --burst)")

    def _leave_bad(self) -> float:
        return 1.0 / self.burst

    def _enter_bad(self) -> float:
        # stationary loss = enter / (enter + leave)  =>  enter = loss * leave / (1 - loss)
        return self.loss * self._leave_bad() / (1.0 - self.loss)

    @property
    def lossless(self) -> bool:
        return self.loss == 0.0 and self.delay == 0.0 and self.jitter == 0.0


IDEAL = LinkConfig()
WIFI = LinkConfig(loss=0.09, burst=2.0, delay=0.100, jitter=0.050)


@dataclass(slots=True)
class LinkStats:
    sent: int = 0
    lost: int = 0
    longest_burst: int = 0

    @property
    def delivered(self) -> int:
        return self.sent - self.lost

    @property
    def loss_fraction(self) -> float:
        return self.lost / self.sent if self.sent else 0.0


class LinkModel:
    """Decide, packet by packet, whether and when a packet arrives. Not thread-safe."""

    def __init__(self, config: LinkConfig = IDEAL, seed: int | random.Random | None = None):
        config.validate()
        self.config = config
        self._rng = seed if isinstance(seed, random.Random) else random.Random(seed)
        self._bad = False
        self._run = 0
        self._last_delivery = float("-inf")
        self.stats = LinkStats()

    def lose_next(self) -> bool:
        """Advance the loss chain by one packet; True if that packet is lost."""
        cfg = self.config
        if cfg.loss >= 1.0:
            lost = True
        elif cfg.loss <= 0.0:
            lost = False
        else:
            u = self._rng.random()
            self._bad = u >= cfg._leave_bad() if self._bad else u < cfg._enter_bad()
            lost = self._bad
        self.stats.sent += 1
        if lost:
            self.stats.lost += 1
            self._run += 1
            self.stats.longest_burst = max(self.stats.longest_burst, self._run)
        else:
            self._run = 0
        return lost

    def sample_delay(self) -> float:
        """One-way delay for one packet: ``delay + uniform(0, jitter)`` seconds."""
        cfg = self.config
        return cfg.delay + (self._rng.uniform(0.0, cfg.jitter) if cfg.jitter > 0.0 else 0.0)

    def transmit(self, t_send: float) -> float | None:
        """Delivery time of a packet sent at ``t_send`` (same clock), or None if it is lost."""
        if self.lose_next():
            return None
        t = max(t_send + self.sample_delay(), self._last_delivery)
        self._last_delivery = t
        return t
