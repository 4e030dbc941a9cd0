"""KITTI AP evaluator: analytic cases, a literal devkit port on random scenes, and the CLI."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from vsrd_mi.cli import main
from vsrd_mi.errors import DataError
from vsrd_mi.evaluate.ap import average_precision, devkit_thresholds
from vsrd_mi.evaluate.matching import FrameMatchInput, count_at_threshold
from vsrd_mi.evaluate.metrics import hungarian_pairs, yaw_error_mod_pi
from vsrd_mi.evaluate.sequence import EvalConfig, FrameBoxes, evaluate_frames, evaluate_sequence
from vsrd_mi.export.kitti_labels import label_from_box, write_labels
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


def _devkit_statistics(ov, ig_gt, ig_det, scores, min_overlap, compute_fp, thresh):
    assigned = [False] * len(scores)
    ig_thr = [s < thresh for s in scores]
    tp = fp = fn = 0
    v = []
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
            assigned[det_idx] = True
    if compute_fp:
        fp = sum(1 for j in range(len(scores)) if not (assigned[j] or ig_det[j] or ig_thr[j]))
    return tp, fp, fn, v


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


def _reference_aps(frames, min_overlap):
    n_gt = sum(int(np.sum(~f.gt_ignored)) for f in frames)
    args = [(f.overlap.tolist(), f.gt_ignored.tolist(), f.det_ignored.tolist(), f.scores.tolist())
            for f in frames]
    v = [s for a in args for s in _devkit_statistics(*a, min_overlap, False, 0.0)[3]]

    def totals(t):
        return np.sum([_devkit_statistics(*a, min_overlap, True, t)[:3] for a in args], axis=0)

    # devkit curve
    thresholds = _get_thresholds(v, n_gt)
    prec = [0.0] * 41
    for i, t in enumerate(thresholds):
        tp, fp, _ = totals(t)
        prec[i] = tp / (tp + fp)
    prec = [max(prec[i:]) for i in range(41)]
    devkit = (100 * sum(prec[1:]) / 40, 100 * sum(prec[0::4]) / 11)
    # exact curve, from every distinct score
    points = []
    for t in sorted({s for a in args for s in a[3]}):
        tp, fp, _ = totals(t)
        points.append((tp / n_gt, tp / (tp + fp) if tp + fp else 0.0))
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
    for metric in (0, 1):
        for thr in (0.3, 0.5):
            for min_h in (25.0, 40.0):
                inputs = [FrameMatchInput(overlap=iou_matrices(g, d)[metric], gt_ignored=gh <= min_h,
                                          det_ignored=dh <= min_h, scores=s) for g, d, s, gh, dh in frames]
                res = average_precision(inputs, thr)
                (r40, r11), (d40, d11) = _reference_aps(inputs, thr)
                assert res.r40 == pytest.approx(r40, abs=1e-9)
                assert res.r11 == pytest.approx(r11, abs=1e-9)
                assert res.devkit_r40 == pytest.approx(d40, abs=1e-9)
                assert res.devkit_r11 == pytest.approx(d11, abs=1e-9)


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
    assert main(["eval", "--pred", str(pred), "--gt", str(dataset), "--sequence", "7", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["sequence"] == SEQ and result["frames"] == [0, 1, 2]
    assert result["counts"]["easy"]["n_gt"] == 6 and result["counts"]["hard"]["n_gt"] == 9
    for key in ("R40", "R11"):
        assert all_ap_values(result, key) == pytest.approx([100.0] * 12, abs=1e-6)
    assert result["pairs"]["dynamic"]["n_gt"] == 3
    assert result["pairs"]["dynamic"]["mean_iou_3d"] == pytest.approx(1.0, abs=1e-5)
    assert result["protocol"]["headline_curve"] == "exact"
    assert main(["eval", "--pred", str(pred), "--gt", str(dataset), "--sequence", SEQ]) == 0
    table = capsys.readouterr().out
    assert "AP_BEV@0.3" in table and "AP_3D@0.5" in table and "100.00" in table and "dynamic" in table


def test_cli_nested_layout_frames_and_misses(dataset, tmp_path, capsys):
    labels = tmp_path / "out" / SEQ / "labels"
    boxes = _camera_boxes(0)
    moved = [boxes[0], boxes[1], Box3D(centre=boxes[2].centre + (0, 0, 0.45 * 4.6), size=boxes[2].size,
                                       yaw=0.0, dynamic=True)]
    _write_predictions(labels, 0, moved, [0.9, 0.8, 0.7])
    _write_predictions(labels, 2, _camera_boxes(2), [0.9, 0.8, 0.7])
    # frames 0-1: frame 1 has no file and counts as all missed; frame 2 is not selected
    assert main(["eval", "--pred", str(tmp_path / "out"), "--gt", str(dataset), "--sequence", "7",
                 "--frames", "0-1", "--json"]) == 0
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
    result = evaluate_sequence(tmp_path / "out", dataset, SEQ)
    assert result["frames"] == [0, 2] and result["frames_without_predictions"] == []


def test_visible_only_keeps_ground_truth_present_in_the_instance_map(dataset, tmp_path, capsys):
    pred = tmp_path / "pred"
    _write_predictions(pred, 0, _camera_boxes(0)[::2], [0.9, 0.7])  # the hard-only car not labelled
    args = ["eval", "--pred", str(pred), "--gt", str(dataset), "--sequence", "7", "--json"]
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
    assert main(["eval", "--pred", str(pred), "--gt", str(dataset), "--sequence", "7"]) == 1
    err = capsys.readouterr().err
    assert "0000000001.txt" in err and "line 1" in err
    (pred / "0000000001.txt").write_text("Car 0 0 0 1 2 3 40 1.5 1.8 4.2 0 1 10 0.1\n")
    with pytest.raises(DataError, match="no score"):
        evaluate_sequence(pred, dataset, 7)
    assert evaluate_sequence(pred, dataset, 7, config=EvalConfig(default_score=1.0))["frames"] == [1]
    (pred / "0000000009.txt").write_text("")
    with pytest.raises(DataError, match="not a frame"):
        evaluate_sequence(pred, dataset, 7, config=EvalConfig(default_score=1.0))
    with pytest.raises(DataError, match="not frames"):
        evaluate_sequence(pred, dataset, 7, frames=[1, 5])
    with pytest.raises(SystemExit):
        main(["eval", "--pred", str(pred), "--gt", str(dataset), "--sequence", "7", "--frames", "5-2"])
