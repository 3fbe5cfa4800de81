"""The Wi-Fi link model (estop.model.wifi): loss and burst statistics, delay and order,
seeds and edge cases.
"""

from __future__ import annotations

import statistics

import pytest

from estop.model.wifi import WIFI, LinkConfig, LinkModel

pytestmark = pytest.mark.timeout(60)



# ---------------------------------------------------------------------------- link model

def burst_lengths(lost: list[bool]) -> list[int]:
    runs, n = [], 0
    for x in lost:
        if x:
            n += 1
        elif n:
            runs.append(n)
            n = 0
    return runs


@pytest.mark.parametrize(("loss", "burst"), [(0.09, 1.0), (0.09, 2.0), (0.3, 3.0), (0.5, 1.0)])
def test_link_model_loss_statistics(loss: float, burst: float) -> None:
    model = LinkModel(LinkConfig(loss=loss, burst=burst), seed=12345)
    lost = [model.lose_next() for _ in range(40_000)]
    frac = sum(lost) / len(lost)
    assert abs(frac - loss) < 0.15 * loss
    assert model.stats.loss_fraction == frac and model.stats.sent == 40_000
    assert abs(statistics.mean(burst_lengths(lost)) - burst) < 0.1 * burst
    assert model.stats.longest_burst == max(burst_lengths(lost))


def test_link_model_wifi_delay_and_order() -> None:
    model = LinkModel(WIFI, seed=3)
    times = [model.transmit(i * 0.02) for i in range(5000)]
    got = [(i * 0.02, t) for i, t in enumerate(times) if t is not None]
    assert all(WIFI.delay <= t - s <= WIFI.delay + WIFI.jitter + 0.02 for s, t in got)
    arrivals = [t for _, t in got]
    assert arrivals == sorted(arrivals)  # never reordered
    assert abs(1 - len(got) / 5000 - 0.09) < 0.02


def test_link_model_seeded_and_edge_cases() -> None:
    a = LinkModel(WIFI, seed=99)
    b = LinkModel(WIFI, seed=99)
    assert [a.transmit(i / 50) for i in range(500)] == [b.transmit(i / 50) for i in range(500)]
    ideal = LinkModel()
    assert all(ideal.transmit(float(i)) == float(i) for i in range(100))
    dead = LinkModel(LinkConfig(loss=1.0))
    assert all(dead.transmit(0.0) is None for _ in range(100)) and dead.stats.lost == 100
    for cfg, msg in [(LinkConfig(loss=1.5), "loss"), (LinkConfig(burst=0.5), "burst"),
                     (LinkConfig(delay=-1), "delay"), (LinkConfig(loss=0.6), "impossible")]:
        with pytest.raises(ValueError, match=msg):
            LinkModel(cfg)
