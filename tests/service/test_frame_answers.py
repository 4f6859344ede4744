"""service.frame_answers: the odometry a stereo frame is answered with on its intake thread."""

from __future__ import annotations

import numpy as np

from macroloc.service.frame_answers import OdometryBuffer


def _T(x_m: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x_m
    return T


def test_a_frame_takes_the_odometry_nearest_its_stamp_or_the_newest_where_its_own_is_on_its_way() -> None:
    buffer = OdometryBuffer(size=4, match_ns=60_000_000)
    assert buffer.at(0) is None
    for k in range(6):
        buffer.add(k * 33_000_000, _T(float(k)))
    assert 3 * 33_000_000 in buffer and 3 * 33_000_000 + 1 not in buffer
    assert buffer.at(3 * 33_000_000)[0, 3] == 3.0  # its own stamp
    assert buffer.at(3 * 33_000_000 + 10_000_000)[0, 3] == 3.0  # the nearest
    assert buffer.at(9 * 33_000_000, newest_if_later=True)[0, 3] == 5.0  # newer than all: the newest ...
    assert buffer.at(9 * 33_000_000) is None  # ... or none: the worker's sightings wait for theirs
    assert buffer.at(0) is None  # older than the four kept (66 ms and on), beyond 60 ms of any
    buffer.clear()
    assert buffer.at(5 * 33_000_000) is None
