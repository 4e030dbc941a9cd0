"""Synthetic KITTI-360 generator: determinism, file round trip, exact masks, box geometry, stereo.

The full-resolution sequence (3 frames) is generated once per module; determinism runs at a
reduced resolution, which exercises the same code paths on 1/16 of the pixels.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from vsrd_mi.cli import main as cli_main
from vsrd_mi.data.kitti360 import Sequence, read_world_boxes
from vsrd_mi.data.masks import tight_box
from vsrd_mi.synth import SynthConfig, generate_sequence, render_frame
from vsrd_mi.synth.cars import (GLASS, TYRE, ProceduralCarConfig, bundled_mesh_paths,
                                     load_car_mesh, procedural_car)
from vsrd_mi.synth.config import RigConfig, TrafficConfig
from vsrd_mi.synth.attributes import car_visibility
from vsrd_mi.synth.layout import build_world
from vsrd_mi.synth.world import WORLD_TO_G, PlacementError
from vsrd_mi.errors import DataError
from vsrd_mi.geometry.boxes import wrap_angle
from vsrd_mi.geometry.boxes2d import iou
from vsrd_mi.geometry.camera import box_to_2d, project, transform_points

SEQ = 3
FRAMES = 3


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    root = tmp_path_factory.mktemp("synth")
    summary = generate_sequence(root, seq=SEQ, frames=FRAMES, n_static=5, n_dynamic=2, seed=11)
    return summary, Sequence(root, SEQ)


def small_config() -> SynthConfig:
    """The default rig at a quarter of the resolution in each direction."""
    r = RigConfig()
    return replace(SynthConfig(), rig=replace(r, image_size=(352, 94), fx=r.fx / 4, fy=r.fy / 4,
                                              cx=(r.cx + 0.5) / 4 - 0.5, cy=(r.cy + 0.5) / 4 - 0.5))


def tree_bytes(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


# --------------------------------------------------------------------------------------------
# determinism
# --------------------------------------------------------------------------------------------

def test_same_seed_same_bytes_different_seed_differs(tmp_path):
    cfg = small_config()
    runs = {}
    for name, seed in (("a", 4), ("b", 4), ("c", 5)):
        generate_sequence(tmp_path / name, frames=2, n_static=3, n_dynamic=1, seed=seed, config=cfg)
        runs[name] = tree_bytes(tmp_path / name)
    assert len(runs["a"]) == 1 + 1 + 2 + 2 * 2 + 2 + 2  # calib x2, poses x2, images, masks, xml, attributes
    assert runs["a"] == runs["b"]
    assert runs["a"].keys() == runs["c"].keys()
    differing = [k for k in runs["a"] if runs["a"][k] != runs["c"][k]]
    assert any("data_2d_raw" in k for k in differing)
    assert any(k.endswith(".xml") for k in differing)


# --------------------------------------------------------------------------------------------
# files: layout, calibration, poses, boxes
# --------------------------------------------------------------------------------------------

def test_calibration_and_poses(synth):
    summary, seq = synth
    cal = seq.calibration
    assert cal.image_size == (1408, 376)
    np.testing.assert_allclose(cal.K, [[552.554261, 0, 682.049453], [0, 552.554261, 238.769549],
                                       [0, 0, 1]], atol=1e-6)
    assert cal.baseline == pytest.approx(0.594, abs=1e-9)
    assert seq.frames == list(range(FRAMES))
    # poses.txt and cam0_to_world.txt agree through cam0_to_world = pose @ T_cam0_to_pose @ inv(R_rect)
    root = summary.root / "data_poses" / summary.sequence
    rows = {int(l.split()[0]): np.array(l.split()[1:], float)
            for l in (root / "poses.txt").read_text().splitlines()}
    R_rect = np.eye(4)
    R_rect[:3, :3] = cal.R_rect_00
    for f in seq.frames:
        pose = np.vstack([rows[f].reshape(3, 4), [0, 0, 0, 1]])
        np.testing.assert_allclose(pose @ cal.T_cam0_to_pose @ np.linalg.inv(R_rect),
                                   seq.cam0_to_world(f), atol=1e-7)
    # camera 1.55 m above the z = 0 road, looking forward and slightly down, ~0.85 m per frame
    centres = np.array([seq.cam0_to_world(f)[:3, 3] for f in seq.frames])
    np.testing.assert_allclose(centres[:, 2], 1.55, atol=1e-8)
    steps = np.linalg.norm(np.diff(centres[:, :2], axis=0), axis=1)
    assert np.all(np.abs(steps - 0.85) < 0.1)
    forward_z = np.array([seq.cam0_to_world(f)[2, 2] for f in seq.frames])
    assert np.all((forward_z < -0.05) & (forward_z > -0.15))  # KITTI-360's ~6 deg downward pitch


def test_xml_elements(synth):
    summary, seq = synth
    boxes = read_world_boxes(seq.boxes_path)
    cars = summary.world.cars
    assert len(boxes) == sum(FRAMES if c.dynamic else 1 for c in cars)
    for car in cars:
        mine = [b for b in boxes if b.instance_id == car.instance_id]
        assert all(b.kitti_id == 13 for b in mine)
        assert all(b.start_frame == 0 and b.end_frame == FRAMES - 1 for b in mine)
        stamps = sorted(b.timestamp for b in mine)
        assert stamps == (list(range(FRAMES)) if car.dynamic else [-1])
        for b in mine:
            np.testing.assert_allclose(b.size_lwh, car.model.size, atol=1e-9)


def test_ground_truth_round_trip(synth):
    summary, seq = synth
    assert {c.dynamic for c in summary.world.cars} == {True, False}
    for f in seq.frames:
        loaded = {b.instance_id: b for b in seq.ground_truth(f)}
        mine = {b.instance_id: b for b in summary.boxes[f]}
        assert loaded.keys() == mine.keys() == set(summary.instance_ids())
        for k, b in mine.items():
            g = loaded[k]
            np.testing.assert_allclose(g.centre, b.centre, atol=1e-5)
            np.testing.assert_allclose(g.size, b.size, atol=1e-5)
            assert abs(wrap_angle(g.yaw - b.yaw)) < 1e-5
            np.testing.assert_allclose(g.velocity, b.velocity, atol=1e-5)
            assert g.dynamic == b.dynamic


def test_velocities_and_placement(synth):
    summary, _ = synth
    world = summary.world
    for car in world.cars:
        speed = np.linalg.norm(car.velocity) * world.config.rig.frame_rate
        if car.dynamic:
            assert 2.0 * 0.98 <= speed <= 12.0 * 1.02  # chord of a gently curved lane
            assert car.velocity[2] == 0.0
            heading = np.array([np.cos(car.yaw), np.sin(car.yaw)])
            assert heading @ car.velocity[:2] / np.linalg.norm(car.velocity) > 0.9999
        else:
            assert speed == 0.0
    for i in range(FRAMES):  # no two cars overlap at any frame
        prints = [c.footprint(i) for c in world.cars]
        for a in range(len(prints)):
            for b in range(a + 1, len(prints)):
                assert not prints[a].intersects(prints[b])


def test_box_is_tight_box_of_placed_mesh(synth):
    summary, _ = synth
    world = summary.world
    for i in range(FRAMES):
        for car in world.cars:
            box = car.box_world_g(i)  # y-down gravity frame: x = x_w, y = -z_w, z = y_w
            verts_g = transform_points(WORLD_TO_G, car.world_vertices(i))
            local = (verts_g - box.centre) @ box.rotation  # box-local (x = width, z = length)
            half = 0.5 * box.size
            assert np.all(np.abs(local) <= half + 1e-9)
            np.testing.assert_allclose(np.abs(local).max(axis=0), half, atol=1e-9)
            assert verts_g[:, 1].max() == pytest.approx(0.0, abs=1e-9)  # wheels on the road


# --------------------------------------------------------------------------------------------
# masks
# --------------------------------------------------------------------------------------------

def first_hit_faces(origin: np.ndarray, dirs: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Float64 Moller-Trumbore: index of the nearest triangle hit by each ray (-1: none)."""
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    out = np.full(len(dirs), -1)
    for r, d in enumerate(dirs):
        p = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, p)
        ok = np.abs(det) > 1e-12
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = origin - tri[:, 0]
        u = np.einsum("ij,ij->i", s, p) * inv
        q = np.cross(s, e1)
        v = (q @ d) * inv
        t = np.einsum("ij,ij->i", e2, q) * inv
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-6)
        if np.any(hit):
            out[r] = np.flatnonzero(hit)[np.argmin(t[hit])]
    return out


def test_masks_equal_hit_shape_at_pixel_centre(synth):
    summary, seq = synth
    world = summary.world
    rng = np.random.default_rng(0)
    frame = seq.frames[1]
    imap = seq.instance_map(frame)
    mesh = world.frame_mesh(1)
    W, H = world.rig.image_size
    cars = imap >= 26000
    edges = cars & ~cv2.erode(cars.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    ev, eu = np.nonzero(edges)
    pick = rng.choice(len(eu), size=min(120, len(eu)), replace=False)
    u = np.concatenate([eu[pick], rng.integers(0, W, 120)])
    v = np.concatenate([ev[pick], rng.integers(0, H, 120)])
    T = seq.cam0_to_world(frame)
    d = np.stack([u, v, np.ones_like(u)], 1).astype(float) @ np.linalg.inv(seq.calibration.K).T
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)) @ T[:3, :3].T
    faces = first_hit_faces(T[:3, 3], d, mesh.vertices[mesh.faces])
    expected = np.where(faces < 0, 23, np.where(mesh.instance[faces] > 0,
                                                26000 + mesh.instance[faces], mesh.semantic[faces]))
    np.testing.assert_array_equal(imap[v, u], expected)
    assert set(np.unique(imap[imap < 1000])) <= {7, 8, 11, 22, 23}
    np.testing.assert_array_equal(imap, render_frame(world, 1)[0].instance)


def test_projected_boxes_cover_masks(synth):
    summary, seq = synth
    world = summary.world
    K, size = world.rig.K, world.rig.image_size
    checked, box_ious = 0, []
    for i, frame in enumerate(seq.frames):
        imap = seq.instance_map(frame)
        for car, vis in zip(world.cars, car_visibility(world, i, imap)):
            if vis.visible_px < 50 or vis.occluded_fraction > 0 or vis.truncated:
                continue
            mask_box = tight_box(imap == car.global_id)
            gt_box = box_to_2d(car.box_world_g(i), K, world.g_to_camera(i), size)
            # the silhouette's pixel centres lie inside the projected ground-truth box
            assert np.all(mask_box[:2] + 0.5 >= gt_box[:2] - 1e-6)
            assert np.all(mask_box[2:] - 0.5 <= gt_box[2:] + 1e-6)
            # ... and the mask's box is the projected mesh's box up to pixel quantisation
            uv = project(K, transform_points(np.linalg.inv(seq.cam0_to_world(frame)),
                                             car.world_vertices(i)))
            mesh_box = np.concatenate([uv.min(axis=0), uv.max(axis=0)])
            assert np.abs(mask_box - mesh_box).max() <= 1.0
            assert iou(mask_box, mesh_box) >= 0.9
            box_ious.append(iou(mask_box, gt_box))
            checked += 1
    assert checked >= 3
    # a car is not its box (inset wheels, rounded corners), but gross errors (swapped sizes,
    # wrong yaw) would fall far below this
    assert min(box_ious) >= 0.6


def test_visibility_counts_are_consistent(synth):
    summary, seq = synth
    imap = seq.instance_map(0)
    world = summary.world
    every_pixel = replace(world.config.visibility, max_rays_per_car=10 ** 7)
    exact = car_visibility(replace(world, config=replace(world.config, visibility=every_pixel)),
                           0, imap)
    for vis, sampled in zip(exact, car_visibility(world, 0, imap)):
        assert vis.visible_px == np.count_nonzero(imap == vis.instance_value)
        assert vis.visible_px <= vis.inside_px or vis.inside_px == 0
        # large silhouettes are counted on a sparser grid by default
        assert sampled.visible_px == pytest.approx(vis.visible_px, rel=0.05, abs=1)
        assert sampled.inside_px == pytest.approx(vis.inside_px, rel=0.05, abs=1)


# --------------------------------------------------------------------------------------------
# stereo texture
# --------------------------------------------------------------------------------------------

def test_sgbm_finds_true_disparities(synth):
    summary, seq = synth
    left, _ = render_frame(summary.world, 0)
    grey = [cv2.cvtColor(seq.image(0, c), cv2.COLOR_RGB2GRAY) for c in (0, 1)]
    bs = 5
    sgbm = cv2.StereoSGBM_create(0, 128, bs, P1=8 * bs * bs, P2=32 * bs * bs, uniquenessRatio=10,
                                 speckleWindowSize=100, speckleRange=2,
                                 mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    disp = sgbm.compute(*grey).astype(np.float64) / 16.0
    K = seq.calibration.K
    true = K[0, 0] * seq.calibration.baseline / left.depth
    imap = seq.instance_map(0)
    # where SGBM can answer: 2-96 px of disparity (3.4-164 m), not in the left band of
    # numDisparities columns that it leaves empty
    measurable = (true > 2) & (true < 96)
    measurable[:, :128] = False
    fractions = {}
    for name, region in (("cars", imap >= 26000), ("road", imap == 7), ("buildings", imap == 11)):
        good = (np.abs(disp - true) < 1.0) & (disp > 0)
        fractions[name] = good[region & measurable].mean()
    assert min(fractions.values()) >= 0.8, fractions


# --------------------------------------------------------------------------------------------
# cars
# --------------------------------------------------------------------------------------------

def test_procedural_cars_cover_the_body_types():
    rng = np.random.default_rng(3)
    cfg = ProceduralCarConfig()
    for name, l_rng, w_rng, h_rng in cfg.types:
        for _ in range(10):
            car = procedural_car(rng, cfg, kind=name)
            l, w, h = car.size
            assert l_rng[0] - 1e-9 <= l <= l_rng[1] + 1e-9
            assert w_rng[0] - 1e-9 <= w <= w_rng[1] + 1e-9
            assert h_rng[0] - 0.02 <= h <= h_rng[1] + 1e-9  # faceted wheels lose < 2 cm
            assert car.box_min[2] == 0.0
            assert {GLASS, TYRE} <= set(np.unique(car.materials))
    assert max(t[1][1] for t in cfg.types) >= 5.2 and max(t[2][1] for t in cfg.types) >= 2.3
    assert max(t[3][1] for t in cfg.types) >= 2.2


def test_bundled_meshes_in_car_frame():
    paths = bundled_mesh_paths()
    assert len(paths) == 2
    for p in paths:
        car = load_car_mesh(p)
        length, width, height = car.size
        assert 3.9 < length < 4.3 and 1.7 < width < 1.9 and 1.1 < height < 1.25


def test_bad_mesh_files(tmp_path):
    with pytest.raises(DataError, match="does not exist"):
        load_car_mesh(tmp_path / "missing.ply")
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\nend_header\n\x00")
    with pytest.raises(DataError, match="bad.ply"):
        load_car_mesh(bad)
    flat = tmp_path / "flat.ply"
    flat.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                    "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
                    "end_header\n0 0 0\n1 0 0\n0 0 1\n3 0 1 2\n")
    with pytest.raises(DataError, match="degenerate"):
        load_car_mesh(flat)


def test_too_many_cars_is_a_clear_error():
    cfg = replace(SynthConfig(), traffic=replace(TrafficConfig(), max_tries=5))
    with pytest.raises(PlacementError, match="could not place"):
        build_world(frames=2, n_static=60, n_dynamic=0, seed=0, config=cfg)


def test_cli(tmp_path, capsys):
    out = tmp_path / "cli"
    assert cli_main(["synth", str(out), "--seq", "7", "--frames", "1", "--static", "1",
                     "--dynamic", "1", "--seed", "2", "--procedural-only", "--quiet"]) == 0
    assert "2013_05_28_drive_0007_sync" in capsys.readouterr().out
    seq = Sequence(out, 7)
    assert seq.frames == [0] and len(seq.ground_truth(0)) == 2
    # --procedural-only is meshes=[]: every car is built procedurally
    assert all(c.model.name.startswith("procedural")
               for c in build_world(7, 1, 1, 1, 2, meshes=[]).cars)
    assert cli_main(["synth", str(tmp_path / "x"), "--frames", "1",
                     "--mesh", str(tmp_path / "nope.ply")]) == 2
    assert "nope.ply" in capsys.readouterr().err


# --------------------------------------------------------------------------------------------
# the bundled example (scenes/README.md)
# --------------------------------------------------------------------------------------------

BUNDLED = Path(__file__).resolve().parents[1] / "scenes" / "kitti360-synth"


@pytest.mark.skipif(not BUNDLED.is_dir(), reason="bundled scene not present")
def test_bundled_scene_is_reproducible(tmp_path):
    from vsrd_mi.synth import write_annotations

    world = build_world(seq=0, frames=30, n_static=5, n_dynamic=2, seed=0)  # scenes/README.md
    write_annotations(tmp_path, world)
    for p in sorted(tmp_path.rglob("*")):
        if p.is_file():
            assert p.read_bytes() == (BUNDLED / p.relative_to(tmp_path)).read_bytes(), p.name
    seq = Sequence(BUNDLED, 0)
    assert seq.frames == list(range(30))
    # the instance map of one frame is re-rendered (Embree may differ at a few edge pixels on
    # another CPU, hence not a byte comparison)
    left, _ = render_frame(world, 15)
    assert np.mean(seq.instance_map(15) == left.instance) >= 0.9999
    assert sum(b.dynamic for b in seq.ground_truth(15)) == 2
