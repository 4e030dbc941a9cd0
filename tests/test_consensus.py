"""Sequence-level consensus of parked cars (vsrd_mi.autolabel.consensus).

The target results are built from the bundled scene's ground truth: every parked car's box is
perturbed per target by offsets that cancel (+d, -d, 0, ...), so the fused box must be the ground
truth itself -- an independent check of the frame chain (target optimisation frames -> reference
frame -> every group frame's camera) and of the median / mean-axis fusion.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import vsrd_mi  # noqa: F401
from vsrd_mi.autolabel.consensus import (
    TargetBoxes,
    apply_consensus,
    axis_inliers,
    axis_mean,
    crossed,
    fuse_boxes,
    fuse_parked_cars,
    labels_in_frame,
    weighted_median,
)
from vsrd_mi.data.kitti360 import Sequence
from vsrd_mi.data.kitti_labels import (
    box_from_label,
    parse_label_line,
    read_labels,
    write_labels,
)
from vsrd_mi.data.observations import opt_from_world
from vsrd_mi.data.selection import SelectionConfig, select_targets
from vsrd_mi.geometry.boxes import Box3D, axis_difference
from vsrd_mi.optimise.config import (
    AutolabelConfig,
    ConsensusConfig,
    default_config,
    paper_config,
)

ROOT = Path(__file__).resolve().parents[1] / "scenes" / "kitti360-synth"
#: Per-target perturbations of parked cars, cycled; every pair / triple of consecutive ones cancels
#: in the median and the mean axis (see ``cancelling``).
SHIFT_M, YAW_RAD, SCALE = 0.4, 0.15, 0.08


def cancelling(k: int, n: int) -> float:
    """Signed unit offset of the k-th of n contributors: +1, -1 (n even) or +1, -1, 0 (n odd)."""
    if n % 2 and k == n - 1:
        return 0.0
    return 1.0 if k % 2 == 0 else -1.0


@pytest.fixture(scope="module")
def scene():
    seq = Sequence(ROOT, 0)
    specs = select_targets(seq, SelectionConfig())
    assert len(specs) >= 3
    return seq, specs


def write_results(seq, specs, out: Path, moved: dict[tuple[int, int], float] | None = None) -> dict:
    """Write ``boxes/%010d.json`` and the targets' own labels as :func:`process_target` does."""
    seq_dir = out / seq.name
    counts: dict[int, int] = {}
    for spec in specs:
        for iid in spec.instance_ids:
            counts[iid] = counts.get(iid, 0) + 1
    seen: dict[int, int] = {}
    gt_world = {}
    for spec in specs:
        t = spec.target
        T_opt = opt_from_world(seq.cam0_to_world(t))
        cam_to_opt = T_opt @ seq.cam0_to_world(t)
        gt = {b.instance_id: b for b in seq.ground_truth(t)}
        boxes = []
        for iid in spec.instance_ids:
            b = gt[iid].transformed(cam_to_opt)
            if not b.dynamic:
                k = seen.get(iid, 0)
                seen[iid] = k + 1
                u = cancelling(k, counts[iid])
                shift = np.array([SHIFT_M * u + (moved or {}).get((t, iid), 0.0), 0.0, -SHIFT_M * u])
                b = replace(b, centre=b.centre + shift, yaw=b.yaw + YAW_RAD * u + (math.pi if k == 1 else 0.0),
                            size=b.size * (1 + SCALE * u))
                gt_world.setdefault(iid, gt[iid])
            boxes.append(b)
        conf = [0.5] * len(boxes)
        for f in (t, *[g for g in spec.group if g != t]):
            write_labels(seq_dir / f"labels/{f:010d}.txt",
                         labels_in_frame(boxes, conf, T_opt @ seq.cam0_to_world(f), seq.calibration.K,
                                         seq.calibration.image_size, float(f - t)))
        (seq_dir / "boxes").mkdir(parents=True, exist_ok=True)
        (seq_dir / f"boxes/{t:010d}.json").write_text(json.dumps({
            "target": t, "group": sorted({t, *spec.group}),
            "boxes": [{**b.to_dict(), "confidence": c} for b, c in zip(boxes, conf)]}))
    return {iid: n for iid, n in counts.items()}


def label_texts(seq_dir: Path) -> dict[str, str]:
    return {p.name: p.read_text() for p in sorted((seq_dir / "labels").glob("*.txt"))}


def test_axis_mean_has_period_pi():
    assert axis_mean(np.array([0.1, 0.1 + math.pi])) == pytest.approx(0.1)
    assert axis_mean(np.array([0.2, 0.0, math.pi - 0.1])) == pytest.approx(0.1 / 3, abs=1e-3)
    # across the +-pi/2 seam, turned to the first heading
    assert axis_mean(np.array([math.pi / 2 - 0.05, -math.pi / 2 + 0.05])) == pytest.approx(math.pi / 2)
    assert axis_mean(np.array([-math.pi / 2 + 0.05, math.pi / 2 - 0.05])) == pytest.approx(-math.pi / 2)


def test_fuse_boxes_median_gate_and_too_few():
    a = Box3D([0.0, 1.0, 10.0], [1.8, 1.5, 4.0], 0.1, instance_id=26001)
    b = Box3D([0.4, 1.0, 10.2], [2.0, 1.5, 4.4], 0.3, instance_id=26001)
    c = Box3D([0.2, 1.0, 10.6], [1.6, 1.6, 4.2], 0.2 + math.pi, instance_id=26001)
    far = Box3D([5.0, 1.0, 10.0], [1.8, 1.5, 4.0], 1.0, instance_id=26001)
    box, inliers = fuse_boxes([a, b, c, far], gate=2.0)
    assert inliers.tolist() == [True, True, True, False]
    np.testing.assert_allclose(box.centre, [0.2, 1.0, 10.2])
    np.testing.assert_allclose(box.size, [1.8, 1.5, 4.2])
    assert box.yaw == pytest.approx(0.2, abs=1e-3) and not box.dynamic and box.instance_id == 26001
    assert fuse_boxes([a, far], gate=2.0) is None  # the median is between them: no two inliers


def test_consensus_fuses_parked_cars_to_the_ground_truth(scene, tmp_path):
    seq, specs = scene
    counts = write_results(seq, specs, tmp_path)
    seq_dir = tmp_path / seq.name
    before = label_texts(seq_dir)
    # equal weights (every car nearer than near_range): the perturbations cancel in the median
    report = apply_consensus(seq_dir, seq, ConsensusConfig(near_range=1e3))
    assert report["fused"] and report == apply_consensus(seq_dir, seq, ConsensusConfig(near_range=1e3))
    fused = {c["instance_id"]: c for c in report["fused"]}
    parked_multi = {iid for iid, n in counts.items() if n >= 2 and not any(
        b.dynamic for b in seq.ground_truth(specs[0].target) if b.instance_id == iid)}
    assert parked_multi and parked_multi <= set(fused)
    for c in fused.values():
        assert c["spread_m"] < 0.8 and 0.5 < c["confidence"] <= 1.0 and not c["outliers"]
    assert json.loads((seq_dir / "consensus.json").read_text())["fused"] == report["fused"]
    # every label of a fused car is its ground truth in that frame; the rest are unchanged
    checked = 0
    for spec in specs:
        for f in sorted({spec.target, *spec.group}):
            gt = [b for b in seq.ground_truth(f) if b.instance_id in spec.instance_ids]
            for lab in read_labels(seq_dir / f"labels/{f:010d}.txt"):
                box = box_from_label(lab)
                g = min(gt, key=lambda b: np.linalg.norm(b.centre - box.centre))
                if g.instance_id in fused and spec.target in fused[g.instance_id]["targets"]:
                    np.testing.assert_allclose(box.centre, g.centre, atol=0.02)
                    np.testing.assert_allclose(box.size, g.size, atol=0.02)
                    assert abs(math.sin(box.yaw - g.yaw)) < 0.01
                    assert lab.score == pytest.approx(fused[g.instance_id]["confidence"], abs=0.01)
                    checked += 1
    assert checked >= 10
    after = label_texts(seq_dir)
    assert after.keys() == before.keys() and after != before
    # the moving cars' lines are unchanged
    moving = 0
    for name, text in before.items():
        gt = seq.ground_truth(int(name[:10]))
        for line in text.splitlines():
            box = box_from_label(parse_label_line(line))
            if min(gt, key=lambda b: np.linalg.norm(b.centre - box.centre)).dynamic:
                assert line in after[name].splitlines()
                moving += 1
    assert moving >= 5


def test_consensus_off_restores_the_targets_labels(scene, tmp_path):
    seq, specs = scene
    write_results(seq, specs, tmp_path)
    seq_dir = tmp_path / seq.name
    before = label_texts(seq_dir)
    apply_consensus(seq_dir, seq, ConsensusConfig())
    assert label_texts(seq_dir) != before
    report = apply_consensus(seq_dir, seq, replace(ConsensusConfig(), enabled=False))
    assert report["fused"] == [] and report["labels_rewritten"]
    assert label_texts(seq_dir) == before
    # nothing fused before: nothing rewritten
    assert apply_consensus(seq_dir, seq, replace(ConsensusConfig(), enabled=False))["labels_rewritten"] == []


def test_consensus_gate_and_damaged_results(scene, tmp_path):
    seq, specs = scene
    t0 = specs[0].target
    kept = specs[:-1]  # the last target's result is damaged below
    parked = [b.instance_id for b in seq.ground_truth(t0) if not b.dynamic and b.instance_id in specs[0].instance_ids
              and sum(b.instance_id in s.instance_ids for s in kept) >= 3]
    assert parked
    moved = {(t0, parked[0]): 6.0}  # this target's box of one car is 6 m off
    write_results(seq, specs, tmp_path, moved=moved)
    seq_dir = tmp_path / seq.name
    bad = seq_dir / f"boxes/{specs[-1].target:010d}.json"
    bad.write_text('{"target": 1, "boxes": [')
    report = apply_consensus(seq_dir, seq, ConsensusConfig())
    assert len(report["skipped"]) == 1 and str(bad) in report["skipped"][0] and "unreadable" in report["skipped"][0]
    assert specs[-1].target not in report["targets"]
    car = next(c for c in report["fused"] if c["instance_id"] == parked[0])
    assert t0 in car["outliers"] and t0 not in car["targets"]


def test_consensus_config():
    assert default_config().consensus.enabled and paper_config().consensus.enabled
    cfg = default_config().with_overrides(["consensus.enabled=false", "consensus.gate=1.5"])
    assert not cfg.consensus.enabled and cfg.consensus.gate == 1.5
    assert AutolabelConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ValueError, match="min_targets"):
        ConsensusConfig(min_targets=1)
    for bad in (0.0, 95.0):
        with pytest.raises(ValueError, match="axis_gate_deg must be in"):
            ConsensusConfig(axis_gate_deg=bad)


def test_axis_difference_has_period_pi():
    np.testing.assert_allclose(axis_difference(np.array([0.1, 0.1, 0.0]), np.array([0.1 + math.pi, -0.1, math.pi / 2])),
                               [0.0, 0.2, math.pi / 2], atol=1e-12)
    assert axis_difference(math.pi / 2 - 0.05, -math.pi / 2 + 0.05) == pytest.approx(0.1)


def test_axis_inliers_keep_the_axis_most_weight_agrees_with():
    gate = math.radians(30)
    # two along the road (one end for end), one across: the crossed one is out
    assert axis_inliers(np.array([0.05, math.pi - 0.1, 1.6]), np.ones(3), gate).tolist() == [True, True, False]
    # the one across weighs more than the two together: it alone is kept
    assert axis_inliers(np.array([0.05, -0.1, 1.6]), np.array([1.0, 1.0, 3.0]), gate).tolist() == [False, False, True]
    # two that disagree: the heavier; equal weights: the first
    assert axis_inliers(np.array([0.0, 1.5]), np.array([1.0, 2.0]), gate).tolist() == [False, True]
    assert axis_inliers(np.array([0.0, 1.5]), np.ones(2), gate).tolist() == [True, False]


def test_crossed_boxes_are_not_averaged_into_a_diagonal():
    """Two targets' boxes of one car, one standing across it: the fused box is the more
    confident one (yaw, size and centre), not the 45-degree mean, and it replaces both."""
    right = Box3D([3.0, 0.8, 18.0], [2.1, 1.7, 4.8], 0.01, instance_id=7)
    across = Box3D([3.4, 0.8, 17.6], [2.0, 1.5, 4.4], 0.01 + math.pi / 2 + 0.15, instance_id=7)
    for conf, winner in (((0.8, 0.6), right), ((0.5, 0.7), across)):
        fused, inliers = fuse_boxes([right, across], gate=2.0, weights=np.ones(2), axis_gate_deg=30.0,
                                    confidences=np.array(conf))
        assert inliers.tolist() == [True, True]
        assert axis_difference(fused.yaw, winner.yaw) < 1e-9
        np.testing.assert_allclose(fused.size, winner.size)
        np.testing.assert_allclose(fused.centre, winner.centre)
    # without the gate (90 degrees) the two are averaged, as before the gate existed
    mean, _ = fuse_boxes([right, across], gate=2.0, axis_gate_deg=90.0, confidences=np.array([0.8, 0.6]))
    assert math.radians(40) < axis_difference(mean.yaw, right.yaw) < math.radians(50)
    # of three boxes the one across is left out of the fusion but still gets the fused box
    third = Box3D([3.2, 0.8, 18.2], [2.2, 1.7, 5.0], -0.03, instance_id=7)
    fused, inliers = fuse_boxes([right, across, third], gate=2.0, axis_gate_deg=30.0)
    assert inliers.tolist() == [True, True, True]
    assert axis_difference(fused.yaw, 0.0) < math.radians(2)
    np.testing.assert_allclose(fused.size, [2.15, 1.7, 4.9])


def test_crossed_boxes_are_judged_on_the_same_frames():
    """A target that saw a car end-on from 12 m turned its box across the car; one that saw it
    from 18 m did not. Each target's own confidence is over its own frames, and the nearer one
    weighs more, so it won; scored again over both targets' frames (``rescore``), the box that
    matches more of the car's masks wins, whatever its range. Boxes that agree are not rescored."""
    right = Box3D([3.0, 0.8, 18.0], [2.1, 1.7, 4.8], 0.01, instance_id=7)
    across = Box3D([3.2, 0.8, 11.8], [2.0, 1.5, 4.4], 0.01 + math.pi / 2, instance_id=7)
    results = [TargetBoxes(0, (0, 1, 2), (right,), (0.80,)), TargetBoxes(5, (4, 5, 6), (across,), (0.80,))]
    ident = {0: np.eye(4), 5: np.eye(4)}
    cfg = ConsensusConfig(gate=7.0)
    calls = []

    def rescore(boxes, targets):
        calls.append(sorted(targets))
        return np.array([0.75 if abs(b.yaw - right.yaw) < 0.1 else 0.60 for b in boxes])

    (own,) = fuse_parked_cars(results, ident, cfg)
    assert axis_difference(own.box.yaw, across.yaw) < 1e-9       # the nearer box's say
    (fused,) = fuse_parked_cars(results, ident, cfg, rescore=rescore)
    assert calls == [[0, 5]] and axis_difference(fused.box.yaw, right.yaw) < 1e-9
    np.testing.assert_allclose(fused.box.size, right.size)
    agree = [results[0], TargetBoxes(5, (4, 5, 6), (replace(across, yaw=0.05),), (0.7,))]
    fuse_parked_cars(agree, ident, cfg, rescore=rescore)
    assert calls == [[0, 5]]
    assert crossed(np.array([0.0, math.pi - 0.1]), 30.0) is False
    assert crossed(np.array([0.0, 0.2, 1.2]), 30.0) is True


def test_autolabel_cli_applies_the_consensus_after_its_targets(scene, tmp_path, monkeypatch, capsys):
    """``vsrd-mi autolabel`` runs the consensus after the batch (the batch itself replaced by
    writing the ground-truth-derived results); the per-target tasks do not carry its settings,
    so changing them reruns no target."""
    from vsrd_mi.autolabel import cli as autolabel_cli
    from vsrd_mi.batch.runner import BatchSummary
    from vsrd_mi.cli import main

    seq, specs = scene
    seen_tasks = []

    def fake_batch(tasks, process, **kwargs):
        seen_tasks.extend(tasks)
        write_results(seq, specs, tmp_path)
        return BatchSummary(done=len(tasks))

    monkeypatch.setattr(autolabel_cli, "run_batch", fake_batch)
    assert main(["autolabel", str(ROOT), "--sequence", "0", "--out", str(tmp_path), "--no-progress",
                 "--set", "consensus.gate=1.5"]) == 0
    assert seen_tasks and all("consensus" not in t.config for t in seen_tasks)
    report = json.loads((tmp_path / seq.name / "consensus.json").read_text())
    assert report["config"]["gate"] == 1.5 and report["fused"]
    assert f"consensus: {len(report['fused'])} parked car(s) fused over {len(specs)} target(s)" in capsys.readouterr().out


def test_autolabel_cli_keeps_the_targets_labels_when_the_consensus_fails(scene, tmp_path, monkeypatch, capsys):
    """A consensus that cannot read its input is a warning: the batch's labels stay, exit code 0."""
    from vsrd_mi.autolabel import cli as autolabel_cli
    from vsrd_mi.batch.runner import BatchSummary
    from vsrd_mi.cli import main
    from vsrd_mi.errors import DataError

    seq, specs = scene

    def fake_batch(tasks, process, **kwargs):
        write_results(seq, specs, tmp_path)
        return BatchSummary(done=len(tasks))

    def broken(seq_dir, *args):
        raise DataError(Path(seq_dir) / "poses.txt", "NaN in the pose of frame 3")

    monkeypatch.setattr(autolabel_cli, "run_batch", fake_batch)
    monkeypatch.setattr(autolabel_cli, "apply_consensus", broken)
    assert main(["autolabel", str(ROOT), "--sequence", "0", "--out", str(tmp_path), "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert "consensus of parked cars skipped" in err and "NaN in the pose of frame 3" in err
    assert label_texts(tmp_path / seq.name) and not (tmp_path / seq.name / "consensus.json").exists()


def test_closer_views_weigh_more_in_the_fused_box():
    """Three boxes of one car seen from 12, 40 and 45 m: the near one's yaw, size and centre win."""
    near = Box3D(centre=(3.0, 1.0, 12.0), size=(1.8, 1.5, 4.4), yaw=0.5)
    far = [Box3D(centre=(3.3, 1.0, 12.2 + 0.1 * k), size=(1.7, 1.4, 3.9), yaw=0.1) for k in range(2)]
    weights = np.array([1 / 12.0 ** 2, 1 / 40.0 ** 2, 1 / 45.0 ** 2])
    fused, inliers = fuse_boxes([near, *far], gate=2.0, weights=weights)
    assert inliers.all()
    np.testing.assert_allclose(fused.centre, near.centre)
    np.testing.assert_allclose(fused.size, near.size)
    assert 0.42 < fused.yaw < 0.5   # the weighted axis mean (0.448), close to the near box's
    equal, _ = fuse_boxes([near, *far], gate=2.0)
    np.testing.assert_allclose(equal.size, far[0].size)   # unweighted: the far majority
    for n in (3, 4):
        vals = np.random.default_rng(n).normal(size=(n, 3))
        np.testing.assert_allclose(weighted_median(vals, np.ones(n)), np.median(vals, axis=0))


def test_consensus_keeps_the_batch_manifest_true_to_the_labels_it_rewrites(scene, tmp_path):
    """The consensus rewrites label files the targets wrote; the manifest records them anew, so
    that rerunning the batch on the same output skips every finished target."""
    from vsrd_mi.batch.manifest import Manifest, default_output_checks
    from vsrd_mi.batch.tasks import TargetResult, TargetTask

    seq, specs = scene
    write_results(seq, specs, tmp_path)
    seq_dir, checks = tmp_path / seq.name, default_output_checks()
    tasks = [TargetTask(root=str(ROOT), sequence=seq.name, frame=s.target, output_dir=str(tmp_path),
                        config={}, seed=0) for s in specs]
    with Manifest(seq_dir, seq.name) as manifest:
        for task, spec in zip(tasks, specs):
            outputs = (f"boxes/{spec.target:010d}.json",
                       *(f"labels/{f:010d}.txt" for f in sorted({spec.target, *spec.group})))
            manifest.record(task, TargetResult(status="done", outputs=outputs), checks)
    report = apply_consensus(seq_dir, seq, ConsensusConfig(near_range=1e3))
    assert report["labels_rewritten"]
    with Manifest(seq_dir, seq.name) as manifest:
        assert all(manifest.is_finished(t, checks) for t in tasks)
        # a file changed by anything else still makes its target run again
        (seq_dir / report["labels_rewritten"][0]).write_text("Car 0 0 0 0 0 0 0 1 1 1 0 0 0 0\n")
        assert not all(manifest.is_finished(t, checks) for t in tasks)
