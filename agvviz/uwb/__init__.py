"""UWB localisation (paper 003 §2.1): two-way ranging, the trilateral centroid, Gauss–Newton
multilateration with an NLOS/outlier gate, GDOP, and a tracker that turns a stream of ranges
into fixes. Numpy only — no I/O, no rerun.
"""

from agvviz.uwb.localize import (
    UwbFix,
    UwbLocalizationError,
    gdop,
    least_squares_fix,
    trilateral_centroid,
)
from agvviz.uwb.ranging import SPEED_OF_LIGHT_MPS, range_from_timestamps_m, time_of_flight_s
from agvviz.uwb.tracker import RangeRecord, UwbTracker

__all__ = [
    "SPEED_OF_LIGHT_MPS",
    "RangeRecord",
    "UwbFix",
    "UwbLocalizationError",
    "UwbTracker",
    "gdop",
    "least_squares_fix",
    "range_from_timestamps_m",
    "time_of_flight_s",
    "trilateral_centroid",
]
