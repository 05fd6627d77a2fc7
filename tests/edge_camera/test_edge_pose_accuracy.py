"""Unit tests of ``edge_camera.pose_accuracy``: declared standard deviations -> the header's 6x6 covariance."""

from __future__ import annotations

import math

import numpy as np
import pytest

from edge_camera.pose_accuracy import declared_covariance, pose_covariance


class TestPoseCovariance:
    def test_exact_diagonal(self):
        C = pose_covariance(0.5, 90.0)
        assert C.shape == (6, 6) and C.dtype == np.float64
        assert np.array_equal(C, np.diag([0.25, 0.25, 0.25] + [math.radians(90.0) ** 2] * 3))
        assert C[3, 3] == pytest.approx(math.pi**2 / 4, rel=1e-15)
        assert np.count_nonzero(C - np.diag(np.diag(C))) == 0

    def test_round_trip_to_sigmas(self):
        C = pose_covariance(0.03, 2.0)
        assert np.sqrt(np.diag(C)[:3]) == pytest.approx([0.03] * 3)
        assert np.degrees(np.sqrt(np.diag(C)[3:])) == pytest.approx([2.0] * 3)

    @pytest.mark.parametrize(("st", "sr"), [(0.0, 1.0), (0.1, 0.0), (-0.1, 1.0), (math.nan, 1.0), (0.1, math.inf)])
    def test_zero_negative_or_non_finite_is_refused(self, st, sr):
        with pytest.raises(ValueError, match="must be finite and > 0"):
            pose_covariance(st, sr)

    def test_both_or_neither(self):
        assert declared_covariance(None, None, "x") is None
        assert np.array_equal(declared_covariance(0.1, 1.0, "x"), pose_covariance(0.1, 1.0))
        with pytest.raises(ValueError, match="file.json: .*both or neither"):
            declared_covariance(0.1, None, "file.json")
