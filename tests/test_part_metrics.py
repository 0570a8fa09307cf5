"""Part segmentation metrics (``tasks/part_metrics.py``) on hand-made shapes whose scores are worked
out by hand below; and plausible wrong implementations (IoU over all 50 parts, an absent part
counted as 0, class mIoU as the mean over shapes, an unrestricted argmax) give other numbers on
the same shapes, so these cases tell them apart."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from mvtn_exp.tasks.part_metrics import part_miou, restrict, shape_iou

# A toy benchmark: Airplane's 4 parts and Bag's 2 as in ShapeNet Parts, and a one-part category.
PARTS_OF = {0: [0, 1, 2, 3], 1: [4, 5], 2: [6]}
CLASSES = ["Airplane", "Bag", "Solo"]

# Airplane, part 3 absent from both prediction and truth:
#   part 0: pred {0, 5}, true {0, 1}: 1 / 3;  part 1: pred {1, 2, 3}, true {2, 3}: 2 / 3
#   part 2: pred {4}, true {4, 5}: 1 / 2;     part 3: absent from both: 1
#   shape IoU = (1/3 + 2/3 + 1/2 + 1) / 4 = 5/8
PLANE_TRUE, PLANE_PRED = [0, 0, 1, 1, 2, 2], [0, 1, 1, 1, 2, 0]
# Airplane, every point right, parts 2 and 3 absent from both: (1 + 1 + 1 + 1) / 4 = 1
PLANE2_TRUE, PLANE2_PRED = [0, 1], [0, 1]
# Bag: part 4: pred {0, 1, 2}, true {0, 1}: 2/3; part 5: pred {3}, true {2, 3}: 1/2; (2/3 + 1/2) / 2 = 7/12
BAG_TRUE, BAG_PRED = [4, 4, 5, 5], [4, 4, 4, 5]
# Solo (one part): all right: 1
SOLO_TRUE, SOLO_PRED = [6, 6, 6], [6, 6, 6]

SHAPES = [(PLANE_PRED, PLANE_TRUE, 0), (PLANE2_PRED, PLANE2_TRUE, 0), (BAG_PRED, BAG_TRUE, 1),
          (SOLO_PRED, SOLO_TRUE, 2)]
# instance mIoU = (5/8 + 1 + 7/12 + 1) / 4 = (77/24) / 4 = 77/96
# class mIoU = (Airplane (5/8 + 1)/2 = 13/16, Bag 7/12, Solo 1) / 3 = (115/48) / 3 = 115/144
INSTANCE, CLASS = 77 / 96, 115 / 144


def _miou(shapes=SHAPES):
    preds, trues, cats = zip(*shapes)
    return part_miou(list(preds), list(trues), list(cats), PARTS_OF, CLASSES)


# ------------------------------------------------------------------------------ the right numbers
def test_shape_iou_counts_a_part_absent_from_both_as_one():
    assert shape_iou(PLANE_PRED, PLANE_TRUE, PARTS_OF[0]) == pytest.approx(5 / 8)
    assert shape_iou(PLANE2_PRED, PLANE2_TRUE, PARTS_OF[0]) == 1.0
    assert shape_iou(BAG_PRED, BAG_TRUE, PARTS_OF[1]) == pytest.approx(7 / 12)


def test_shape_iou_of_a_one_part_category():
    assert shape_iou(SOLO_PRED, SOLO_TRUE, PARTS_OF[2]) == 1.0
    # a predicted id outside the category matches no part: part 6: pred {0, 1}, true {0, 1, 2}: 2/3
    assert shape_iou([6, 6, 0], SOLO_TRUE, PARTS_OF[2]) == pytest.approx(2 / 3)
    # Bag, both points predicted 4 but labelled 5: part 4: pred {0, 1}, true {}: 0/2; part 5: 0/2 -> 0
    assert shape_iou([4, 4], [5, 5], PARTS_OF[1]) == 0.0


def test_part_miou_instance_class_and_per_category():
    m = _miou()
    assert m["instance_miou"] == pytest.approx(INSTANCE)
    assert m["class_miou"] == pytest.approx(CLASS)
    assert m["per_category"] == {"Airplane": {"miou": pytest.approx(13 / 16), "shapes": 2},
                                 "Bag": {"miou": pytest.approx(7 / 12), "shapes": 1},
                                 "Solo": {"miou": 1.0, "shapes": 1}}


def test_class_miou_is_over_the_categories_present_only():
    m = _miou(SHAPES[:3])  # no Solo shape: (13/16 + 7/12) / 2 = 67/96
    assert m["class_miou"] == pytest.approx(67 / 96) and set(m["per_category"]) == {"Airplane", "Bag"}


def test_tensors_and_stacked_arrays_give_the_same_numbers():
    preds = torch.tensor([PLANE_PRED, [4, 4, 4, 5, 4, 4]])
    trues = torch.tensor([PLANE_TRUE, [4, 4, 5, 5, 4, 4]])
    # Bag: part 4: pred {0,1,2,4,5}, true {0,1,4,5}: 4/5; part 5: pred {3}, true {2,3}: 1/2; (4/5 + 1/2)/2 = 13/20
    m = part_miou(preds, trues, torch.tensor([0, 1]), PARTS_OF, CLASSES)
    assert m["instance_miou"] == pytest.approx((5 / 8 + 13 / 20) / 2)
    assert m == part_miou(preds.numpy(), trues.numpy(), [0, 1], PARTS_OF, CLASSES)


def test_restrict_picks_among_the_categorys_parts_only():
    logits = torch.zeros(3, 50)
    logits[0, 10], logits[0, 2] = 9.0, 1.0  # Car's part 10 is largest; among Airplane's 0..3: 2
    logits[1, 49], logits[1, 3] = 5.0, 4.0  # Table's 49 largest; among 0..3: 3
    logits[2, 1] = 0.5  # already an Airplane part
    assert restrict(logits, 0, PARTS_OF).tolist() == [2, 3, 1]
    assert restrict(logits.numpy(), 0, PARTS_OF).tolist() == [2, 3, 1]
    assert restrict(logits, 1, PARTS_OF).tolist() == [4, 4, 4]  # ties (all 0): the lowest part id
    batch = restrict(torch.stack([logits, logits]), torch.tensor([0, 1]), PARTS_OF)
    assert batch.dtype == torch.long and batch.tolist() == [[2, 3, 1], [4, 4, 4]]
    assert restrict(torch.stack([logits, logits]), 0, PARTS_OF).tolist() == [[2, 3, 1]] * 2


def test_bad_arguments_are_one_line():
    with pytest.raises(ValueError, match="3 predicted labels for 2 true labels"):
        shape_iou([0, 0, 0], [0, 0], [0, 1])
    with pytest.raises(ValueError, match="category 7 has no parts"):
        restrict(torch.zeros(2, 50), 7, PARTS_OF)
    with pytest.raises(ValueError, match="2 categories for a batch of 3"):
        restrict(torch.zeros(3, 2, 50), [0, 1], PARTS_OF)
    with pytest.raises(ValueError, match="1 predictions and 1 truths for 2 categories"):
        part_miou([[0]], [[0]], [0, 0], PARTS_OF, CLASSES)


# ------------------------------------------------------------------------------ wrong implementations
def _iou_over_all_50_parts(pred, true, parts):
    """WRONG: the mean over every part of the benchmark (absent from both: 1), not the category's."""
    pred, true = np.asarray(pred), np.asarray(true)
    ious = []
    for p in range(50):
        union = np.count_nonzero((pred == p) | (true == p))
        ious.append(1.0 if union == 0 else np.count_nonzero((pred == p) & (true == p)) / union)
    return float(np.mean(ious))


def _iou_absent_as_zero(pred, true, parts):
    """WRONG: a part absent from both prediction and truth counts as 0."""
    pred, true = np.asarray(pred), np.asarray(true)
    ious = []
    for p in parts:
        union = np.count_nonzero((pred == p) | (true == p))
        ious.append(0.0 if union == 0 else np.count_nonzero((pred == p) & (true == p)) / union)
    return float(np.mean(ious))


@pytest.mark.parametrize("wrong", [_iou_over_all_50_parts, _iou_absent_as_zero])
def test_wrong_shape_ious_give_other_numbers(wrong):
    # over all 50 parts: (1/3 + 2/3 + 1/2 + 47 * 1) / 50 = 0.97; absent as 0: (1/3 + 2/3 + 1/2 + 0) / 4 = 3/8
    expected = {_iou_over_all_50_parts: 0.97, _iou_absent_as_zero: 3 / 8}[wrong]
    assert wrong(PLANE_PRED, PLANE_TRUE, PARTS_OF[0]) == pytest.approx(expected)
    assert wrong(PLANE_PRED, PLANE_TRUE, PARTS_OF[0]) != pytest.approx(shape_iou(PLANE_PRED, PLANE_TRUE, PARTS_OF[0]))
    wrong_instance = np.mean([wrong(p, t, PARTS_OF[c]) for p, t, c in SHAPES])
    assert wrong_instance != pytest.approx(_miou()["instance_miou"])


def test_class_miou_as_the_mean_over_shapes_is_another_number():
    wrong = np.mean([shape_iou(p, t, PARTS_OF[c]) for p, t, c in SHAPES])  # WRONG: weighs categories by size
    assert wrong == pytest.approx(INSTANCE) and wrong != pytest.approx(_miou()["class_miou"])


def test_an_unrestricted_argmax_is_another_number():
    logits = torch.zeros(4, 50)
    logits[:, 0] = 1.0
    logits[0, 10] = 9.0  # WRONG: argmax over all 50 predicts Car's 10 for point 0
    true = [0, 0, 1, 1]
    # restricted: pred [0, 0, 0, 0]: part 0: 2/4, part 1: 0/2, parts 2, 3 absent: 1, 1 -> (1/2 + 0 + 2) / 4 = 5/8
    # unrestricted: pred [10, 0, 0, 0]: part 0: 1/4 -> (1/4 + 0 + 2) / 4 = 9/16
    assert shape_iou(restrict(logits, 0, PARTS_OF), true, PARTS_OF[0]) == pytest.approx(5 / 8)
    assert shape_iou(logits.argmax(-1), true, PARTS_OF[0]) == pytest.approx(9 / 16)
