"""Pieces of one object that a person in front cut in two are joined (mapper.perception.occluded)."""

from __future__ import annotations

import numpy as np

from mapper.perception.base import Detection, label_descriptor
from mapper.perception.occluded import join_split_by_people


def det(label: str, cols: tuple[int, int], rows: tuple[int, int] = (10, 30), shape: tuple[int, int] = (40, 60),
        conf: float = 0.8) -> Detection:
    m = np.zeros(shape, bool)
    m[rows[0]:rows[1], cols[0]:cols[1]] = True
    return Detection(m, label, conf, label_descriptor(label))


PERSON = det("person", (25, 35), rows=(0, 40))


def test_a_sofa_cut_in_two_by_a_person_is_one_detection_again() -> None:
    left, right = det("sofa", (5, 25), conf=0.7), det("sofa", (35, 55), conf=0.9)
    lamp = det("lamp", (56, 59))
    out, n = join_split_by_people([left, lamp, right], [PERSON], 0.8)
    assert n == 1 and [d.label for d in out] == ["sofa", "lamp"]
    assert out[0].mask.sum() == left.mask.sum() + right.mask.sum() and out[0].confidence == 0.9
    assert abs(float(np.linalg.norm(out[0].descriptor)) - 1.0) < 1e-5


def test_pieces_apart_from_the_person_or_unlike_stay_apart() -> None:
    far = det("sofa", (45, 55))  # 10 px from the person: two sofas, not one cut in two
    assert join_split_by_people([det("sofa", (5, 25)), far], [PERSON], 0.8)[1] == 0
    assert join_split_by_people([det("sofa", (5, 25)), det("armchair", (35, 55))], [PERSON], 0.8)[1] == 0
    assert join_split_by_people([det("sofa", (5, 25)), det("sofa", (35, 55))], [], 0.8)[1] == 0  # no person
    # two people: each piece touches another one
    p2 = det("person", (0, 4), rows=(0, 40))
    assert join_split_by_people([det("sofa", (5, 20)), det("sofa", (36, 55))], [p2, det("person", (37, 40))],
                                0.8)[1] == 0


def test_masks_at_another_resolution_are_compared_at_the_pieces() -> None:
    small = det("person", (12, 18), rows=(0, 20), shape=(20, 30))  # the person at half the resolution
    out, n = join_split_by_people([det("sofa", (5, 25)), det("sofa", (35, 55))], [small], 0.8)
    assert n == 1 and out[0].mask.shape == (40, 60)
