"""The accuracy measures of the study (datagen/study): known answers."""

from __future__ import annotations

import numpy as np
import pytest

from datagen.study.metrics import final_distance, max_distance, rms_distance
from datagen.study.sweep import CHAOS_MM, pareto, predictable_frames


@pytest.fixture
def trajectory():
    rng = np.random.default_rng(3)
    return rng.normal(size=(31, 500, 3))


def test_reference_against_itself_is_zero(trajectory):
    assert rms_distance(trajectory, trajectory) == 0.0
    assert max_distance(trajectory, trajectory) == 0.0
    assert final_distance(trajectory, trajectory) == 0.0


def test_rigid_shift_of_one_millimetre_reads_one_millimetre(trajectory):
    direction = np.array([2.0, -1.0, 2.0]) / 3.0  # unit length
    shifted = trajectory + 0.001 * direction
    assert rms_distance(shifted, trajectory) == pytest.approx(0.001, rel=1e-9)
    assert max_distance(shifted, trajectory) == pytest.approx(0.001, rel=1e-9)
    assert final_distance(shifted, trajectory) == pytest.approx(0.001, rel=1e-9)


def test_horizon_limits_the_frames_compared(trajectory):
    late = trajectory.copy()
    late[10:] += 0.5  # differs only from frame 10 on
    assert rms_distance(late, trajectory, 10) == 0.0
    assert rms_distance(late, trajectory) > 0.0


def test_predictable_frames_is_where_the_twin_leaves(trajectory):
    twin = trajectory.copy()
    twin[7:] += 2 * CHAOS_MM / 1000 / np.sqrt(3)  # 2 mm away from frame 7 on
    assert predictable_frames(trajectory, twin) == 7
    assert predictable_frames(trajectory, trajectory) == len(trajectory)


def test_pareto_front():
    points = [(1.0, 10.0), (2.0, 5.0), (3.0, 6.0), (4.0, 1.0), (0.5, 20.0)]
    assert sorted(pareto(points)) == [0, 1, 3, 4]
