"""Information gain over sampled completions: entropies and hand-computed cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from planner.gain import factored_gain, joint_gain, mutual_information, row_entropy_bits


def h2(p: float) -> float:
    return -(p * math.log2(p) + (1 - p) * math.log2(1 - p))


class TestRowEntropy:
    def test_values(self) -> None:
        v = np.array([[1, 1, 1, 1], [1, 1, 2, 2], [1, 2, 3, 4], [5, 5, 5, 7]], dtype=float)
        np.testing.assert_allclose(row_entropy_bits(v), [0.0, 1.0, 2.0, h2(0.25)], atol=1e-12)

    def test_empty(self) -> None:
        assert row_entropy_bits(np.zeros((3, 0))).tolist() == [0.0, 0.0, 0.0]

    def test_bad_shape(self) -> None:
        with pytest.raises(ValueError):
            row_entropy_bits(np.zeros(4))


class TestMutualInformation:
    def test_disagreeing_completions_one_bit(self) -> None:
        # Two completions, one jitter each: the view shows different things under each -> 1 bit.
        assert mutual_information(np.array([[3.0, 0.0]]), 2, 1)[0] == pytest.approx(1.0)

    def test_agreeing_completions_zero(self) -> None:
        assert mutual_information(np.array([[3.0, 3.0]]), 2, 1)[0] == pytest.approx(0.0)

    def test_jitter_only_uncertainty_is_not_information(self) -> None:
        # Each completion's outcome varies only with jitter, identically: H(Y) = H(Y|G) -> 0.
        assert mutual_information(np.array([[1.0, 0.0, 1.0, 0.0]]), 2, 2)[0] == pytest.approx(0.0)

    def test_wrong_sample_count(self) -> None:
        with pytest.raises(ValueError):
            mutual_information(np.zeros((1, 5)), 2, 2)


class TestJointGain:
    def test_hand_computed_two_completions_with_jitter(self) -> None:
        # Hypotheses (label 0 = "cup"): completion 0 has a cup in both jitter draws (samples 0, 1);
        # completion 1 has nothing. Candidate 0 sees the cup only in jitter draw 0; candidate 1 looks
        # at mapped space and sees no hypothesis.
        label_idx = np.array([0, 0])
        sample_idx = np.array([0, 1])
        V = np.array([[True, False], [False, False]])
        g = joint_gain(V, label_idx, sample_idx, n_labels=1, n_completions=2, n_jitter=2)
        # Y over the 4 samples: {cup}, {}, {}, {} -> H = h2(1/4); within completion 0: {cup}, {} -> 1 bit,
        # completion 1: 0 bits -> H(Y|G) = 0.5.
        assert g[0] == pytest.approx(h2(0.25) - 0.5, abs=1e-12)
        assert g[1] == 0.0

    def test_multiset_distinguishes_labels_and_counts(self) -> None:
        # 4 completions, one jitter: {chair}, {table}, {chair, chair}, {} -> four outcomes, 2 bits.
        label_idx = np.array([0, 1, 0, 0])
        sample_idx = np.array([0, 1, 2, 2])
        V = np.ones((1, 4), bool)
        assert joint_gain(V, label_idx, sample_idx, 2, 4, 1)[0] == pytest.approx(2.0)

    def test_saturates_at_log2_k(self) -> None:
        rng = np.random.default_rng(0)
        K = 8
        label_idx = rng.integers(0, 20, size=200)
        sample_idx = rng.integers(0, K, size=200)
        g = joint_gain(np.ones((1, 200), bool), label_idx, sample_idx, 20, K, 1)
        assert g[0] <= math.log2(K) + 1e-9

    def test_no_hypotheses(self) -> None:
        assert joint_gain(np.zeros((3, 0), bool), np.zeros(0, int), np.zeros(0, int), 0, 2, 1).tolist() == [
            0,
            0,
            0,
        ]


class TestFactoredGain:
    def test_equals_joint_for_one_label(self) -> None:
        label_idx = np.array([0, 0, 0])
        sample_idx = np.array([0, 2, 3])
        V = np.array([[True, True, False], [True, True, True]])
        j = joint_gain(V, label_idx, sample_idx, 1, 2, 2)
        f = factored_gain(V, label_idx, sample_idx, 1, 2, 2)
        np.testing.assert_allclose(f, j, atol=1e-12)

    def test_sums_over_labels(self) -> None:
        # Two independent uncertain labels seen by the view: 1 bit each.
        label_idx = np.array([0, 1])
        sample_idx = np.array([0, 2])
        V = np.ones((1, 2), bool)
        assert factored_gain(V, label_idx, sample_idx, 2, 4, 1)[0] == pytest.approx(2 * h2(0.25))
