"""KITTI AP evaluator: analytic cases, a literal devkit port on random scenes, and the CLI."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from vsrd_mi.cli import main
from vsrd_mi.data.kitti_labels import label_from_box, write_labels
from vsrd_mi.errors import DataError
from vsrd_mi.evaluate.ap import average_precision, devkit_thresholds
from vsrd_mi.evaluate.attributes import (
    ATTRIBUTES_FORMAT,
    CarAttributes,
    read_attributes,
)
from vsrd_mi.evaluate.matching import (
    FrameMatchInput,
    count_at_threshold,
    orientation_similarity,
)
from vsrd_mi.evaluate.metrics import car_interval, hungarian_pairs, yaw_error_mod_pi
from vsrd_mi.evaluate.sequence import (
    EvalConfig,
    FrameBoxes,
    evaluate_frames,
    evaluate_sequence,
    observation_angles,
)
from vsrd_mi.geometry.boxes import Box3D
from vsrd_mi.geometry.camera import box_to_2d
from vsrd_mi.geometry.iou3d import iou_matrices

W, H, L = 1.8, 1.5, 4.2
EASY_PX, HARD_ONLY_PX, TINY_PX = 100.0, 30.0, 20.0  # 2D heights: Easy, Hard but not Easy, ignored
FAR = 1000.0  # x offset that makes a box disjoint from every ground truth


def car(x: float = 0.0, z: float = 20.0, yaw: float = 0.0, y: float = 1.0, dynamic: bool = False) -> Box3D:
    return Box3D(centre=(x, y, z), size=(W, H, L), yaw=yaw, dynamic=dynamic)


def row(n: int, yaw: float = 0.0) -> list[Box3D]:
    """``n`` disjoint cars side by side."""
    return [car(x=4.0 * i, yaw=yaw) for i in range(n)]


def frame(gt, pred=(), scores=(), gt_h=None, pred_h=None, index=0) -> FrameBoxes:
    return FrameBoxes(frame=index, gt=list(gt),
                      gt_height=np.full(len(gt), EASY_PX) if gt_h is None else gt_h,
                      pred=list(pred), pred_score=np.asarray(scores, dtype=float),
                      pred_height=np.full(len(pred), EASY_PX) if pred_h is None else pred_h)


def ap(result, metric="3d", thr="0.5", difficulty="easy"):
    return result["ap"][metric][thr][difficulty]


def perfect_frames(n_frames: int, per_frame: int) -> list[FrameBoxes]:
    out = []
    for i in range(n_frames):
        gt = row(per_frame, yaw=0.1 * i)
        out.append(frame(gt, gt, np.linspace(0.9, 0.5, per_frame) - 0.01 * i, index=i))
    return out


def all_ap_values(result, key):
    return [v[key] for m in result["ap"].values() for t in m.values() for v in t.values()]


def test_perfect_predictions_score_100():
    result = evaluate_frames(perfect_frames(9, 5))  # 45 ground-truth cars
    for key in ("R40", "R11", "devkit_R40", "devkit_R11"):
        assert all_ap_values(result, key) == pytest.approx([100.0] * 12, abs=1e-9)
    assert result["pairs"]["all"]["mean_iou_3d"] == pytest.approx(1.0, abs=1e-9)
    assert result["pairs"]["all"]["centre_error_m"] == pytest.approx(0.0, abs=1e-9)


def test_devkit_curve_quirk_with_few_ground_truth_boxes():
    """The devkit maps the k-th kept threshold to recall sample k: with exactly 40 boxes the first
    true positive (recall 1/40) lands on sample 0 and sample 40 stays empty."""
    res = ap(evaluate_frames(perfect_frames(8, 5)))
    assert res["R40"] == pytest.approx(100.0) and res["R11"] == pytest.approx(100.0)
    assert res["devkit_R40"] == pytest.approx(97.5)
    assert res["devkit_R11"] == pytest.approx(100.0 * 10 / 11)


def test_false_positives_with_lower_scores_do_not_lower_ap():
    frames = []
    for i in range(10):
        gt = row(4)
        fps = [car(x=FAR + 4.0 * k) for k in range(4)]
        frames.append(frame(gt, gt + fps, [0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3, 0.2], index=i))
    res = ap(evaluate_frames(frames))
    assert res["R40"] == pytest.approx(100.0) and res["R11"] == pytest.approx(100.0)


def test_false_positives_with_higher_scores_halve_ap():
    frames = []
    for i in range(12):
        gt = row(4)
        fps = [car(x=FAR + 4.0 * k) for k in range(4)]
        frames.append(frame(gt, fps + gt, [0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3, 0.2], index=i))
    res = ap(evaluate_frames(frames))
    # at any threshold that keeps a TP, all 48 FPs are kept: precision tp / (tp + 48) <= 1/2
    assert res["R40"] == pytest.approx(50.0) and res["R11"] == pytest.approx(50.0)
    assert res["devkit_R40"] == pytest.approx(50.0)


def test_interleaved_false_positives_give_the_analytic_ap():
    """Scores alternate TP, FP, TP, FP... over 40 ground-truth cars (one per frame)."""
    frames = []
    for k in range(40):
        gt = [car()]
        frames.append(frame(gt, [gt[0], car(x=FAR)], [1.0 - 0.02 * k, 0.99 - 0.02 * k], index=k))
    res = ap(evaluate_frames(frames), metric="bev", thr="0.7")
    precision = {k: k / (2 * k - 1) for k in range(1, 41)}  # right after the k-th TP
    precision[0] = 1.0
    assert res["R40"] == pytest.approx(100 * np.mean([precision[k] for k in range(1, 41)]), abs=1e-9)
    assert res["R11"] == pytest.approx(100 * np.mean([precision[k] for k in range(0, 41, 4)]), abs=1e-9)


@pytest.mark.parametrize("rel", [0.2, 0.45, 0.6])
def test_shift_along_length_decides_true_positives(rel):
    d = rel * L
    iou = (L - d) / (L + d)  # BEV and 3D (same height)
    frames = [frame(row(3), [car(x=4.0 * i, z=20.0 + d) for i in range(3)], [0.9, 0.8, 0.7], index=j)
              for j in range(15)]
    result = evaluate_frames(frames)
    for thr in ("0.3", "0.5", "0.7"):
        expected = 100.0 if iou > float(thr) else 0.0
        for metric in ("bev", "3d"):
            assert ap(result, metric, thr)["R40"] == pytest.approx(expected, abs=1e-9)
            assert ap(result, metric, thr)["devkit_R11"] == pytest.approx(expected, abs=1e-9)
    pairs = result["pairs"]["all"]
    assert pairs["mean_iou_bev"] == pytest.approx(iou, abs=1e-9)
    assert pairs["centre_error_m"] == pytest.approx(d, abs=1e-9)
    assert pairs["yaw_error_deg"] == pytest.approx(0.0, abs=1e-9)


def test_quarter_turn_fails_every_threshold_but_is_matched():
    gt = row(3, yaw=0.3)
    turned = row(3, yaw=0.3 + math.pi / 2)
    result = evaluate_frames([frame(gt, turned, [0.9, 0.8, 0.7])])
    assert all_ap_values(result, "R40") == [0.0] * 12
    iou = W * W / (2 * W * L - W * W)
    assert result["pairs"]["all"]["n_matched"] == 3
    assert result["pairs"]["all"]["mean_iou_3d"] == pytest.approx(iou, abs=1e-9)
    assert result["pairs"]["all"]["yaw_error_deg"] == pytest.approx(90.0, abs=1e-9)


def test_half_turn_is_a_perfect_match():
    gt = row(2, yaw=0.2)
    result = evaluate_frames([frame(gt, row(2, yaw=0.2 + math.pi), [0.9, 0.8])] * 30)
    assert all_ap_values(result, "R40") == pytest.approx([100.0] * 12)
    assert result["pairs"]["all"]["yaw_error_deg"] == pytest.approx(0.0, abs=1e-9)


def test_disjoint_predictions():
    gt = row(3)
    result = evaluate_frames([frame(gt, [car(x=FAR + 4.0 * i) for i in range(3)], [0.9, 0.8, 0.7])])
    assert all_ap_values(result, "R40") == [0.0] * 12
    s = result["pairs"]["all"]
    assert s["n_gt"] == 3 and s["n_matched"] == 0
    assert s["mean_iou_3d"] is None and s["recall_weighted_iou_3d"] == 0.0


def test_no_ground_truth_gives_undefined_ap():
    result = evaluate_frames([frame([], [car()], [0.5])])
    assert all_ap_values(result, "R40") == [None] * 12


def test_small_boxes_are_ignored_either_way():
    base = perfect_frames(10, 5)  # 50 counted cars, AP 100
    extra_gt = [car(x=-10.0), car(x=-20.0), car(x=-30.0)]
    extra_pred = [extra_gt[0], extra_gt[1], car(x=FAR)]
    small = frame(extra_gt, extra_pred, [0.99, 0.98, 0.97],
                  # GT: hard-only (matched), tiny (matched), tiny (missed); preds: matched hard-only
                  # pred, tiny pred on tiny GT, tiny unmatched false positive with a top score.
                  gt_h=np.array([HARD_ONLY_PX, TINY_PX, TINY_PX]),
                  pred_h=np.array([HARD_ONLY_PX, TINY_PX, TINY_PX]), index=99)
    result = evaluate_frames(base + [small])
    for difficulty in ("easy", "hard"):
        res = ap(result, difficulty=difficulty)
        assert res["R40"] == pytest.approx(100.0) and res["devkit_R40"] == pytest.approx(100.0)
    assert ap(result, difficulty="easy")["n_gt"] == 50
    assert ap(result, difficulty="hard")["n_gt"] == 51
    assert result["counts"]["hard"] == {"n_gt": 51, "n_pred": 51}
    # the same small GT left unmatched would be a miss in Hard only
    unmatched = frame(extra_gt[:1], [], [], gt_h=np.array([HARD_ONLY_PX]), pred_h=np.empty(0), index=98)
    result = evaluate_frames(base + [unmatched])
    assert ap(result, difficulty="easy")["R40"] == pytest.approx(100.0)
    assert ap(result, difficulty="hard")["max_recall"] == pytest.approx(50 / 51)
    assert ap(result, difficulty="hard")["R40"] == pytest.approx(100.0 * 39 / 40)


def test_small_prediction_on_counted_ground_truth_is_neither_tp_nor_fn():
    """Devkit rule: a match between counted GT and an ignored detection only assigns the detection."""
    f = FrameMatchInput(overlap=np.array([[0.9]]), gt_ignored=np.array([False]),
                        det_ignored=np.array([True]), scores=np.array([0.5]))
    c = count_at_threshold(f, 0.5, 0.0)
    assert (c.tp, c.fp, c.fn) == (0, 0, 0)


def test_car_count_names_each_car_once_across_frames_and_sequences():
    """The same instance in three frames of one sequence is one car; the same id in another
    sequence is another car; ground truth without an id counts per record."""
    def named(iid, x=0.0):
        return Box3D(centre=(x, 1.0, 20.0), size=(W, H, L), yaw=0.0, instance_id=iid)

    frames = [dataclasses.replace(frame([named(7), named(8, x=4.0)], index=i), sequence="a") for i in range(3)]
    frames.append(dataclasses.replace(frame([named(7), car(x=8.0)], index=0), sequence="b"))
    frames.append(dataclasses.replace(frame([car(x=8.0)], index=1), sequence="b"))
    s = evaluate_frames(frames)["pairs"]["all"]
    assert (s["n_gt"], s["n_cars"]) == (9, 5)


def test_car_interval_resamples_cars_not_records():
    """Ten records of a car 10 % long and one of a car 10 % short: the mean over records is
    +8.2 %, but with two cars nothing says which is typical, so the interval over cars spans
    nearly both; resampling the eleven records as independent ones would give a narrow one."""
    values = np.array([0.1] * 10 + [-0.1])
    lo, hi = car_interval(values, np.array([0] * 10 + [1]))
    assert lo == pytest.approx(-0.1, abs=1e-9) and hi == pytest.approx(0.1, abs=1e-9)
    lo_rec, hi_rec = car_interval(values, np.arange(11))
    assert lo_rec > 0.0 and hi_rec == pytest.approx(0.1)
    # one car: no spread between cars is known, the interval is its mean
    assert car_interval(np.array([0.02, 0.04]), np.array([5, 5])) == pytest.approx((0.03, 0.03))
    # many cars of one error each: the interval holds the mean and shrinks with the number of cars
    rng = np.random.default_rng(1)
    widths = []
    for n in (10, 200):
        v = rng.normal(0.05, 0.08, n)
        lo, hi = car_interval(v, np.arange(n))
        assert lo < v.mean() < hi
        widths.append(hi - lo)
    assert widths[1] < 0.4 * widths[0]
    with pytest.raises(ValueError, match="car labels"):
        car_interval(np.zeros(3), np.zeros(2))


def test_size_bias_reports_an_interval_over_cars():
    """The size bias of one car seen in three frames and another in one: the interval's ends are
    the two cars' errors (a car either way round twice)."""
    def named(iid, length, x=0.0):
        return Box3D(centre=(x, 1.0, 20.0), size=(W, H, length), yaw=0.0, instance_id=iid)

    frames = [dataclasses.replace(frame([named(1, L), named(2, L, x=5.0)],
                                        [named(1, 1.1 * L), named(2, 0.9 * L, x=5.0)], [0.9, 0.9], index=0),
                                  sequence="s")]
    frames += [dataclasses.replace(frame([named(1, L)], [named(1, 1.1 * L)], [0.9], index=i), sequence="s")
               for i in (1, 2)]
    bias = evaluate_frames(frames)["pairs"]["all"]["size_bias"]["length"]
    assert bias["mean_rel"] == pytest.approx((3 * 0.1 - 0.1) / 4)
    assert bias["mean_rel_ci95"] == pytest.approx([-0.1, 0.1])
    assert evaluate_frames(frames)["pairs"]["all"]["size_bias"]["n_cars"] == 2
    assert evaluate_frames(frames)["pairs"]["all"]["size_bias"]["height"]["mean_rel_ci95"] == pytest.approx([0, 0])


def test_pair_statistics_split_static_dynamic():
    gt = [car(x=0.0), car(x=5.0, dynamic=True), car(x=10.0, dynamic=True)]
    pred = [Box3D(centre=(0.3, 1.0, 20.0), size=(W + 0.2, H, L - 0.4), yaw=0.1),
            car(x=5.0, z=20.5)]  # third car missed
    result = evaluate_frames([frame(gt, pred, [0.8, 0.7])])
    s, d, a = (result["pairs"][g] for g in ("static", "dynamic", "all"))
    assert (s["n_gt"], s["n_matched"], d["n_gt"], d["n_matched"], a["n_gt"]) == (1, 1, 2, 1, 3)
    assert s["centre_error_m"] == pytest.approx(0.3)
    assert s["yaw_error_deg"] == pytest.approx(math.degrees(0.1))
    assert s["size_error_m"] == pytest.approx({"w": 0.2, "h": 0.0, "l": 0.4})
    iou_dyn = (L - 0.5) / (L + 0.5)
    assert d["mean_iou_3d"] == pytest.approx(iou_dyn)
    assert d["recall_weighted_iou_3d"] == pytest.approx(iou_dyn / 2)
    bev, iou3d = iou_matrices(gt[:1], pred[:1])
    assert a["mean_iou_bev"] == pytest.approx((bev[0, 0] + iou_dyn) / 2)
    assert a["recall_weighted_iou_3d"] == pytest.approx((iou3d[0, 0] + iou_dyn) / 3)


def test_hungarian_prefers_the_global_optimum():
    gt = [car(x=0.0), car(x=1.0)]
    pred = [car(x=0.6), car(x=-0.9)]  # greedy on pred 0 would take gt 1 and leave a worse pair
    pairs = hungarian_pairs(gt, pred)
    assert sorted((i, j) for i, j, _, _ in pairs) == [(0, 1), (1, 0)]


def test_yaw_error_is_modulo_pi():
    assert math.degrees(yaw_error_mod_pi(0.1, math.pi + 0.1)) == pytest.approx(0.0, abs=1e-9)
    assert math.degrees(yaw_error_mod_pi(math.radians(170), math.radians(-170))) == pytest.approx(20.0)
    assert math.degrees(yaw_error_mod_pi(0.0, math.radians(100))) == pytest.approx(80.0)


# ---- a literal port of the devkit's loops, to check the vectorised / event-sum implementation ----

NO_DETECTION = -10000000.0


def _devkit_statistics(ov, ig_gt, ig_det, scores, min_overlap, compute_fp, thresh, alpha_gt=None, alpha_det=None):
    assigned = [False] * len(scores)
    ig_thr = [s < thresh for s in scores]
    tp = fp = fn = 0
    v, delta = [], []
    for i in range(len(ig_gt)):
        det_idx, valid, max_iou, assigned_ignored = -1, NO_DETECTION, 0.0, False
        for j in range(len(scores)):
            if assigned[j] or ig_thr[j]:
                continue
            o = ov[i][j]
            if not compute_fp and o > min_overlap and scores[j] > valid:
                det_idx, valid = j, scores[j]
            elif compute_fp and o > min_overlap and (o > max_iou or assigned_ignored) and not ig_det[j]:
                max_iou, det_idx, valid, assigned_ignored = o, j, 1, False
            elif compute_fp and o > min_overlap and valid == NO_DETECTION and ig_det[j]:
                det_idx, valid, assigned_ignored = j, 1, True
        if valid == NO_DETECTION and not ig_gt[i]:
            fn += 1
        elif valid != NO_DETECTION and (ig_gt[i] or ig_det[det_idx]):
            assigned[det_idx] = True
        elif valid != NO_DETECTION:
            tp += 1
            v.append(scores[det_idx])
            if alpha_gt is not None:
                delta.append(alpha_gt[i] - alpha_det[det_idx])
            assigned[det_idx] = True
    if compute_fp:
        fp = sum(1 for j in range(len(scores)) if not (assigned[j] or ig_det[j] or ig_thr[j]))
    similarity = sum((1.0 + math.cos(d)) / 2.0 for d in delta)
    return tp, fp, fn, v, similarity


def _get_thresholds(v, n_groundtruth, n_sample_pts=41):
    """The devkit's getThresholds, line by line."""
    t = []
    v = sorted(v, reverse=True)
    current_recall = 0.0
    for i in range(len(v)):
        l_recall = (i + 1) / n_groundtruth
        r_recall = (i + 2) / n_groundtruth if i < len(v) - 1 else l_recall
        if (r_recall - current_recall) < (current_recall - l_recall) and i < len(v) - 1:
            continue
        current_recall += 1.0 / (n_sample_pts - 1.0)
        t.append(v[i])
    return t


def _reference_aps(frames, min_overlap, alphas=None, aos=False):
    """(exact, devkit) AP|R40 and AP|R11 of a literal port; AOS instead of AP with ``aos``
    (``alphas``: per frame (gt alphas, detection alphas))."""
    n_gt = sum(int(np.sum(~f.gt_ignored)) for f in frames)
    alphas = alphas or [(None, None)] * len(frames)
    args = [(f.overlap.tolist(), f.gt_ignored.tolist(), f.det_ignored.tolist(), f.scores.tolist())
            for f in frames]
    v = [s for a in args for s in _devkit_statistics(*a, min_overlap, False, 0.0)[3]]

    def totals(t):
        stats = [_devkit_statistics(*a, min_overlap, True, t, *al) for a, al in zip(args, alphas)]
        return np.sum([(tp, fp, fn, sim) for tp, fp, fn, _, sim in stats], axis=0)

    def value(tp, fp, sim):
        return (sim if aos else tp) / (tp + fp) if tp + fp else 0.0

    # devkit curve
    thresholds = _get_thresholds(v, n_gt)
    prec = [0.0] * 41
    for i, t in enumerate(thresholds):
        tp, fp, _, sim = totals(t)
        prec[i] = value(tp, fp, sim)
    prec = [max(prec[i:]) for i in range(41)]
    devkit = (100 * sum(prec[1:]) / 40, 100 * sum(prec[0::4]) / 11)
    # exact curve, from every distinct score
    points = []
    for t in sorted({s for a in args for s in a[3]}):
        tp, fp, _, sim = totals(t)
        points.append((tp / n_gt, value(tp, fp, sim)))
    samples = [max([p for r, p in points if r >= k / 40 - 1e-12], default=0.0) for k in range(41)]
    exact = (100 * sum(samples[1:]) / 40, 100 * sum(samples[0::4]) / 11)
    return exact, devkit


@pytest.mark.parametrize("seed", range(4))
def test_against_a_literal_devkit_port(seed):
    rng = np.random.default_rng(seed)
    frames = []
    for _ in range(25):
        n_gt, n_det = rng.integers(0, 6), rng.integers(0, 8)
        gt = [car(x=rng.uniform(-6, 6), z=rng.uniform(10, 30), yaw=rng.uniform(-3, 3)) for _ in range(n_gt)]
        det = [Box3D(centre=g.centre + rng.normal(0, 0.5, 3) * [1, 0.1, 1], size=g.size * rng.uniform(0.8, 1.2),
                     yaw=g.yaw + rng.normal(0, 0.2)) for g in gt if rng.uniform() < 0.8]
        det += [car(x=rng.uniform(-6, 6), z=rng.uniform(10, 30), yaw=rng.uniform(-3, 3))
                for _ in range(max(0, n_det - len(det)))]
        if det and rng.uniform() < 0.3:
            det.append(det[0])  # an exact duplicate: ties in overlap
        frames.append((gt, det, np.round(rng.uniform(0.05, 1, len(det)), 1),  # ties in score
                       rng.choice([TINY_PX, HARD_ONLY_PX, EASY_PX], len(gt), p=[0.15, 0.25, 0.6]),
                       rng.choice([TINY_PX, HARD_ONLY_PX, EASY_PX], len(det), p=[0.15, 0.25, 0.6])))
    alphas = [(observation_angles(g), observation_angles(d)) for g, d, *_ in frames]
    for metric in (0, 1):
        for thr in (0.3, 0.5):
            for min_h in (25.0, 40.0):
                inputs = [FrameMatchInput(overlap=iou_matrices(g, d)[metric], gt_ignored=gh <= min_h,
                                          det_ignored=dh < min_h, scores=s,
                                          similarity=orientation_similarity(*al))
                          for (g, d, s, gh, dh), al in zip(frames, alphas)]
                res = average_precision(inputs, thr)
                (r40, r11), (d40, d11) = _reference_aps(inputs, thr)
                assert res.r40 == pytest.approx(r40, abs=1e-9)
                assert res.r11 == pytest.approx(r11, abs=1e-9)
                assert res.devkit_r40 == pytest.approx(d40, abs=1e-9)
                assert res.devkit_r11 == pytest.approx(d11, abs=1e-9)
                (a40, a11), (da40, da11) = _reference_aps(inputs, thr, alphas, aos=True)
                assert res.aos_r40 == pytest.approx(a40, abs=1e-9)
                assert res.aos_r11 == pytest.approx(a11, abs=1e-9)
                assert res.devkit_aos_r40 == pytest.approx(da40, abs=1e-9)
                assert res.devkit_aos_r11 == pytest.approx(da11, abs=1e-9)
                assert res.aos_r40 <= res.r40 + 1e-9


def test_devkit_thresholds_pick_nearest_recall():
    scores = list(np.linspace(1.0, 0.01, 100))  # 100 TPs of 100 GT: recall i/100
    t = devkit_thresholds(scores, 100)
    assert len(t) == 41
    # sample k (k >= 1) uses the TP whose recall is nearest k/40 (ties to the lower one)
    for k in range(1, 41):
        i = scores.index(t[k])
        assert abs((i + 1) / 100 - k / 40) <= 0.005 + 1e-12


# ---------------------------------- the CLI on a tiny KITTI-360 ----------------------------------

SEQ = "2013_05_28_drive_0007_sync"
FX, CX, CY, IMG_W, IMG_H = 500.0, 500.0, 150.0, 1000, 300
K = np.array([[FX, 0, CX], [0, FX, CY], [0, 0, 1.0]])
# rectified camera (x right, y down, z forward) -> world (z up), camera looking along world +x
R_CAM_TO_WORLD = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
CAM_STEP = 1.0  # camera moves 1 m along world +x per frame
PROJECTED = EvalConfig(gt_boxes="projected")


def _matrix_xml(tag: str, m: np.ndarray) -> str:
    data = " ".join(f"{v:.9f}" for v in m.ravel())
    return (f"<{tag} type_id=\"opencv-matrix\"><rows>{m.shape[0]}</rows><cols>{m.shape[1]}</cols>"
            f"<dt>d</dt><data>{data}</data></{tag}>")


def _object_xml(index, instance_id, world_centre, lwh, timestamp, start, end) -> str:
    T = np.eye(4)
    T[:3, :3] = np.diag(lwh)  # heading along world +x
    T[:3, 3] = world_centre
    unit = np.array([[.5, .5, .5], [.5, .5, -.5], [.5, -.5, .5], [.5, -.5, -.5],
                     [-.5, .5, -.5], [-.5, .5, .5], [-.5, -.5, -.5], [-.5, -.5, .5]])
    return (f"<object{index}><index>{index}</index><label>car</label><semanticId>13</semanticId>"
            f"<instanceId>{instance_id}</instanceId><category>vehicle</category>"
            f"<start_frame>{start}</start_frame><end_frame>{end}</end_frame>"
            f"<timestamp>{timestamp}</timestamp>{_matrix_xml('transform', T)}"
            f"{_matrix_xml('vertices', unit)}{_matrix_xml('faces', np.zeros((1, 3)))}</object{index}>")


def _camera_boxes(frame: int) -> list[Box3D]:
    """The ground truth of ``frame`` written by :func:`_write_dataset`, in camera coordinates."""
    dz = -CAM_STEP * frame
    return [Box3D(centre=(-3.0, 1.0, 12.0 + dz), size=(1.8, 1.5, 4.2), yaw=0.0),            # static, easy
            Box3D(centre=(4.0, 1.0, 25.0 + dz), size=(1.8, 1.5, 4.2), yaw=0.0),             # static, hard only
            Box3D(centre=(0.0, 1.0, 15.0 + 2.0 * frame), size=(1.9, 1.6, 4.6), yaw=0.0,
                  dynamic=True)]                                                           # moving, easy


def _write_dataset(root: Path, frames=(0, 1, 2)) -> None:
    (root / "calibration").mkdir(parents=True)
    P0 = np.hstack([K, np.zeros((3, 1))])
    P1 = P0.copy()
    P1[0, 3] = -FX * 0.6
    fmt = lambda a: " ".join(f"{v:.9e}" for v in np.ravel(a))  # noqa: E731
    (root / "calibration" / "perspective.txt").write_text(
        f"S_rect_00: {IMG_W} {IMG_H}\nR_rect_00: {fmt(np.eye(3))}\nP_rect_00: {fmt(P0)}\n"
        f"S_rect_01: {IMG_W} {IMG_H}\nP_rect_01: {fmt(P1)}\n")
    poses = root / "data_poses" / SEQ
    poses.mkdir(parents=True)
    lines = []
    for f in frames:
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R_CAM_TO_WORLD, (CAM_STEP * f, 0.0, 0.0)
        lines.append(f"{f} {fmt(T)}")
    (poses / "cam0_to_world.txt").write_text("\n".join(lines) + "\n")
    images = root / "data_2d_raw" / SEQ / "image_00" / "data_rect"
    images.mkdir(parents=True)
    for f in frames:
        cv2.imwrite(str(images / f"{f:010d}.png"), np.zeros((IMG_H, IMG_W, 3), np.uint8))
    # world = R_CAM_TO_WORLD @ cam + t: cam (x, y, z) -> world (z + t, -x, -y)
    objects = [_object_xml(1, 1, (12.0, 3.0, -1.0), (4.2, 1.8, 1.5), -1, 0, 100),
               _object_xml(2, 2, (25.0, -4.0, -1.0), (4.2, 1.8, 1.5), -1, 0, 100)]
    objects += [_object_xml(3 + f, 3, (15.0 + 3.0 * f, 0.0, -1.0), (4.6, 1.9, 1.6), f, 0, 100)
                for f in frames]
    boxes = root / "data_3d_bboxes" / "train"
    boxes.mkdir(parents=True)
    (boxes / f"{SEQ}.xml").write_text("<?xml version=\"1.0\"?>\n<opencv_storage>\n"
                                      + "\n".join(objects) + "\n</opencv_storage>\n")


def _write_predictions(label_dir: Path, frame: int, boxes: list[Box3D], scores) -> None:
    labels = [label_from_box(b, box_to_2d(b, K, image_size=(IMG_W, IMG_H)), s) for b, s in zip(boxes, scores)]
    write_labels(label_dir / f"{frame:010d}.txt", labels)


@pytest.fixture()
def dataset(tmp_path):
    root = tmp_path / "kitti360"
    _write_dataset(root)
    return root


def test_tiny_sequence_ground_truth_is_what_was_written(dataset):
    from vsrd_mi.data.kitti360 import Sequence
    seq = Sequence(dataset, 7)
    for f in (0, 1, 2):
        got = sorted(seq.ground_truth(f), key=lambda b: b.instance_id)
        for g, e in zip(got, _camera_boxes(f)):
            np.testing.assert_allclose(g.centre, e.centre, atol=1e-6)
            np.testing.assert_allclose(g.size, e.size, atol=1e-6)
            assert abs(math.sin(g.yaw - e.yaw)) < 1e-6 and g.dynamic == e.dynamic


def test_cli_perfect_predictions(dataset, tmp_path, capsys):
    pred = tmp_path / "pred"
    for f in (0, 1, 2):
        _write_predictions(pred, f, _camera_boxes(f), [0.9, 0.8, 0.7])
    assert main(["eval", "--pred", str(pred), "--gt", str(dataset), "--sequence", "7", "--json",
                 "--gt-boxes", "projected"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["sequence"] == SEQ and result["frames"] == [0, 1, 2]
    assert result["protocol"]["gt_boxes"] == "projected"
    assert result["counts"]["easy"]["n_gt"] == 6 and result["counts"]["hard"]["n_gt"] == 9
    for key in ("R40", "R11"):
        assert all_ap_values(result, key) == pytest.approx([100.0] * 12, abs=1e-6)
    assert result["pairs"]["dynamic"]["n_gt"] == 3
    assert result["pairs"]["dynamic"]["mean_iou_3d"] == pytest.approx(1.0, abs=1e-5)
    assert result["protocol"]["headline_curve"] == "exact"
    assert main(["eval", "--pred", str(pred), "--gt", str(dataset), "--sequence", SEQ, "--gt-boxes", "projected"]) == 0
    table = capsys.readouterr().out
    assert "AP_BEV@0.3" in table and "AP_3D@0.5" in table and "100.00" in table and "dynamic" in table
    assert "Ground-truth 2D boxes: projected" in table and "AOS(3D@0.5)" in table


def test_cli_nested_layout_frames_and_misses(dataset, tmp_path, capsys):
    labels = tmp_path / "out" / SEQ / "labels"
    boxes = _camera_boxes(0)
    moved = [boxes[0], boxes[1], Box3D(centre=boxes[2].centre + (0, 0, 0.45 * 4.6), size=boxes[2].size,
                                       yaw=0.0, dynamic=True)]
    _write_predictions(labels, 0, moved, [0.9, 0.8, 0.7])
    _write_predictions(labels, 2, _camera_boxes(2), [0.9, 0.8, 0.7])
    # frames 0-1: frame 1 has no file and counts as all missed; frame 2 is not selected
    assert main(["eval", "--pred", str(tmp_path / "out"), "--gt", str(dataset), "--sequence", "7",
                 "--frames", "0-1", "--json", "--gt-boxes", "projected"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["frames"] == [0, 1] and result["frames_without_predictions"] == [1]
    easy_iou = (1 - 0.45) / (1 + 0.45)  # the moving car, shifted by 45 % of its length
    assert ap(result, "bev", "0.3")["max_recall"] == pytest.approx(2 / 4)
    assert ap(result, "bev", "0.5")["max_recall"] == pytest.approx(1 / 4)
    assert ap(result, "bev", "0.3")["R40"] == pytest.approx(100 * 20 / 40)
    assert ap(result, "bev", "0.5")["R40"] == pytest.approx(100 * 10 / 40)
    assert result["pairs"]["dynamic"]["mean_iou_bev"] == pytest.approx(easy_iou, abs=1e-6)
    assert result["pairs"]["dynamic"]["recall_weighted_iou_bev"] == pytest.approx(easy_iou / 2, abs=1e-6)
    # without --frames only files count: frames 0 and 2
    result = evaluate_sequence(tmp_path / "out", dataset, SEQ, config=PROJECTED)
    assert result["frames"] == [0, 2] and result["frames_without_predictions"] == []


def test_visible_only_keeps_ground_truth_present_in_the_instance_map(dataset, tmp_path, capsys):
    pred = tmp_path / "pred"
    _write_predictions(pred, 0, _camera_boxes(0)[::2], [0.9, 0.7])  # the hard-only car not labelled
    args = ["eval", "--pred", str(pred), "--gt", str(dataset), "--sequence", "7", "--json", "--gt-boxes", "projected"]
    assert main(args) == 0
    assert ap(json.loads(capsys.readouterr().out), "3d", "0.7", "hard")["max_recall"] == pytest.approx(2 / 3)
    assert main(args + ["--visible-only"]) == 1
    assert "instance" in capsys.readouterr().err  # no instance maps yet
    inst_dir = dataset / "data_2d_semantics" / "train" / SEQ / "image_00" / "instance"
    inst_dir.mkdir(parents=True)
    inst = np.zeros((IMG_H, IMG_W), np.uint16)
    inst[100:200, 100:300] = 26001  # car 1 and car 3 are visible, car 2 is hidden
    inst[120:220, 400:600] = 26003
    inst[0:10, 0:10] = 7  # road (stuff)
    cv2.imwrite(str(inst_dir / "0000000000.png"), inst)
    assert main(args + ["--visible-only"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert ap(result, "3d", "0.7", "hard")["n_gt"] == 2
    assert ap(result, "3d", "0.7", "hard")["R40"] == pytest.approx(100.0)


def test_cli_errors(dataset, tmp_path, capsys):
    assert main(["eval", "--pred", str(tmp_path / "none"), "--gt", str(dataset), "--sequence", "7"]) == 1
    assert "missing prediction directory" in capsys.readouterr().err
    pred = tmp_path / "pred"
    pred.mkdir()
    assert main(["eval", "--pred", str(pred), "--gt", str(dataset), "--sequence", "7"]) == 1
    assert "no prediction files" in capsys.readouterr().err
    (pred / "0000000001.txt").write_text("Car 0 0 0 1 2 3 40 1.5 1.8 4.2 0 1 10 0.1 0.5 extra\n")
    assert main(["eval", "--pred", str(pred), "--gt", str(dataset), "--sequence", "7", "--gt-boxes", "projected"]) == 1
    err = capsys.readouterr().err
    assert "0000000001.txt" in err and "line 1" in err
    (pred / "0000000001.txt").write_text("Car 0 0 0 1 2 3 40 1.5 1.8 4.2 0 1 10 0.1\n")
    with pytest.raises(DataError, match="no score"):
        evaluate_sequence(pred, dataset, 7, config=PROJECTED)
    lenient = EvalConfig(default_score=1.0, gt_boxes="projected")
    assert evaluate_sequence(pred, dataset, 7, config=lenient)["frames"] == [1]
    with pytest.raises(DataError, match="instance map.*--gt-boxes projected"):
        evaluate_sequence(pred, dataset, 7, config=EvalConfig(default_score=1.0))
    (pred / "0000000009.txt").write_text("")
    with pytest.raises(DataError, match="not a frame"):
        evaluate_sequence(pred, dataset, 7, config=lenient)
    with pytest.raises(DataError, match="not frames"):
        evaluate_sequence(pred, dataset, 7, frames=[1, 5])
    with pytest.raises(SystemExit):
        main(["eval", "--pred", str(pred), "--gt", str(dataset), "--sequence", "7", "--frames", "5-2"])


# ------------------------------ the devkit's height rules, AOS, breakdowns ------------------------------


def test_prediction_at_exactly_the_height_limit_counts():
    """eval.py: ground truth is ignored at height <= limit, a detection only below it."""
    gt = row(2)
    result = evaluate_frames([frame(gt, gt, [0.9, 0.8], gt_h=np.array([EASY_PX, 40.0]),
                                    pred_h=np.array([40.0, 40.0]), index=k) for k in range(30)])
    easy = ap(result, difficulty="easy")
    assert easy["n_gt"] == 30 and easy["R40"] == pytest.approx(100.0)
    assert result["counts"]["easy"] == {"n_gt": 30, "n_pred": 60}


def _visible_part_frames(n_frames: int = 12) -> tuple[list, list, list]:
    """Ground truth written as predictions whose 2D boxes are their visible parts: one car of
    three is partly hidden, so its visible box is below the Easy limit while its projected box
    is above it."""
    rng = np.random.default_rng(3)
    gts, projected, visible = [], [], []
    for _ in range(n_frames):
        gts.append(row(3, yaw=float(rng.uniform(-1, 1))))
        projected.append(np.array([EASY_PX, EASY_PX, 60.0]))
        visible.append(np.array([EASY_PX, EASY_PX - 20.0, HARD_ONLY_PX]))
    return gts, projected, visible


def test_ground_truth_as_predictions_with_visible_boxes():
    """Projected ground-truth boxes: the hidden car's match is an ignored prediction, neither hit
    nor miss, and it stays in the devkit's recall denominator, so AP < 100 in our evaluator *and*
    in the literal port; with the ground truth's own visible boxes (the mask protocol) AP = 100."""
    gts, projected, visible = _visible_part_frames()
    scores = [0.9, 0.8, 0.7]
    frames = [frame(g, g, scores, gt_h=p, pred_h=v, index=k) for k, (g, p, v) in enumerate(zip(gts, projected, visible))]
    easy = ap(evaluate_frames(frames), difficulty="easy")
    inputs = [FrameMatchInput(overlap=iou_matrices(f.gt, f.pred)[1], gt_ignored=f.gt_height <= 40.0,
                              det_ignored=f.pred_height < 40.0, scores=f.pred_score) for f in frames]
    (r40, r11), (d40, _) = _reference_aps(inputs, 0.5)
    assert easy["max_recall"] == pytest.approx(2 / 3)
    assert easy["R40"] == pytest.approx(r40) and easy["R11"] == pytest.approx(r11)
    assert easy["devkit_R40"] == pytest.approx(d40)
    assert easy["R40"] == pytest.approx(100.0 * 26 / 40)  # recall 2/3 reaches sample 26 of 40
    masked = [frame(g, g, scores, gt_h=v, pred_h=v, index=k) for k, (g, v) in enumerate(zip(gts, visible))]
    result = evaluate_frames(masked)
    for difficulty in ("easy", "hard"):
        assert ap(result, difficulty=difficulty)["R40"] == pytest.approx(100.0)


def test_aos_and_heading_accuracy_see_backwards_boxes():
    gt = row(4, yaw=0.4)
    n = 12  # 48 cars: the devkit curve has no few-box quirk
    frames = [frame(gt, gt, [0.9, 0.8, 0.7, 0.6], index=k) for k in range(n)]
    result = evaluate_frames(frames)
    res = ap(result)
    assert res["AOS_R40"] == pytest.approx(100.0) and res["devkit_AOS_R11"] == pytest.approx(100.0)
    assert result["pairs"]["all"]["heading_accuracy"] == 1.0
    # every box turned end for end: the same box (AP 100), the opposite heading (AOS 0)
    backwards = [frame(gt, row(4, yaw=0.4 + math.pi), [0.9, 0.8, 0.7, 0.6], index=k) for k in range(n)]
    result = evaluate_frames(backwards)
    res = ap(result)
    assert res["R40"] == pytest.approx(100.0) and res["AOS_R40"] == pytest.approx(0.0, abs=1e-9)
    assert result["pairs"]["all"]["heading_accuracy"] == 0.0
    assert result["pairs"]["all"]["yaw_error_deg"] == pytest.approx(0.0, abs=1e-9)
    # half of them turned: AOS = half of AP at every recall
    mixed = [frame(gt, gt[:2] + row(4, yaw=0.4 + math.pi)[2:], [0.9, 0.8, 0.7, 0.6], index=k) for k in range(n)]
    result = evaluate_frames(mixed)
    assert result["pairs"]["all"]["heading_accuracy"] == pytest.approx(0.5)
    res = ap(result)
    assert res["R40"] == pytest.approx(100.0)
    # precision is 1 at every threshold; thresholds keep t = n, 2n, 3n or 4n TPs, of which the first
    # 2n (scores 0.9 / 0.8) face the right way: sample k is the best min(t, 2n) / t with t / 4n >= k / 40
    samples = [max(min(t, 2 * n) / t for t in (n, 2 * n, 3 * n, 4 * n) if t * 40 >= k * 4 * n) for k in range(41)]
    assert res["AOS_R40"] == pytest.approx(100.0 * np.mean(samples[1:]))
    assert res["AOS_R11"] == pytest.approx(100.0 * np.mean(samples[::4]))


def test_size_bias_heading_and_missed_share_per_class():
    gt = [car(x=0.0), car(x=5.0), car(x=10.0), car(x=15.0)]
    attrs = [CarAttributes(vehicle_class="sedan"), CarAttributes(vehicle_class="sedan"),
             CarAttributes(vehicle_class="van"), CarAttributes(vehicle_class="van")]
    pred = [Box3D(centre=(0.0, 1.0, 20.0), size=(0.9 * W, H, 1.1 * L), yaw=0.0),
            Box3D(centre=(5.0, 1.0, 20.0), size=(0.9 * W, H, 1.3 * L), yaw=math.pi),
            Box3D(centre=(10.0, 1.0, 20.0), size=(W, 1.2 * H, L), yaw=0.0)]  # the last van is missed
    f = FrameBoxes(frame=0, gt=gt, gt_height=np.full(4, EASY_PX), pred=pred, pred_score=[0.9, 0.8, 0.7],
                   pred_height=np.full(3, EASY_PX), gt_attributes=attrs)
    result = evaluate_frames([f])
    sedan, van = result["breakdown"]["by_class"]["sedan"], result["breakdown"]["by_class"]["van"]
    assert sedan["size_bias"]["length"]["mean_rel"] == pytest.approx(0.2)
    assert sedan["size_bias"]["length"]["median_m"] == pytest.approx(0.2 * L)
    assert sedan["size_bias"]["width"]["mean_rel"] == pytest.approx(-0.1)
    assert sedan["size_bias"]["height"]["mean_m"] == pytest.approx(0.0)
    assert sedan["heading_accuracy"] == pytest.approx(0.5) and sedan["missed_share"] == 0.0
    assert van["missed_share"] == pytest.approx(0.5) and van["n_matched"] == 1
    assert van["size_bias"]["height"]["mean_rel"] == pytest.approx(0.2)
    assert result["pairs"]["all"]["missed_share"] == pytest.approx(0.25)
    assert list(result["breakdown"]["by_distance"]) == ["20-40 m"]  # 20.0-25.0 m away
    assert result["breakdown"]["by_occlusion"] is None and result["breakdown"]["by_parking"] is None


def test_breakdown_bins_by_distance_and_occlusion():
    gt = [car(x=0.0, z=z) for z in (10.0, 30.0, 50.0, 70.0)]
    attrs = [CarAttributes(occlusion=o) for o in (0.0, 0.45, 0.7, 0.95)]
    f = FrameBoxes(frame=0, gt=gt, gt_height=np.full(4, EASY_PX), pred=gt[:3], pred_score=[0.9, 0.8, 0.7],
                   pred_height=np.full(3, EASY_PX), gt_attributes=attrs)
    b = evaluate_frames([f])["breakdown"]
    assert list(b["by_distance"]) == ["0-20 m", "20-40 m", "40-60 m", "60 m+"]
    assert list(b["by_occlusion"]) == ["0-30 %", "30-60 %", "60-80 %", "80 %+"]
    assert [g["missed_share"] for g in b["by_occlusion"].values()] == [0.0, 0.0, 0.0, 1.0]
    assert b["by_distance"]["60 m+"]["n_matched"] == 0 and b["by_distance"]["40-60 m"]["mean_iou_3d"] == pytest.approx(1.0)


# ------------------------------ the mask protocol and the attributes sidecar on the CLI ------------------------------


def _write_instance_maps(root: Path, frames=(0, 1, 2)) -> None:
    """Car 1 (static, Easy) 60 px tall, car 3 (moving) 30 px tall; car 2 is hidden (no pixels)."""
    inst_dir = root / "data_2d_semantics" / "train" / SEQ / "image_00" / "instance"
    inst_dir.mkdir(parents=True)
    for f in frames:
        inst = np.zeros((IMG_H, IMG_W), np.uint16)
        inst[100:161, 100:300] = 26001  # rows 100..160: masks_to_boxes height 60
        inst[120:151, 400:600] = 26003  # rows 120..150: height 30
        cv2.imwrite(str(inst_dir / f"{f:010d}.png"), inst)


def _write_sidecar(root: Path, data: dict) -> Path:
    path = root / "data_3d_bboxes" / "train" / f"{SEQ}.attributes.json"
    path.write_text(json.dumps(data))
    return path


SIDECAR = {"format": ATTRIBUTES_FORMAT,
           "instances": {"26001": {"vehicle_class": "sedan", "dynamic": False, "parking": "angled",
                                   "angle_to_road_deg": 30.0},
                         "26003": {"vehicle_class": "van", "dynamic": True, "parking": None}},
           "frames": {str(f): {"26001": {"occlusion": 0.1, "truncation": 0.0},
                               "26003": {"occlusion": 0.5, "truncation": 0.0}} for f in (0, 1, 2)}}


def test_mask_protocol_takes_ground_truth_from_the_instance_maps(dataset, tmp_path, capsys):
    pred = tmp_path / "pred"
    for f in (0, 1, 2):
        _write_predictions(pred, f, _camera_boxes(f), [0.9, 0.8, 0.7])
    _write_instance_maps(dataset)
    assert main(["eval", "--pred", str(pred), "--gt", str(dataset), "--sequence", "7", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["protocol"]["gt_boxes"] == "mask" and "masks_to_boxes" in result["protocol"]["gt_boxes_rule"]
    # Easy: car 1 only (60 px); car 3's 30 px box is Hard only; car 2 is not ground truth
    assert result["counts"]["easy"]["n_gt"] == 3 and result["counts"]["hard"]["n_gt"] == 6
    assert ap(result, "3d", "0.7", "easy")["R40"] == pytest.approx(100.0)
    # Hard: the prediction of the hidden car 2 (score 0.8, about 30 px) is a false positive
    assert ap(result, "3d", "0.7", "hard")["R40"] == pytest.approx(100.0 * (20 + 20 * 2 / 3) / 40)
    assert result["pairs"]["all"]["n_gt"] == 6 and result["pairs"]["all"]["missed_share"] == 0.0
    assert result["attributes"] is None and result["breakdown"]["by_class"] is None
    # the same predictions under the projection protocol: car 2 is ground truth again
    assert main(["eval", "--pred", str(pred), "--gt", str(dataset), "--sequence", "7", "--json",
                 "--gt-boxes", "projected"]) == 0
    assert ap(json.loads(capsys.readouterr().out), "3d", "0.7", "hard")["R40"] == pytest.approx(100.0)


def test_sidecar_attributes_feed_the_breakdowns(dataset, tmp_path, capsys):
    pred = tmp_path / "pred"
    for f in (0, 1, 2):
        _write_predictions(pred, f, _camera_boxes(f), [0.9, 0.8, 0.7])
    _write_instance_maps(dataset)
    path = _write_sidecar(dataset, SIDECAR)
    result = evaluate_sequence(pred, dataset, 7)
    assert result["attributes"] == str(path)
    b = result["breakdown"]
    assert list(b["by_class"]) == ["sedan", "van"] and b["by_class"]["van"]["n_gt"] == 3
    assert list(b["by_occlusion"]) == ["0-30 %", "30-60 %"]
    assert list(b["by_parking"]) == ["angled"] and b["by_parking"]["angled"]["yaw_error_deg"] == pytest.approx(0.0, abs=1e-3)
    assert main(["eval", "--pred", str(pred), "--gt", str(dataset), "--sequence", "7"]) == 0
    table = capsys.readouterr().out
    assert "By vehicle class:" in table and "sedan" in table and "30-60 %" in table and "angled" in table


@pytest.mark.parametrize("change, problem", [
    ({"format": "other"}, "not a sidecar"),
    ({"instances": {"car": {}}}, "not a non-negative integer"),
    ({"instances": {"26001": {"parking": "diagonal"}}}, "not one of"),
    ({"frames": {"0": {"26001": {"occlusion": 1.5}}}}, "outside"),
    ({"instances": {"26001": {"dynamic": "yes"}}}, "true / false"),
])
def test_bad_sidecar_names_the_file(dataset, change, problem):
    path = _write_sidecar(dataset, {**SIDECAR, **change})
    with pytest.raises(DataError, match=problem) as info:
        read_attributes(dataset, 7)
    assert str(path) in str(info.value)
    path.write_text("{not json")
    with pytest.raises(DataError, match="malformed JSON"):
        read_attributes(dataset, 7)


def test_missing_sidecar_means_no_attributes(dataset):
    assert read_attributes(dataset, 7) is None
    path = _write_sidecar(dataset, SIDECAR)
    attrs = read_attributes(dataset, 7)
    assert attrs.path == path
    assert attrs.lookup(1, 26001) == CarAttributes("sedan", False, "angled", 30.0, 0.1, 0.0)
    assert attrs.lookup(7, 26003) == CarAttributes("van", True, None, None, None, None)
    assert attrs.lookup(0, 26099) == CarAttributes()


def test_far_end_shift_sees_a_passing_car_but_not_the_length_of_one_straight_ahead():
    from vsrd_mi.evaluate.metrics import LENGTH_SEEN_PX
    from vsrd_mi.geometry.camera import LENGTH_PROBE_M, far_end_shift
    size = (IMG_W, IMG_H)
    # straight ahead, the camera inside the strip its sides span and 0.2 m above its top: only
    # the top edge moves, to the far top corners' new image row
    ahead = Box3D(centre=(0.0, 1.0, 15.0), size=(1.8, 1.6, 4.2), yaw=0.0)
    z_far = 15.0 + 2.1
    expected = FX * 0.2 * (1.0 / z_far - 1.0 / (z_far + LENGTH_PROBE_M))
    assert far_end_shift(ahead, K, size) == pytest.approx(expected, rel=1e-6)
    assert far_end_shift(ahead, K, size) < LENGTH_SEEN_PX
    # the same car facing away or towards the camera: the far end is the one moved
    assert far_end_shift(dataclasses.replace(ahead, yaw=math.pi), K, size) == pytest.approx(expected, rel=1e-6)
    # beside the lane: its side's far corner sets the box's right side
    beside = Box3D(centre=(-3.0, 1.0, 12.0), size=(1.8, 1.5, 4.2), yaw=0.0)
    x_side, z_far = -3.0 + 0.9, 12.0 + 2.1
    expected = FX * x_side * (1.0 / (z_far + LENGTH_PROBE_M) - 1.0 / z_far)
    assert far_end_shift(beside, K, size) == pytest.approx(expected, rel=1e-6)
    assert far_end_shift(beside, K, size) > LENGTH_SEEN_PX
    # crossing the view, either way round: the far end is the one farther left, which sets x1
    for yaw in (0.5 * math.pi, -0.5 * math.pi):
        crossing = Box3D(centre=(-3.0, 1.0, 12.0), size=(1.8, 1.5, 4.2), yaw=yaw)
        x_far, z_near = -3.0 - 2.1, 12.0 - 0.9
        expected = FX * (x_far / z_near - (x_far - LENGTH_PROBE_M) / z_near)
        assert far_end_shift(crossing, K, size) == pytest.approx(expected, rel=1e-6)
    # behind the camera: not in the image
    assert far_end_shift(dataclasses.replace(beside, centre=(-3.0, 1.0, -12.0)), K, size) is None
    with pytest.raises(ValueError, match="probe"):
        far_end_shift(beside, K, size, probe=0.0)


def test_far_end_shift_through_a_camera_pose_at_a_time_offset():
    """A moving box in a world frame, seen by a camera 5 m along z and turned by 0.3 rad, 4 frames
    later: the same shift as that box moved by 4 velocities and expressed in the camera frame
    (where the far end is the one farther from that camera, not from the world origin)."""
    from vsrd_mi.geometry.camera import far_end_shift
    size = (IMG_W, IMG_H)
    c, s = math.cos(0.3), math.sin(0.3)
    cam_to_world = np.array([[c, 0.0, s, 1.0], [0.0, 1.0, 0.0, 0.0], [-s, 0.0, c, 5.0], [0.0, 0.0, 0.0, 1.0]])
    world_to_cam = np.linalg.inv(cam_to_world)
    box = Box3D(centre=(2.0, 1.0, 14.0), size=(1.8, 1.5, 4.2), yaw=0.4, velocity=np.array([0.1, 0.0, -0.6]),
                dynamic=True)
    in_camera = box.at_offset(4.0).transformed(world_to_cam)
    expected = far_end_shift(in_camera, K, size)
    assert expected is not None and expected > 1.0
    assert far_end_shift(box, K, size, world_to_cam=world_to_cam, dt=4.0) == pytest.approx(expected, rel=1e-6)
    assert far_end_shift(box, K, size, world_to_cam=world_to_cam) != pytest.approx(expected, rel=1e-3)
    # a camera beyond the box, looking back: the end farther from it is the one nearer the origin
    back = np.array([[-1.0, 0.0, 0.0, 0.5], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 30.0], [0.0, 0.0, 0.0, 1.0]])
    parked = Box3D(centre=(0.0, 1.0, 14.0), size=(1.8, 1.5, 4.2), yaw=0.0)
    seen_back = far_end_shift(parked, K, size, world_to_cam=np.linalg.inv(back))
    assert seen_back == pytest.approx(far_end_shift(parked.transformed(np.linalg.inv(back)), K, size), rel=1e-6)
    origin_end = dataclasses.replace(parked, centre=(0.0, 1.0, 14.25), size=(1.8, 1.5, 4.7))  # +z end moved out
    camera_end = dataclasses.replace(parked, centre=(0.0, 1.0, 13.75), size=(1.8, 1.5, 4.7))  # -z end moved out
    to_back = np.linalg.inv(back)
    moved = {name: np.abs(box_to_2d(b, K, to_back, size) - box_to_2d(parked, K, to_back, size)).max()
             for name, b in (("origin", origin_end), ("camera", camera_end))}
    assert seen_back == pytest.approx(moved["camera"], rel=1e-6)
    assert moved["camera"] != pytest.approx(moved["origin"], rel=1e-2)


def test_length_views_split_the_pairs_by_whether_a_view_sees_the_length(dataset, tmp_path, capsys):
    pred = tmp_path / "pred"
    for f in (0, 1, 2):
        _write_predictions(pred, f, _camera_boxes(f), [0.9, 0.8, 0.7])
    _write_instance_maps(dataset)
    _write_sidecar(dataset, SIDECAR)
    # car 1 stands beside the lane, car 3 drives straight ahead of the camera
    result = evaluate_sequence(pred, dataset, 7, config=EvalConfig(length_views=True))
    b = result["breakdown"]
    assert list(b["by_length_view"]) == ["seen", "not seen"]
    assert b["by_length_view"]["seen"]["n_gt"] == 3 and b["by_length_view"]["not seen"]["n_gt"] == 3
    assert list(b["by_class_length_seen"]) == ["sedan"]
    # three frames are too few for the selection's four sources: each frame counted alone
    assert result["length_views_from_one_frame"] == [0, 1, 2]
    assert evaluate_sequence(pred, dataset, 7)["breakdown"]["by_length_view"] is None
    assert main(["eval", "--pred", str(pred), "--gt", str(dataset), "--sequence", "7", "--length-views"]) == 0
    table = capsys.readouterr().out
    assert "sees its length" in table and "not seen" in table


def test_length_view_shift_searches_the_selected_frames(dataset):
    from vsrd_mi.data.kitti360 import Sequence
    from vsrd_mi.data.selection import SelectionConfig
    from vsrd_mi.evaluate.observability import labelling_frames, length_view_shift
    _write_instance_maps(dataset)
    seq = Sequence(dataset, 7)
    assert labelling_frames(seq, 1) is None  # too few sources for the default selection
    frames = labelling_frames(seq, 1, SelectionConfig(min_sources=2))
    assert frames == [0, 1, 2]
    shifts = length_view_shift(seq, frames, [26001, 26003])
    # the largest shift is the nearest view's: car 1 stands 12 - frame m ahead, 3 m to the left
    x_side = -3.0 + 0.9
    expected = max(FX * x_side * (1.0 / (z + 2.1 + 0.5) - 1.0 / (z + 2.1)) for z in (12.0, 11.0, 10.0))
    assert shifts[26001] == pytest.approx(expected, rel=1e-6)
    assert shifts[26003] < 1.0  # straight ahead in every frame
    with pytest.raises(DataError, match="instance map"):
        labelling_frames(seq, 5)
