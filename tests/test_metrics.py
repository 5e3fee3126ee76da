import numpy as np
import pytest

from racklay import layout as L
from racklay.metrics import LayoutMetrics, average_precision_from_hist, confusion, format_tables, paper_scores


def test_paper_scores_hand_computed():
    gt = np.zeros((1, 4, 4), np.uint8)
    pred = np.zeros((1, 4, 4), np.uint8)
    gt[0, :2, :2] = L.BOX      # 4 box pixels
    pred[0, :2, :3] = L.BOX    # 6 predicted, 4 correct
    iou, prec = paper_scores(pred, gt, L.BOX)
    assert iou[0] == pytest.approx(4 / 6) and prec[0] == pytest.approx(4 / 6)
    pred2 = np.zeros_like(pred)
    pred2[0, 0, 0] = L.BOX     # 1 predicted, correct
    iou, prec = paper_scores(pred2, gt, L.BOX)
    assert iou[0] == pytest.approx(1 / 4) and prec[0] == 1.0


def test_empty_in_both_counts_one_and_empty_prediction_zero():
    gt = np.zeros((2, 8, 8), np.uint8)
    pred = np.zeros((2, 8, 8), np.uint8)
    gt[1, 0, 0] = L.SHELF
    iou, prec = paper_scores(pred, gt, L.SHELF)
    np.testing.assert_array_equal(iou, [1.0, 0.0])
    np.testing.assert_array_equal(prec, [1.0, 0.0])


def test_all_background_floor_vs_dataset_level():
    # 4 channels, 1 visible shelf: the paper protocol gives an empty prediction 3/4, the
    # dataset-level IoU gives it 0.
    gt = np.zeros((1, 4, 8, 8), np.uint8)
    gt[0, 0, 2:6, :] = L.SHELF
    gt[0, 0, 3:5, 2:4] = L.BOX
    m = LayoutMetrics()
    m.update("top", np.zeros_like(gt), gt)
    r = m.result()["top"]
    assert r["paper"]["rack"]["mIoU"] == pytest.approx(0.75)
    assert r["paper"]["box"]["mIoU"] == pytest.approx(0.75)
    assert r["dataset"]["box"]["IoU"] == 0.0 and r["dataset"]["shelf"]["IoU"] == 0.0


def test_perfect_prediction_and_confusion():
    rng = np.random.default_rng(0)
    gt = rng.integers(0, 3, size=(3, 4, 16, 16)).astype(np.uint8)
    m = LayoutMetrics()
    probs = np.eye(3, dtype=np.float32)[gt].transpose(0, 1, 4, 2, 3)  # (N, R, 3, D, D) one-hot
    m.update("front", gt, gt, probs=probs)
    r = m.result()["front"]
    for k in ("rack", "box"):
        assert r["paper"][k]["mIoU"] == 1.0 and r["paper"][k]["pixel_precision"] == 1.0
    for c in ("shelf", "box"):
        assert r["dataset"][c]["IoU"] == 1.0 and r["dataset"][c]["AP"] == pytest.approx(1.0)
    cm = np.array(r["confusion"])
    assert cm.sum() == gt.size and np.count_nonzero(cm - np.diag(np.diag(cm))) == 0
    np.testing.assert_array_equal(confusion(np.array([0, 1, 2, 2]), np.array([0, 2, 2, 1])),
                                  [[1, 0, 0], [0, 0, 1], [0, 1, 1]])


def test_average_precision_hand_computed():
    # scores: positives in bins 9 and 5, negatives in bins 7 and 1
    pos = np.zeros(10, np.int64); pos[[9, 5]] = 1
    neg = np.zeros(10, np.int64); neg[[7, 1]] = 1
    # ranking: P(9) N(7) P(5) N(1): AP = 1*0.5 + 2/3*0.5
    assert average_precision_from_hist(pos, neg) == pytest.approx(0.5 + 1 / 3)


def test_shape_mismatch_is_an_error():
    with pytest.raises(ValueError, match="shape"):
        LayoutMetrics().update("top", np.zeros((4, 8, 8)), np.zeros((4, 16, 16)))


def test_tables_label_precision_honestly():
    gt = np.zeros((1, 4, 8, 8), np.uint8)
    m = LayoutMetrics()
    m.update("top", gt, gt)
    txt = format_tables(m.result())
    assert "pixel precision" in txt and "mAP" in txt and "| top rack |" in txt


def test_eval_counts_separate_boxes_in_place_in_the_front_view():
    """What `racklay eval` reports for boxes as boxes: shelves whose truth holds two loads apart,
    how many the prediction separates, and how many with its gap where the truth's is."""
    G = L.Grid(size=128, extent=4.0)
    two = [L.Box(-0.6, 0.0, 0.4, 0.5, 0.3), L.Box(0.5, 0.0, 0.4, 0.5, 0.3)]   # a gap from x = -0.4 to 0.3 m
    truth = L.stack_shelves([L.rasterize_shelf(L.Shelf(2.0, 0.8, 0.6), two, G)], R=2, grid=G)[1]
    wrong = [L.Box(-0.85, 0.0, 0.1, 0.5, 0.3), L.Box(0.1, 0.0, 1.6, 0.5, 0.3)]  # a gap from -0.8 to -0.7 m
    pred = L.stack_shelves([L.rasterize_shelf(L.Shelf(2.0, 0.8, 0.6), wrong, G)], R=2, grid=G)[1]
    merged = truth.copy()
    cols = np.nonzero((merged[0] == L.BOX).any(0))[0]
    merged[0][np.ix_((merged[0] == L.BOX).any(1), np.arange(cols[0], cols[-1] + 1))] = L.BOX
    m = LayoutMetrics()
    m.update("front", np.stack([truth, pred, merged]), np.stack([truth, truth, truth]))
    sep = m.result()["front"]["separation"]
    assert sep["shelves"] == {"truth": 3, "separated": 2, "placed": 1, "predicted": 2}
    assert sep["images"] == sep["shelves"]
    assert "separates 2 of them, 1 with its gaps where the truth's are" in format_tables(m.result())
    m.update("top", truth, truth)
    assert "separation" not in m.result()["top"]


def test_eval_counts_images_whose_prediction_misses_or_merges_a_shelf():
    """What `racklay eval` reports for multi-level racks: per image, whether the prediction holds
    as many shelves as the truth, fewer or more, and how many two-shelf images keep both."""
    G = L.Grid(size=64, extent=4.0)
    shelf = L.rasterize_shelf(L.Shelf(2.0, 0.8, 0.6), [], G)
    one = L.stack_shelves([shelf], R=3, grid=G)[1]
    two = L.stack_shelves([shelf, shelf], R=3, grid=G)[1]
    m = LayoutMetrics()
    # two shelves seen as one (the failure), two as two, one as two, one as one
    m.update("front", np.stack([one, two, two, one]), np.stack([two, two, one, one]))
    c = m.result()["front"]["shelf_count"]
    assert c == {"equal": 2, "fewer": 1, "more": 1, "multi": 2, "multi_found": 1}
    assert "fewer in 1, more in 1; all of them in 1 of the 2 images whose truth holds two or more" in format_tables(m.result())
