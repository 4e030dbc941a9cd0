"""Synthetic generator, the harder world: vehicle classes, parking rows, props, camera attitude,
the attributes file and the development / validation suites (all through public functions)."""

from __future__ import annotations

from collections import Counter
from dataclasses import replace

import numpy as np
import pytest
import trimesh

from vsrd_mi.cli import main as cli_main
from vsrd_mi.data.kitti360 import Sequence
from vsrd_mi.synth import generate_sequence, render_frame
from vsrd_mi.synth.attributes import (ATTRIBUTES_FORMAT, attributes_path, car_visibility,
                                      read_attributes)
from vsrd_mi.synth.cars import bundled_mesh_paths, load_car_mesh
from vsrd_mi.synth.config import ParkingConfig, SynthConfig
from vsrd_mi.synth.layout import build_world
from vsrd_mi.synth.render import RayCaster, pixel_directions
from vsrd_mi.synth.suites import (EVEN_MIX, LONG_OFFSET, LONG_SEEDS, ROUND_STRIDE, SCENARIOS, SET_SEEDS,
                                  SET_SEQUENCE_BASE, hard_config,
                                  select, suite)
from vsrd_mi.synth.vehicles import (VEHICLE_CLASSES, VehicleConfig, VehicleDeck, build_vehicle,
                                    draw_profile)
from vsrd_mi.synth.world import PROP, camera_pitch_roll

CAR_VALUES = range(26001, 27000)
PROP_SEMANTICS = {17, 20, 21, 24, 39}


def small(config: SynthConfig, factor: int = 4) -> SynthConfig:
    """``config`` with the default rig at 1 / ``factor`` of the resolution in each direction."""
    r = config.rig
    w, h = r.image_size
    return replace(config, rig=replace(r, image_size=(w // factor, h // factor), fx=r.fx / factor,
                                       fy=r.fy / factor, cx=(r.cx + 0.5) / factor - 0.5,
                                       cy=(r.cy + 0.5) / factor - 0.5))


# --------------------------------------------------------------------------------------------
# vehicles
# --------------------------------------------------------------------------------------------

def test_vehicle_classes_cover_the_required_ranges():
    lengths = [r for c in VEHICLE_CLASSES for r in c.length]
    widths = [r for c in VEHICLE_CLASSES for r in c.body_width]
    heights = [r for c in VEHICLE_CLASSES for r in c.height]
    assert {c.name for c in VEHICLE_CLASSES} == {"city_car", "hatchback", "sedan", "estate", "suv",
                                                 "pickup", "van", "sports"}
    assert min(lengths) <= 3.3 and max(lengths) >= 5.95
    assert min(widths) <= 1.6 and max(widths) >= 2.1
    assert min(heights) <= 1.2 and max(heights) >= 2.1


@pytest.mark.parametrize("vclass", VEHICLE_CLASSES, ids=lambda c: c.name)
def test_vehicle_sizes_and_tight_box_with_mirrors(vclass):
    cfg = VehicleConfig()
    for seed in range(8):
        drawn = draw_profile(np.random.default_rng(seed), vclass, cfg)  # build_vehicle's first draws
        car = build_vehicle(np.random.default_rng(seed), vclass, cfg)
        length, width, height = car.size
        assert vclass.length[0] <= length <= vclass.length[1]
        assert vclass.body_width[0] <= drawn.body_width <= vclass.body_width[1]
        assert vclass.mirror[0] <= drawn.mirror <= vclass.mirror[1]
        assert vclass.height[0] <= height <= vclass.height[1]
        # the tight box is the whole vehicle: body width plus both mirrors
        np.testing.assert_allclose([length, width, height],
                                   [drawn.length, drawn.body_width + 2 * drawn.mirror,
                                    drawn.height], atol=1e-9)
        assert car.box_min[2] == 0.0
        np.testing.assert_allclose(car.box_centre[:2], 0.0, atol=1e-9)
        # what sticks out of the body sides are the mirrors, above the belt line
        out = car.vertices[np.abs(car.vertices[:, 1]) > 0.5 * drawn.body_width + 1e-9]
        assert len(out) > 0 and np.all(out[:, 2] >= drawn.belt - 1e-9)
        assert np.all(out[:, 2] <= drawn.belt + cfg.mirror_height[1] + 1e-9)
        assert car.vehicle_class == vclass.name and car.lamps is not None


@pytest.mark.parametrize("vclass", VEHICLE_CLASSES, ids=lambda c: c.name)
def test_rounded_plan_corners_keep_the_tight_box(vclass):
    square = VehicleConfig()
    rounded = replace(square, plan_corner=(0.3, 0.3))
    for seed in range(3):
        drawn = draw_profile(np.random.default_rng(seed), vclass, square)
        rng_a, rng_b = np.random.default_rng(seed), np.random.default_rng(seed)
        a, b = build_vehicle(rng_a, vclass, square), build_vehicle(rng_b, vclass, rounded)
        np.testing.assert_allclose(b.size, a.size, atol=1e-9)  # the mirrors still set the width
        assert rng_a.uniform() == rng_b.uniform()  # one radius draws nothing: the street is the same
        half, hw = 0.5 * drawn.length, 0.5 * drawn.body_width
        # every point but the mirrors' (and a pickup bed's walls) lies inside the rounded plan
        body = b.vertices[np.abs(b.vertices[:, 1]) <= hw + 1e-9]
        if vclass.bed:
            body = body[body[:, 0] > drawn.backlight_base + 1e-9]
        into = np.clip(np.abs(body[:, 0]) - (half - 0.3), 0.0, None)
        outside = np.hypot(into, np.clip(np.abs(body[:, 1]) - (hw - 0.3), 0.0, None)) > 0.3 + 1e-9
        assert not np.any(outside & (into > 0))
        # the square car reaches its plan's front corners, the rounded one stays 0.3 (sqrt 2 - 1)
        # off them
        def corner_gap(car):
            low = car.vertices[(car.vertices[:, 2] < drawn.belt - 1e-6) & (car.vertices[:, 0] > 0)]
            return np.min(np.hypot(half - np.abs(low[:, 0]), hw - np.abs(low[:, 1])))
        assert corner_gap(a) < 0.05 and corner_gap(b) >= 0.3 * (np.sqrt(2.0) - 1.0) - 1e-6


@pytest.mark.parametrize("bad", [dict(plan_corner=(0.3, 0.2)), dict(plan_corner=(-0.1, 0.2)),
                                 dict(plan_segment=0.0)])
def test_plan_corner_settings_are_checked(bad):
    with pytest.raises(ValueError, match="plan_"):
        VehicleConfig(**bad)


def top_profile(car, bins: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """Highest surface point in each of ``bins`` slices along the length (surface samples)."""
    mesh = trimesh.Trimesh(car.vertices, car.faces, process=False)
    pts = trimesh.sample.sample_surface(mesh, 30000, seed=0)[0]
    edges = np.linspace(car.box_min[0], car.box_max[0], bins + 1)
    idx = np.clip(np.digitize(pts[:, 0], edges) - 1, 0, bins - 1)
    top = np.array([pts[idx == k, 2].max() for k in range(bins)])
    return 0.5 * (edges[1:] + edges[:-1]), top


@pytest.mark.parametrize("vclass", VEHICLE_CLASSES, ids=lambda c: c.name)
def test_profiles_are_asymmetric_front_to_back(vclass):
    for seed in range(3):
        car = build_vehicle(np.random.default_rng(100 + seed), vclass)
        x, top = top_profile(car)
        height = car.size[2]
        if vclass.bed:
            # a pickup's bonnet is as high as its bed's rails; the open bed, a quarter of the
            # length at least, lies behind the cab
            assert x[top > 0.9 * height].min() > car.box_min[0] + 0.25 * car.size[0]
        else:
            # the bonnet (front: +x, the last slices) is lower than the tail end, 10 % of the
            # length in from each end
            k = len(top) // 10
            assert top[-1 - k] < top[k] - 0.02 * height, (vclass.name, top[-1 - k], top[k])
        # and the silhouette is not its own mirror image
        assert np.mean(np.abs(top - top[::-1])) > 0.04 * height


def test_vehicle_deck_deals_every_entry_and_rejects_unknown_names():
    deck = VehicleDeck(np.random.default_rng(0), EVEN_MIX,
                       [load_car_mesh(p) for p in bundled_mesh_paths()], VehicleConfig(), 0.04)
    names = [deck.draw()[1].vehicle_class for _ in range(10)]
    assert sorted(names) == sorted([c.name for c in VEHICLE_CLASSES]
                                   + [p.stem for p in bundled_mesh_paths()])
    with pytest.raises(ValueError, match="minivan"):
        VehicleDeck(np.random.default_rng(0), (("minivan", 1),), [], VehicleConfig(), 0.0)


# --------------------------------------------------------------------------------------------
# parking rows, props, camera
# --------------------------------------------------------------------------------------------

def rows_world(seed: int, layouts, gap=(0.5, 0.9), props=()):
    cfg = hard_config(replace(ParkingConfig(), layouts=layouts, gap=gap), props=props)
    return build_world(seq=3, frames=4, n_static=60, n_dynamic=1, seed=seed, config=cfg)


def signed_angle_to_road(world, car) -> float:
    """Angle of the car's length axis to the road direction, folded into (-90, 90] degrees."""
    s, _ = world.centreline.to_road(car.centre0[None, :2])
    a = np.degrees(car.yaw - world.centreline.heading(s[0]))
    return float((a + 90.0) % 180.0 - 90.0)


def test_parking_angles_labels_and_tight_rows():
    angled, perpendicular, facing = [], [], Counter()
    for seed in range(3):
        for layouts in ((("angled", 1.0),), (("perpendicular", 1.0),), (("parallel", 1.0),)):
            world = rows_world(seed, layouts)
            parked = [c for c in world.cars if not c.dynamic]
            assert len(parked) >= 8
            jitter = 4 * world.config.parking.yaw_jitter_deg
            for car in parked:
                a = signed_angle_to_road(world, car)
                if car.parking == "angled":
                    angled.append(a)
                    assert 15.0 - jitter <= abs(a) <= 60.0 + jitter
                elif car.parking == "perpendicular":
                    perpendicular.append(a)
                    assert abs(a) >= 90.0 - jitter
                else:
                    assert abs(a) <= jitter
                    s, n = world.centreline.to_road(car.centre0[None, :2])
                    traffic = 1.0 if n[0] < 0 else -1.0  # right-hand traffic
                    heading = np.array([np.cos(car.yaw), np.sin(car.yaw)])
                    along = heading @ [np.cos(world.centreline.heading(s[0])),
                                       np.sin(world.centreline.heading(s[0]))]
                    facing[car.parking] += 1
                    assert (along * traffic > 0) == (car.parking == "parallel")
                assert world.angle_to_road_deg(car) == pytest.approx(min(abs(a), 180 - abs(a)),
                                                                     abs=1e-6)
            # tight rows: no two footprints closer than the clearance, some gaps below 1 m
            prints = [c.footprint(0) for c in parked]
            gaps = [min(prints[a].distance(prints[b]) for b in range(len(prints)) if b != a)
                    for a in range(len(prints))]
            assert min(gaps) >= world.config.parking.min_clearance - 1e-6
            assert min(gaps) < 1.0
    assert min(angled) < 0 < max(angled)  # leaning both ways along the road
    assert len(perpendicular) >= 8
    assert facing["parallel"] > 0 and facing["parallel_reversed"] > 0


def test_props_never_carry_car_ids(tmp_path):
    cfg = small(hard_config(props=(("pole", 6), ("sign", 4), ("tree", 6), ("pedestrian", 12),
                                   ("bin", 4))))
    world = build_world(seq=1, frames=2, n_static=30, n_dynamic=1, seed=5, config=cfg)
    mesh = world.frame_mesh(0)
    props = mesh.material == PROP
    assert props.sum() > 0 and set(np.unique(mesh.semantic[props])) == PROP_SEMANTICS
    values = np.where(mesh.instance[props] > 0,
                      mesh.semantic[props] * 1000 + mesh.instance[props], mesh.semantic[props])
    assert not np.isin(values, CAR_VALUES).any()
    summary = generate_sequence(tmp_path, seq=1, frames=2, n_static=30, n_dynamic=1, seed=5,
                                config=cfg)
    seen = set()
    for f in summary.frames:
        imap = Sequence(tmp_path, 1).instance_map(f)
        cars = set(np.unique(imap[(imap >= 26001) & (imap <= 26999)]).tolist())
        assert cars <= {c.global_id for c in world.cars}
        seen |= set(np.unique(imap // 1000).tolist())
    assert seen & {17, 20, 24, 39}  # some props are in view, with their own ids


def test_camera_pitch_and_roll_in_written_poses(tmp_path):
    base = small(SynthConfig())
    still = replace(base.ego, yaw_noise_deg=0.0, pitch_noise_deg=0.0, roll_noise_deg=0.0)
    cfg = replace(base, ego=still, rig=replace(base.rig, camera_pitch_deg=(6.4, 6.4),
                                               camera_roll_deg=(-1.1, -1.1)))
    summary = generate_sequence(tmp_path, seq=2, frames=3, n_static=1, n_dynamic=0, seed=1,
                                config=cfg)
    assert summary.world.camera_attitude == pytest.approx((6.4, -1.1))
    seq = Sequence(tmp_path, 2)
    for f in seq.frames:
        np.testing.assert_allclose(camera_pitch_roll(seq.cam0_to_world(f)), (6.4, -1.1),
                                   atol=1e-6)
    # drawn per sequence within the range; the ego noise comes on top
    ranged = replace(base, rig=replace(base.rig, camera_pitch_deg=(5.0, 7.0),
                                       camera_roll_deg=(-1.8, 0.6)))
    drawn = {build_world(seq=k, frames=5, n_static=0, n_dynamic=0, seed=0,
                         config=ranged).camera_attitude for k in range(4)}
    assert len(drawn) == 4
    for pitch, roll in drawn:
        assert 5.0 <= pitch <= 7.0 and -1.8 <= roll <= 0.6
    # the default stays level: the calibration's own pitch, no attitude drawn
    assert build_world(frames=2, n_static=0, n_dynamic=0).camera_attitude is None


# --------------------------------------------------------------------------------------------
# attributes
# --------------------------------------------------------------------------------------------

def amodal_direct(world, i: int, car) -> tuple[int, int]:
    """The car rendered alone in world coordinates through every pixel of the image grown by
    one image size on each side: (pixels inside the image, pixels outside)."""
    w, h = world.rig.image_size
    K = world.rig.K.copy()
    K[0, 2] += w
    K[1, 2] += h
    dirs = pixel_directions(K, (3 * w, 3 * h))
    T = world.cam_to_world(i, 0)
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True) @ T[:3, :3].T
    alone = world.frame_mesh(i, cars=[car], with_static=False)
    hit = RayCaster(alone.vertices, alone.faces).cast(T[:3, 3], dirs).valid.reshape(3 * h, 3 * w)
    inside = hit[h:2 * h, w:2 * w].sum()
    return int(inside), int(hit.sum() - inside)


def test_attributes_file_matches_a_direct_count(tmp_path):
    cfg = small(hard_config(props=(("pedestrian", 10), ("pole", 5))), factor=8)
    exact = replace(cfg.visibility, margin_stride=1, max_rays_per_car=10 ** 7)
    cfg = replace(cfg, visibility=exact)
    summary = generate_sequence(tmp_path, seq=4, frames=3, n_static=25, n_dynamic=2, seed=9,
                                config=cfg)
    world = summary.world
    doc = read_attributes(attributes_path(tmp_path, world.sequence))
    assert doc["format"] == ATTRIBUTES_FORMAT
    assert set(doc["instances"]) == {str(c.global_id) for c in world.cars}
    for car in world.cars:
        entry = doc["instances"][str(car.global_id)]
        assert entry["vehicle_class"] == car.model.vehicle_class
        assert entry["dynamic"] == car.dynamic
        assert entry["parking"] == (None if car.dynamic else car.parking)
        assert entry["parking"] in (None, "parallel", "parallel_reversed", "angled",
                                    "perpendicular")
        assert 0.0 <= entry["angle_to_road_deg"] <= 90.0
    seq = Sequence(tmp_path, 4)
    occlusions = []
    for i, f in enumerate(summary.frames):
        imap = seq.instance_map(f)
        frame = doc["frames"][str(f)]
        for car in world.cars:
            inside, outside = amodal_direct(world, i, car)
            if inside == 0:
                assert str(car.global_id) not in frame
                continue
            visible = int(np.count_nonzero(imap == car.global_id))
            got = frame[str(car.global_id)]
            # a pixel or two may differ where a ray grazes an edge (float32, other frame)
            assert got["occlusion"] == pytest.approx(1 - visible / inside, abs=2.5 / inside + 1e-4)
            assert got["truncation"] == pytest.approx(outside / (inside + outside),
                                                      abs=3.0 / (inside + outside) + 1e-4)
            occlusions.append(got["occlusion"])
    assert max(occlusions) > 0.5 and min(occlusions) < 0.05  # rows hide cars, not all of them


def test_visibility_sampled_on_a_sparser_grid_stays_close(tmp_path):
    cfg = small(hard_config())
    world = build_world(seq=4, frames=2, n_static=25, n_dynamic=2, seed=9, config=cfg)
    imap = render_frame(world, 0)[0].instance
    dense = car_visibility(replace(world, config=replace(
        cfg, visibility=replace(cfg.visibility, max_rays_per_car=10 ** 7))), 0, imap)
    sparse = car_visibility(replace(world, config=replace(
        cfg, visibility=replace(cfg.visibility, max_rays_per_car=200))), 0, imap)
    compared = 0
    for d, s in zip(dense, sparse):
        if d.inside_px > 2000:
            assert s.occluded_fraction == pytest.approx(d.occluded_fraction, abs=0.1)
            assert s.inside_px == pytest.approx(d.inside_px, rel=0.1)
            compared += 1
    assert compared >= 1


# --------------------------------------------------------------------------------------------
# suites
# --------------------------------------------------------------------------------------------

def _set_seeds(name: str) -> set[int]:
    """Every seed of set ``name``, its rounds' and its long street's."""
    return {seed for seeds in SET_SEEDS[name] for seed in seeds} | \
        ({LONG_SEEDS[name]} if name in LONG_SEEDS else set())


def test_suites_are_disjoint_and_deterministic():
    dev, val = suite("development"), suite("validation")
    assert not _set_seeds("development") & _set_seeds("validation")
    assert not {m.seed for m in dev} & {m.seed for m in val}
    assert not {m.sequence for m in dev} & {m.sequence for m in val}
    assert [m.scenario.name for m in dev] == [m.scenario.name for m in val if m.round == 0]
    assert [m.sequence for m in select(dev, None)] == \
        [SET_SEQUENCE_BASE["development"] + k for k in range(len(SCENARIOS))]
    assert [m.scenario.frames for m in select(val, "long")] == [200]
    assert len({m.fingerprint() for m in dev + val}) == len(dev) + len(val)
    # the extra development streets: moving traffic only, seeds and numbers of their own, no long one
    traffic = suite("development-traffic")
    assert {m.scenario.name for m in traffic} == {"moving_traffic"} and all(m.default for m in traffic)
    seeds = [_set_seeds(name) for name in SET_SEEDS]
    assert sum(len(x) for x in seeds) == len(set().union(*seeds))
    assert all(len({m.seed for m in suite(name)}) == len(suite(name)) for name in SET_SEEDS)
    numbers = [{m.sequence for m in suite(name)} for name in SET_SEEDS]
    assert sum(len(x) for x in numbers) == len(set().union(*numbers))
    with pytest.raises(ValueError, match="known"):
        select(dev, "nope")
    with pytest.raises(ValueError, match="development"):
        suite("test")
    first = dev[0]
    worlds = [build_world(first.sequence, 3, first.scenario.n_static, first.scenario.n_dynamic,
                          first.seed, config=first.scenario.config) for _ in range(2)]
    assert [(c.vehicle_class, c.yaw, tuple(c.centre0)) for c in worlds[0].cars] == \
        [(c.vehicle_class, c.yaw, tuple(c.centre0)) for c in worlds[1].cars]


def test_validation_rounds_repeat_every_preset_with_seeds_and_numbers_of_their_own():
    members = select(suite("validation"), None)
    assert len(members) == len(SET_SEEDS["validation"]) * len(SCENARIOS)
    base = SET_SEQUENCE_BASE["validation"]
    for r in range(len(SET_SEEDS["validation"])):
        in_round = [m for m in members if m.round == r]
        assert [m.scenario.name for m in in_round] == [s.name for s in SCENARIOS]
        assert [m.sequence for m in in_round] == [base + ROUND_STRIDE * r + k for k in range(len(SCENARIOS))]
    # the first round alone is the set as first reported (its seeds and numbers); the long
    # street keeps its number
    assert [m.seed for m in members if m.round == 0] == [7741, 7742, 7743, 7744, 7745, 7746]
    assert [m.sequence for m in select(suite("validation"), None, 1)] == [base + k for k in range(len(SCENARIOS))]
    assert [m.sequence for m in select(suite("validation"), "long")] == [base + LONG_OFFSET]
    assert len(select(suite("validation"), "tight_rows")) == len(SET_SEEDS["validation"])
    assert len(select(suite("validation"), "tight_rows", 1)) == 1
    assert LONG_OFFSET < ROUND_STRIDE
    with pytest.raises(ValueError, match="rounds"):
        select(members, None, 0)


@pytest.mark.slow
def test_every_class_and_mesh_appears_in_both_sets():
    wanted = {c.name for c in VEHICLE_CLASSES} | {p.stem for p in bundled_mesh_paths()}
    for name in ("development", "validation"):
        seen, parking = set(), Counter()
        for m in select(suite(name), None):
            s = m.scenario
            world = build_world(m.sequence, s.frames, s.n_static, s.n_dynamic, m.seed,
                                config=s.config)
            seen |= {c.vehicle_class for c in world.cars}
            parking.update(c.parking for c in world.cars)
        assert seen == wanted, name
        assert set(parking) == {None, "parallel", "parallel_reversed", "angled", "perpendicular"}


@pytest.mark.slow
def test_synth_suite_cli_writes_and_keeps(tmp_path, capsys):
    out = tmp_path / "val"
    assert cli_main(["synth-suite", str(out), "--set", "validation", "--only", "moving_traffic",
                     "--rounds", "1", "--quiet"]) == 0
    assert "written" in capsys.readouterr().out
    seq = Sequence(out, 204)
    assert len(seq.frames) == SCENARIOS[4].frames
    assert read_attributes(attributes_path(out, seq.name))["frames"]
    assert cli_main(["synth-suite", str(out), "--set", "validation", "--only", "moving_traffic",
                     "--rounds", "1", "--quiet"]) == 0
    assert "kept" in capsys.readouterr().out


def test_lamp_faces_are_told_by_their_outward_normals():
    """Rear lamps go on faces whose outward normal points backwards, whatever the mesh's winding:
    a face normal pointing into the car is turned round."""
    from vsrd_mi.synth.render import outward

    normals = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    offsets = np.array([[2.0, 0.1, 0.5], [-2.0, 0.1, 0.5], [0.0, 0.0, 0.0]])  # front, rear, centre
    np.testing.assert_array_equal(outward(normals, offsets), [[1.0, 0, 0], [-1.0, 0, 0], [0, 0, -1.0]])
