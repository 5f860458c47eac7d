"""Two-way ranging arithmetic (paper 003 eqs 1–2). Numpy only.

Timestamps follow ``agvviz.UwbRange``: ``t1`` the tag sends the poll (T_t1), ``t2`` the anchor
receives it (T_a1), ``t3`` the anchor sends the reply (T_a2), ``t4`` the tag receives the
reply (T_t2). ``t1``/``t4`` are read on the tag's clock, ``t2``/``t3`` on the anchor's, so
the clocks' offsets cancel; what is left of their drift is ``(ε_tag − ε_anchor)·D/2`` for a
reply delay D (single-sided TWR's known bias).
"""

from __future__ import annotations

import numpy as np

#: Speed of light in vacuum (m/s), paper 003 eq 2.
SPEED_OF_LIGHT_MPS = 299_792_458.0


def time_of_flight_s(t1_ns, t2_ns, t3_ns, t4_ns):
    """Time of flight (s) of eq 1: ``((t4 − t1) − (t3 − t2)) / 2``.

    Paper 003 writes it as ``((T_t1 − T_t2) − (T_a1 − T_a2)) / 2``: the same difference of
    round-trip time and anchor reply time, with the signs of both swapped. Works on scalars
    or arrays (device-clock nanoseconds).
    """
    round_trip_ns = np.subtract(t4_ns, t1_ns)
    reply_ns = np.subtract(t3_ns, t2_ns)
    return (round_trip_ns - reply_ns) / 2.0 * 1e-9


def range_from_timestamps_m(t1_ns, t2_ns, t3_ns, t4_ns):
    """Tag–anchor distance (m) of eq 2: ``c · T_tof``."""
    return SPEED_OF_LIGHT_MPS * time_of_flight_s(t1_ns, t2_ns, t3_ns, t4_ns)
