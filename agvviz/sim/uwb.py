"""Simulated two-way ranging (paper 003 eq 1) with device clocks. Numpy only; randomness
comes from the caller's ``rng``.

One exchange at true time ``t``: the tag sends a poll (its clock reads ``t1``), the anchor
receives it after the time of flight plus any NLOS excess delay (``t2``, anchor clock), replies
``reply_delay_s`` later by its own clock (``t3``), and the tag receives the reply (``t4``, tag
clock). Each device clock is ``offset_s + (1 + drift_ppm·1e-6)·t``; every timestamp gets
Gaussian noise and is quantised to the radio's tick (DW1000: 1/(128 · 499.2 MHz) ≈ 15.65 ps).
The reported range is eq 1–2 applied to the four timestamps, so it carries the noise, the
clock-drift bias ``c·(ε_tag − ε_anchor)·D/2`` and the NLOS excess.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agvviz.uwb.ranging import SPEED_OF_LIGHT_MPS, range_from_timestamps_m

#: Timestamp resolution of a DW1000-class radio (s).
UWB_TICK_S = 1.0 / (128 * 499.2e6)


@dataclass(frozen=True)
class DeviceClock:
    """A free-running device clock: reads ``offset_s + (1 + drift_ppm·1e-6)·t`` at true time t."""

    offset_s: float
    drift_ppm: float

    def read_ns(self, true_time_s: float) -> float:
        return (self.offset_s + (1.0 + self.drift_ppm * 1e-6) * true_time_s) * 1e9


@dataclass(frozen=True)
class TwrExchange:
    """The four timestamps (device-clock ns, see :mod:`agvviz.uwb.ranging`) and the range."""

    t1_ns: float
    t2_ns: float
    t3_ns: float
    t4_ns: float
    range_m: float


def _quantise_ns(t_ns: float) -> float:
    tick_ns = UWB_TICK_S * 1e9
    return round(t_ns / tick_ns) * tick_ns


def simulate_twr(
    true_range_m: float,
    poll_time_s: float,
    tag_clock: DeviceClock,
    anchor_clock: DeviceClock,
    rng: np.random.Generator,
    reply_delay_s: float = 150e-6,
    timestamp_noise_s: float = 0.1e-9,
    nlos_excess_m: float = 0.0,
) -> TwrExchange:
    """One single-sided TWR exchange (module docstring). Draws 4 normals from ``rng``.

    ``poll_time_s`` is true time relative to the clocks' common zero (keep it small — tens of
    seconds — so float64 nanoseconds keep sub-picosecond resolution).
    """
    if true_range_m < 0 or nlos_excess_m < 0 or reply_delay_s <= 0:
        raise ValueError(
            f"need true_range_m ≥ 0, nlos_excess_m ≥ 0, reply_delay_s > 0; got "
            f"{true_range_m}, {nlos_excess_m}, {reply_delay_s}"
        )
    flight_s = (true_range_m + nlos_excess_m) / SPEED_OF_LIGHT_MPS
    arrive_s = poll_time_s + flight_s
    # The anchor waits reply_delay_s by its own clock.
    reply_s = arrive_s + reply_delay_s / (1.0 + anchor_clock.drift_ppm * 1e-6)
    back_s = reply_s + flight_s
    noise_ns = rng.standard_normal(4) * timestamp_noise_s * 1e9
    t1 = _quantise_ns(tag_clock.read_ns(poll_time_s) + noise_ns[0])
    t2 = _quantise_ns(anchor_clock.read_ns(arrive_s) + noise_ns[1])
    t3 = _quantise_ns(anchor_clock.read_ns(reply_s) + noise_ns[2])
    t4 = _quantise_ns(tag_clock.read_ns(back_s) + noise_ns[3])
    return TwrExchange(t1, t2, t3, t4, float(range_from_timestamps_m(t1, t2, t3, t4)))
