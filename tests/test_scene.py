"""Mitsuba sensors, observations in the optimisation frame, default boxes and scene (XML) round trips."""

from __future__ import annotations

import numpy as np
import pytest

from test_kitti360_loader import SEQ, K as TOY_K, H, W, make_dataset

import vsrd_mi  # noqa: F401
import mitsuba as mi

from vsrd_mi.cli import build_parser
from vsrd_mi.data.kitti360 import Sequence
from vsrd_mi.data.observations import load_observations
from vsrd_mi.data.selection import SelectionConfig, select_targets, spec_for_frame
from vsrd_mi.geometry.boxes import Box3D
from vsrd_mi.geometry.camera import project, transform_points
from vsrd_mi.scene import (default_initial_boxes, load_scene, perspective_sensor, pixel_rays,
                           save_scene_xml, scene_dict, sensor_id)
from vsrd_mi.scene.initial import DefaultInitConfig

KITTI_K = np.array([[552.554261, 0.0, 682.049453], [0.0, 552.554261, 238.769549], [0.0, 0.0, 1.0]])
KITTI_SIZE = (1408, 376)
A, B = 26001, 26002


def random_pose(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    T = np.eye(4)
    T[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    T[:3, 3] = rng.uniform(-5, 5, 3)
    return T


def sample_ray(sensor, u: float, v: float, size=KITTI_SIZE):
    ray, _ = sensor.sample_ray(sensor.shutter_open(), 0.5, mi.Point2f(float((u + 0.5) / size[0]), float((v + 0.5) / size[1])),
                               mi.Point2f(0.5, 0.5))
    return (np.array(ray.o, dtype=np.float64).ravel(), np.array(ray.d, dtype=np.float64).ravel(),
            float(np.array(ray.time).ravel()[0]))


def test_pixel_rays_project_back():
    rng = np.random.default_rng(3)
    T = random_pose(rng)
    u, v = rng.uniform(-0.5, 1407.5, 50), rng.uniform(-0.5, 375.5, 50)
    o, d = pixel_rays(KITTI_K, T, u, v)
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)
    assert np.allclose(o, T[:3, 3])
    uv = project(KITTI_K, transform_points(np.linalg.inv(T), o + 7.0 * d))
    assert np.allclose(uv, np.stack([u, v], 1), atol=1e-9)


@pytest.mark.parametrize("seed", [0, 1])
def test_mitsuba_sensor_matches_pixel_rays(seed):
    rng = np.random.default_rng(seed)
    T = random_pose(rng)
    dt = int(rng.integers(-25, 25))
    sensor = mi.load_dict(perspective_sensor(KITTI_K, T, KITTI_SIZE, dt))
    film = sensor.film()
    assert tuple(film.size()) == KITTI_SIZE
    pixels = [(0.0, 0.0), (1407.0, 375.0), (682.049453, 238.769549), (100.25, 300.5), (1300.0, 20.0)]
    pixels += [tuple(p) for p in rng.uniform([0, 0], [1407, 375], (5, 2))]
    for u, v in pixels:
        o, d, time = sample_ray(sensor, u, v)
        o_ref, d_ref = pixel_rays(KITTI_K, T, u, v)
        assert np.allclose(o, o_ref[0], atol=1e-5)
        assert np.allclose(d, d_ref[0], atol=2e-6), (u, v, d, d_ref)
        uv = project(KITTI_K, transform_points(np.linalg.inv(T), o + 10.0 * d))
        assert np.allclose(uv, [u, v], atol=2e-3)
        assert time == dt
    assert sensor.shutter_open() == dt and sensor.shutter_open_time() == 0.0


def test_non_square_pixels_rejected():
    K = KITTI_K.copy()
    K[1, 1] *= 1.01
    with pytest.raises(ValueError, match="square pixels"):
        perspective_sensor(K, np.eye(4), KITTI_SIZE, 0)


def toy_sequence(tmp_path, pitch=0.04, n=9):
    """A car A in every frame, a second car B in frames >= 2 (left half of the image)."""
    layout = {f: {A: (60 + 2 * f, 40, 99 + 2 * f, 69)} for f in range(n)}
    for f in range(2, n):
        layout[f][B] = (5, 45, 30, 70)
    return Sequence(make_dataset(tmp_path, list(range(n)), layout, pitch=pitch), SEQ)


def test_observations(tmp_path):
    seq = toy_sequence(tmp_path)
    cfg = SelectionConfig(num_sources=4, min_sources=4)
    spec = spec_for_frame(seq, 5, cfg)
    obs = load_observations(seq, spec)
    assert obs.target == 5 and obs.frames[0] == 5
    assert list(obs.frames[1:]) == sorted(set(spec.sources) | set(spec.group) - {5})
    assert np.array_equal(obs.dt, obs.frames - 5)
    assert list(obs.instance_ids) == [A, B]
    assert obs.masks.shape == (obs.num_frames, 2, H, W) and obs.weights.shape == (obs.num_frames, H, W)
    # the target camera is the origin; the optimisation frame undoes the 0.04 rad pitch
    assert np.allclose(obs.cam_to_opt[0][:3, 3], 0)
    c, s = np.cos(0.04), np.sin(0.04)
    assert np.allclose(obs.cam_to_opt[0][:3, :3], [[1, 0, 0], [0, c, -s], [0, s, c]])
    # camera centres: straight ahead along the road (opt z), 0.8 m per frame, at constant height
    for i, f in enumerate(obs.frames):
        assert np.allclose(obs.cam_to_opt[i][:3, 3], [0, 0, 0.8 * (f - 5)], atol=1e-9)
        assert np.allclose(obs.cam_to_opt[i][:3, :3], obs.cam_to_opt[0][:3, :3])  # pure translation
    # world -> optimisation frame: world up is -y, the road direction (world +x) is +z
    assert np.allclose(obs.T_opt_from_world[:3, :3] @ [0, 0, 1], [0, -1, 0], atol=1e-12)
    assert np.allclose(obs.T_opt_from_world[:3, :3] @ [1, 0, 0], [0, 0, 1], atol=1e-12)
    i1 = list(obs.frames).index(1)
    # B is absent in frame 1: empty mask, NaN box, invisible
    assert not obs.masks[i1, 1].any() and np.isnan(obs.boxes2d[i1, 1]).all() and not obs.visible[i1, 1]
    assert np.allclose(obs.boxes2d[0, 0], [69.5, 39.5, 109.5, 69.5])  # A in frame 5: x 70..109
    assert obs.visible[0].all()
    # weights: > 0.5 inside a mask, < 0.5 outside, max over instances
    assert np.all(obs.weights[0][obs.masks[0].any(0)] > 0.5) and np.all(obs.weights[0][~obs.masks[0].any(0)] < 0.5)
    assert obs.baseline == pytest.approx(0.6)
    assert obs.image_paths_right[0].parts[-3] == "image_01"


def test_default_initial_boxes(tmp_path):
    seq = toy_sequence(tmp_path, pitch=0.0)
    obs = load_observations(seq, spec_for_frame(seq, 5, SelectionConfig(num_sources=4, min_sources=4)))
    cfg = DefaultInitConfig()
    boxes = default_initial_boxes(obs, cfg)
    assert [b.instance_id for b in boxes] == [A, B]
    for n, box in enumerate(boxes):
        x1, y1, x2, y2 = obs.boxes2d[0, n]
        # independent: the centre projects to the 2D box centre at depth f * h / box height + offset
        cam = transform_points(np.linalg.inv(obs.cam_to_opt[0]), box.centre)
        assert np.allclose(project(TOY_K, cam), [(x1 + x2) / 2, (y1 + y2) / 2])
        assert cam[2] == pytest.approx(np.clip(100.0 * 1.5 / (y2 - y1) + 0.9, cfg.min_depth, cfg.max_depth))
        assert np.allclose(box.size, cfg.size) and box.yaw == 0.0 and not box.dynamic


def test_scene_dict_xml_round_trip(tmp_path):
    seq = toy_sequence(tmp_path)
    obs = load_observations(seq, spec_for_frame(seq, 5, SelectionConfig(num_sources=4, min_sources=4)))
    boxes = [Box3D(centre=(1.0, 0.5, 12.0), size=(1.8, 1.5, 4.3), yaw=0.4, instance_id=A),
             Box3D(centre=(-3.0, 0.6, 9.0), size=(1.7, 1.4, 4.0), yaw=-0.2, velocity=(0.0, 0.0, 0.3),
                   dynamic=True, instance_id=B)]
    from_dict = mi.load_dict(scene_dict(obs, boxes))
    path = save_scene_xml(tmp_path / "scene.xml", obs, boxes)
    text = path.read_text()
    assert text.startswith('<scene version="3.0.0">') and 'type="vsrd_silhouette"' in text
    from_file = mi.load_file(str(path))
    for scene in (from_dict, from_file):
        sensors = scene.sensors()
        assert [s.id() for s in sensors] == [sensor_id(f) for f in obs.frames]
        for i, sensor in enumerate(sensors):
            assert sensor.shutter_open() == obs.dt[i]
            u, v = 33.0, 71.0
            o, d, time = sample_ray(sensor, u, v, (W, H))
            o_ref, d_ref = pixel_rays(obs.K[i], obs.cam_to_opt[i], u, v)
            assert np.allclose(o, o_ref[0], atol=1e-5) and np.allclose(d, d_ref[0], atol=2e-6)
            assert time == obs.dt[i]
    p_dict, p_file = mi.traverse(from_dict.integrator()), mi.traverse(from_file.integrator())
    for key in ("centre", "size", "yaw", "velocity", "dynamic"):
        assert np.allclose(np.array(p_dict[key]), np.array(p_file[key]), atol=1e-6), key
    assert np.array_equal(np.array(p_dict["dynamic"]), [0.0, 1.0])
    np.testing.assert_allclose(np.array(p_dict["size"]), [1.8, 1.5, 4.3, 1.7, 1.4, 4.0], rtol=1e-6)
    np.testing.assert_allclose(np.array(p_dict["yaw"]), [0.4, -0.2], rtol=1e-6)


def test_load_scene_and_cli(tmp_path):
    seq = toy_sequence(tmp_path, n=20)  # 19 candidates >= 16 sources with the default config
    scene, obs = load_scene(seq.root, 0, 10)
    assert obs.target == 10 and len(obs.spec.sources) == 16 and obs.spec.note is None
    assert len(scene.sensors()) == obs.num_frames
    assert type(scene.integrator()).__name__ == "VSRDSilhouetteIntegrator"
    out = tmp_path / "cli.xml"
    args = build_parser().parse_args(["export-scene", str(seq.root), "--sequence", "0", "--frame", "10", str(out)])
    assert args.func(args) == 0
    assert len(mi.load_file(str(out)).sensors()) == obs.num_frames
    args = build_parser().parse_args(["export-scene", str(tmp_path / "missing"), "--sequence", "0",
                                      "--frame", "10", str(out)])
    assert args.func(args) == 2


@pytest.mark.slow
def test_synthetic_round_trip(tmp_path):
    """Synthetic generator -> loader -> observations: ground truth, poses and masks agree (~90 s)."""
    from vsrd_mi.synth import generate_sequence
    from vsrd_mi.geometry.boxes2d import iou
    from vsrd_mi.geometry.camera import box_to_2d

    summary = generate_sequence(tmp_path, seq=0, frames=24, n_static=3, n_dynamic=1, seed=1)
    seq = Sequence(tmp_path, 0)
    assert seq.frames == list(summary.frames) and seq.has_masks and seq.has_boxes
    for f in seq.frames:
        got = {b.instance_id: b for b in seq.ground_truth(f)}
        ref = {b.instance_id: b for b in summary.boxes[f]}
        assert set(got) == set(ref)
        for k, b in got.items():
            assert np.allclose(b.centre, ref[k].centre, atol=1e-5) and np.allclose(b.size, ref[k].size, atol=1e-5)
            assert abs(np.sin(b.yaw - ref[k].yaw)) < 1e-5 and b.dynamic == ref[k].dynamic
            assert np.allclose(b.velocity, ref[k].velocity, atol=1e-5)
    specs = select_targets(seq)
    assert specs and all(len(s.sources) == 16 for s in specs)
    scene, obs = load_scene(tmp_path, 0, specs[0].target)
    assert len(scene.sensors()) == obs.num_frames
    # the target's ground truth, moved into every frame through cam_to_opt (and velocity), covers
    # the masks there: poses, frame offsets and masks are consistent
    gt = {b.instance_id: b for b in seq.ground_truth(obs.target)}
    ious = []
    for n, value in enumerate(obs.instance_ids):
        box = gt[int(value)].transformed(obs.cam_to_opt[0])
        for i in range(obs.num_frames):
            if obs.visible[i, n]:
                proj = box_to_2d(box, obs.K[i], np.linalg.inv(obs.cam_to_opt[i]), obs.image_size, dt=obs.dt[i])
                ious.append(iou(proj, obs.boxes2d[i, n]) if proj is not None else 0.0)
    assert len(ious) > obs.num_frames and np.median(ious) > 0.9, np.percentile(ious, [10, 50, 90])
