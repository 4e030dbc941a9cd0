"""KITTI-360 readers: the real sample, and tiny hand-made datasets with known answers.

``make_dataset`` (also used by the other data-layer tests) writes a small KITTI-360 tree: a camera
driving along world +x at ``SPEED`` m per frame, cars painted as rectangles into the instance maps,
and optionally a 3D-box XML.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from vsrd_mi.data import kitti360_write as kw
from vsrd_mi.data.kitti360 import (CAR_KITTI_ID, Sequence, boxes_in_camera, read_calibration,
                                   read_cam0_to_world, read_world_boxes, sequence_name)
from vsrd_mi.data.masks import car_masks, soft_weight, tight_box, valid_car_ids
from vsrd_mi.data.observations import gravity_rotation, opt_from_world

REAL = Path("/work/shared/data/kitti360-real-0000")
SEQ = sequence_name(0)
W, H = 160, 96
K = np.array([[100.0, 0.0, 80.3], [0.0, 100.0, 47.7], [0.0, 0.0, 1.0]])
SPEED = 0.8

#: OpenCV camera axes expressed in a z-up world for a camera looking along world +x:
#: camera x = -world y, camera y = -world z, camera z = world x.
CAM_AXES = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def camera_pose(frame: int, pitch: float = 0.0) -> np.ndarray:
    """cam0_to_world of ``frame``: at ``(SPEED * frame, 0, 1.6)``, pitched down by ``pitch`` rad."""
    T = np.eye(4)
    c, s = np.cos(pitch), np.sin(pitch)
    pitch_cam = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])  # about camera x
    T[:3, :3] = CAM_AXES @ pitch_cam
    T[:3, 3] = (SPEED * frame, 0.0, 1.6)
    return T


def paint(boxes: dict[int, tuple[int, int, int, int]]) -> np.ndarray:
    """uint16 instance map with road (7) background and a rectangle per car value (x0, y0, x1, y1 incl.)."""
    m = np.full((H, W), 7, dtype=np.uint16)
    for value, (x0, y0, x1, y1) in boxes.items():
        m[y0:y1 + 1, x0:x1 + 1] = value
    return m


def make_dataset(root: Path, frames: list[int], layout: dict[int, dict[int, tuple]] | None = None,
                 world_boxes=None, pitch: float = 0.0) -> Path:
    """Write a tiny KITTI-360 tree below ``root``; ``layout[frame]`` = {car value: rectangle}."""
    kw.write_calibration(root, K, (W, H), baseline=0.6)
    kw.write_cam0_to_world(root, SEQ, {f: camera_pose(f, pitch) for f in frames})
    rng = np.random.default_rng(0)
    for f in frames:
        kw.write_image(root, SEQ, f, rng.integers(0, 255, (H, W, 3), dtype=np.uint8), camera=0)
        kw.write_image(root, SEQ, f, rng.integers(0, 255, (H, W, 3), dtype=np.uint8), camera=1)
        if layout is not None and f in layout:
            kw.write_instance_map(root, SEQ, f, paint(layout[f]))
    if world_boxes is not None:
        kw.write_boxes_xml(root, SEQ, world_boxes)
    return root


# ------------------------------------------------------------------------------------------------
# Real sample
# ------------------------------------------------------------------------------------------------

real = pytest.mark.skipif(not REAL.is_dir(), reason="shared real KITTI-360 sample not present")


@real
def test_real_sample_cameras_poses_stereo():
    seq = Sequence(REAL, 0)
    assert seq.name == "2013_05_28_drive_0000_sync"
    assert seq.frames == [700, 701, 702, 703, 704]
    assert not seq.has_masks and not seq.has_boxes
    cal = seq.calibration
    assert cal.image_size == (1408, 376)
    assert cal.baseline == pytest.approx(0.594, abs=1e-3)
    assert np.allclose(cal.K, [[552.554261, 0, 682.049453], [0, 552.554261, 238.769549], [0, 0, 1]], atol=1e-3)
    assert cal.T_cam0_to_pose is None
    left, right = seq.image(700), seq.image(700, camera=1)
    assert left.shape == right.shape == (376, 1408, 3) and left.dtype == np.uint8
    assert not np.array_equal(left, right)
    centres = np.array([seq.cam0_to_world(f)[:3, 3] for f in seq.frames])
    steps = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    assert np.all(np.abs(steps - 0.85) < 0.05), steps


@real
def test_real_sample_optimisation_frame_is_gravity_aligned():
    seq = Sequence(REAL, 0)
    for f in seq.frames:
        T_world = seq.cam0_to_world(f)
        T = opt_from_world(T_world)
        up = T[:3, :3] @ np.array([0.0, 0.0, 1.0])
        assert abs(up[2]) < 1e-5 and up[1] < -0.99  # world z maps to -y (roll kept: small x part)
        # the target camera centre is the origin, and the rotation is only about camera x
        assert np.allclose(T @ T_world[:, 3], [0, 0, 0, 1], atol=1e-9)
        Rx = T[:3, :3] @ T_world[:3, :3]
        assert np.allclose(Rx[0], [1, 0, 0], atol=1e-6) and np.allclose(Rx[:, 0], [1, 0, 0], atol=1e-6)
        # the real camera is pitched by a few degrees: the rotation is not the identity
        assert np.degrees(np.arccos(np.clip(Rx[1, 1], -1, 1))) > 1.0


# ------------------------------------------------------------------------------------------------
# Synthetic layouts
# ------------------------------------------------------------------------------------------------


def test_sequence_name():
    assert sequence_name(3) == "2013_05_28_drive_0003_sync"
    assert sequence_name("10") == "2013_05_28_drive_0010_sync"
    assert sequence_name("my_clip") == "my_clip"


def test_full_kitti360_calibration_file_with_text_entries(tmp_path):
    """Full KITTI-360 calibration files also hold non-numeric entries such as calib_time."""
    kw.write_calibration(tmp_path, K, (W, H), baseline=0.6)
    path = tmp_path / "calibration" / "perspective.txt"
    path.write_text("calib_time: 09-Jan-2013 15:40:52\ncorner_dist: 9.95e-02\n" + path.read_text())
    cal = read_calibration(tmp_path)
    assert np.allclose(cal.K, K) and cal.image_size == (W, H) and cal.baseline == pytest.approx(0.6)


def test_gravity_rotation_removes_known_pitch():
    for pitch in (-0.2, 0.0, 0.05, 0.3):
        Rx = gravity_rotation(camera_pose(0, pitch))
        # the camera was pitched by ``pitch`` about its x axis: Rx must undo exactly that
        c, s = np.cos(pitch), np.sin(pitch)
        assert np.allclose(Rx, np.array([[1, 0, 0], [0, c, -s], [0, s, c]]), atol=1e-12)


def test_instance_maps_masks_and_boxes(tmp_path):
    layout = {0: {26001: (10, 20, 39, 49), 26002: (60, 30, 64, 34), 24003: (100, 10, 120, 30),
                  26000: (130, 60, 140, 70)}}
    seq = Sequence(make_dataset(tmp_path, [0, 1], layout), SEQ)
    assert seq.has_masks and seq.mask_frames == [0]
    m = seq.instance_map(0)
    assert m.dtype == np.uint16 and m.shape == (H, W)
    cars = seq.car_instances(0)
    assert sorted(cars) == [26001, 26002]  # 24003 is a person, 26000 is no instance
    assert cars[26001].sum() == 30 * 30
    assert np.allclose(tight_box(cars[26001]), [9.5, 19.5, 39.5, 49.5])
    assert valid_car_ids(m, 128, 16) == {26001}  # the 5x5 car is filtered out
    assert valid_car_ids(m, 25, 5) == {26001, 26002}
    assert valid_car_ids(m, 25, 6) == {26001}


def test_soft_weight_signed_distance():
    masks = np.zeros((2, 40, 60), dtype=bool)
    masks[0, 10:20, 10:30] = True
    w = soft_weight(masks, scale=10.0)
    sig = lambda x: 1 / (1 + np.exp(-x / 10.0))  # noqa: E731
    assert w[15, 5] == pytest.approx(sig(-4.5), abs=1e-4)  # 5 px left of the first column
    assert w[10, 20] == pytest.approx(sig(0.5), abs=1e-4)  # on the top row, inside
    assert w[14, 20] == pytest.approx(sig(4.5), abs=1e-4)  # 4.5 px inside the top edge
    # diagonally: centre-to-centre distance minus half a pixel (0.2 px beyond the true corner distance)
    assert w[0, 0] == pytest.approx(sig(-(np.hypot(10, 10) - 0.5)), abs=1e-4)
    # the absent second instance adds nothing; with both present the max wins
    masks[1, 10:20, 34:50] = True
    w2 = soft_weight(masks, scale=10.0)
    assert w2[15, 32] == pytest.approx(sig(-1.5), abs=1e-4)  # 3 px from the first mask, 2 from the second
    assert np.all(w2 >= w - 1e-7)
    assert np.all(soft_weight(np.zeros((1, 5, 5), bool)) == 0.0)


def test_poses_from_imu_file(tmp_path):
    """poses.txt (IMU -> world) is converted with calib_cam_to_pose and R_rect where cam0_to_world lacks a frame."""
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=3), rng.normal(size=3)
    R_rect = _rotation(a * 0.01)
    T_c2p = np.eye(4)
    T_c2p[:3, :3], T_c2p[:3, 3] = _rotation(b), (1.5, 0.2, -0.3)
    kw.write_calibration(tmp_path, K, (W, H), 0.6, R_rect_00=R_rect, T_cam0_to_pose=T_c2p)
    imu = {f: camera_pose(f) for f in (3, 4, 5)}
    kw.write_imu_poses(tmp_path, SEQ, imu)
    kw.write_cam0_to_world(tmp_path, SEQ, {5: np.eye(4)})
    poses = read_cam0_to_world(tmp_path, SEQ)
    assert sorted(poses) == [3, 4, 5]
    assert np.allclose(poses[5], np.eye(4))  # cam0_to_world.txt wins where it lists the frame
    R4 = np.eye(4)
    R4[:3, :3] = R_rect
    # independent reference: rectified cam -> unrectified cam -> IMU -> world, applied to a point
    p_rect = np.array([0.3, -0.2, 4.0, 1.0])
    p_world = imu[3] @ (T_c2p @ (R4.T @ p_rect))
    assert np.allclose(poses[3] @ p_rect, p_world)
    assert read_calibration(tmp_path).T_cam0_to_pose is not None


def _rotation(w: np.ndarray) -> np.ndarray:
    """Rodrigues rotation of axis-angle ``w``."""
    t = np.linalg.norm(w)
    k = w / t
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(t) * Kx + (1 - np.cos(t)) * Kx @ Kx


def test_ground_truth_boxes_in_camera(tmp_path):
    static = kw.world_box(7, CAR_KITTI_ID, centre=(10.0, 2.0, 0.75), size_lwh=(4.2, 1.8, 1.5),
                          heading_yaw=np.pi / 2, start_frame=0, end_frame=3)
    truck = kw.world_box(8, 14, centre=(20.0, -3.0, 1.5), size_lwh=(8.0, 2.5, 3.0),
                         heading_yaw=0.0, start_frame=0, end_frame=5)
    moving = [kw.world_box(9, CAR_KITTI_ID, centre=(12.0 + 0.5 * f, -2.0, 0.7), size_lwh=(4.0, 1.7, 1.4),
                           heading_yaw=0.0, start_frame=0, end_frame=5, timestamp=f) for f in (0, 1, 2, 4)]
    seq = Sequence(make_dataset(tmp_path, [0, 1, 2, 3, 4, 5], world_boxes=[static, truck, *moving]), SEQ)
    assert seq.has_boxes

    gt1 = {b.instance_id: b for b in seq.ground_truth(1)}
    assert sorted(gt1) == [26007, 26009]  # the truck is not a car
    s = gt1[26007]
    # camera at x = 0.8 looking along +x: world (10, 2, 0.75) -> camera (-2, 1.6 - 0.75, 9.2)
    assert np.allclose(s.centre, [-2.0, 0.85, 10.0 - SPEED])
    assert np.allclose(s.size, [1.8, 1.5, 4.2])
    assert abs(abs(s.yaw) - np.pi / 2) < 1e-9  # length along world y = camera -x
    assert not s.dynamic and np.allclose(s.velocity, 0)
    # corners agree with the XML template transformed to the camera (independent of our yaw convention)
    T = np.linalg.inv(camera_pose(1)) @ static.transform
    ref = kw.UNIT_VERTICES @ T[:3, :3].T + T[:3, 3]
    assert np.allclose(np.sort(s.corners(), axis=0), np.sort(ref, axis=0))
    assert {tuple(np.round(c, 9)) for c in s.corners()} == {tuple(np.round(c, 9)) for c in ref}

    d = gt1[26009]
    assert d.dynamic and np.allclose(d.velocity, [0.0, 0.0, 0.5])  # central difference, world +x = camera z
    assert np.allclose(d.centre, [2.0, 0.9, 12.5 - SPEED])
    gt4 = {b.instance_id: b for b in seq.ground_truth(4)}
    assert np.allclose(gt4[26009].velocity, [0, 0, 0.5])  # one-sided: (f4 - f2) / 2
    assert [b.instance_id for b in seq.ground_truth(3)] == [26007]  # no element of car 9 at frame 3
    assert seq.ground_truth(5) == []  # static car ended at 3
    assert len(read_world_boxes(seq.boxes_path)) == 6


def test_boxes_in_camera_velocity_one_sided():
    a = kw.world_box(1, CAR_KITTI_ID, (5, 0, 0.7), (4, 2, 1.5), 0.0, 0, 9, timestamp=0)
    b = kw.world_box(1, CAR_KITTI_ID, (8, 0, 0.7), (4, 2, 1.5), 0.0, 0, 9, timestamp=2)
    (first,) = boxes_in_camera([a, b], 0, camera_pose(0))
    (last,) = boxes_in_camera([a, b], 2, camera_pose(0))
    assert np.allclose(first.velocity, [0, 0, 1.5]) and np.allclose(last.velocity, [0, 0, 1.5])
    (alone,) = boxes_in_camera([a], 0, camera_pose(0))
    assert np.allclose(alone.velocity, 0)
    # a dynamic truck (KITTI id 14) with the same instanceId is another track
    truck = kw.world_box(1, 14, (50, 0, 1.5), (8, 2.5, 3), 0.0, 0, 9, timestamp=1)
    (first,) = boxes_in_camera([a, b, truck], 0, camera_pose(0))
    assert np.allclose(first.velocity, [0, 0, 1.5])


def test_car_masks_helper_matches_instance_values():
    m = paint({26005: (0, 0, 3, 3), 26010: (5, 5, 9, 9)})
    masks = car_masks(m)
    assert sorted(masks) == [26005, 26010] and masks[26005].sum() == 16


def test_max_signed_distance_matches_per_instance_full_image_reference():
    """The cropped / union computation equals the max over instances of full-image transforms."""
    import cv2
    from vsrd_mi.data.masks import max_signed_distance

    def reference(masks):
        best = np.full(masks.shape[1:], -np.inf)
        for m in masks:
            if m.any():
                u = m.astype(np.uint8)
                inside = cv2.distanceTransform(u, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
                outside = cv2.distanceTransform(1 - u, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
                best = np.maximum(best, np.where(m, inside - 0.5, -(outside - 0.5)))
        return best

    rng = np.random.default_rng(0)
    for _ in range(100):
        h, w = rng.integers(5, 40, 2)
        inst = np.zeros((h, w), int)
        for k in range(1, 4):  # touching / overlapping rectangles, later ones on top, plus holes
            x0, y0 = rng.integers(0, w), rng.integers(0, h)
            inst[y0:y0 + rng.integers(1, 20), x0:x0 + rng.integers(1, 20)] = k
        inst[rng.random((h, w)) < 0.05] = 0
        masks = np.stack([inst == k for k in range(1, 4)])
        got, ref = max_signed_distance(masks), reference(masks)
        assert np.array_equal(np.isinf(got), np.isinf(ref))
        finite = np.isfinite(ref)
        assert np.allclose(got[finite], ref[finite], atol=1e-5)
