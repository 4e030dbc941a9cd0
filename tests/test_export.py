"""``vsrd-mi export-dataset`` (KITTI layout, calib, --level) and ``vsrd-mi report`` on the bundled
scene and on a generated synthetic sequence."""

from __future__ import annotations

import html.parser
import itertools
import json
import math
import os
import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest

from vsrd_mi.cli import main
from vsrd_mi.data.kitti360 import (
    Sequence,
    read_calibration,
    read_world_boxes,
    sequence_name,
)
from vsrd_mi.data.kitti_labels import (
    box_from_label,
    label_from_box,
    read_labels,
    write_labels,
)
from vsrd_mi.data.labels import CAR_KITTI_ID, car_instance_value
from vsrd_mi.data.masks import tight_box
from vsrd_mi.errors import DataError
from vsrd_mi.export.calib import (
    CALIB_KEYS,
    VELO_TO_CAM,
    calib_for_frame,
    imu_to_camera,
    read_calib,
    write_calib,
)
from vsrd_mi.export.dataset import ExportConfig, collect_frames, export_dataset
from vsrd_mi.export.level import (
    apply_homography,
    level_box,
    level_homography,
    level_image,
    level_rotation,
)
from vsrd_mi.export.report import ReportConfig, write_report
from vsrd_mi.geometry.boxes import Box3D
from vsrd_mi.geometry.boxes2d import iou_matrix
from vsrd_mi.geometry.camera import box_to_2d, footprint, image_bounds, transform_points
from vsrd_mi.synth import generate_sequence
from vsrd_mi.synth.config import RigConfig, SynthConfig

ROOT = Path(__file__).resolve().parents[1] / "scenes" / "kitti360-synth"
BUNDLED = sequence_name(0)
SYNTH_SEQ = 5
#: Unit-box template of KITTI-360's XML (local x = length, y = width, z = height).
UNIT = np.array(list(itertools.product((-0.5, 0.5), repeat=3)))


# ----------------------------------------------------------------------------------------------
# Fixtures: a real (short) autolabel run of the bundled scene, and a synthetic sequence with a
# run written from its ground truth the way autolabel writes labels
# ----------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def bundled_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("bundled") / "run"
    assert main(["autolabel", str(ROOT), "--sequence", "0", "--out", str(out), "--frames", "14-14",
                 "--steps", "3", "--no-residual", "--no-init", "--vis"]) == 0
    return out


@pytest.fixture(scope="module")
def synth_root(tmp_path_factory) -> Path:
    """6 frames at half KITTI-360 resolution; the rig is pitched like KITTI-360's (about 6 deg)."""
    s = 0.5
    rig = RigConfig(image_size=(int(1408 * s), int(376 * s)), fx=552.554261 * s, fy=552.554261 * s,
                    cx=682.049453 * s, cy=238.769549 * s)
    root = tmp_path_factory.mktemp("synth") / "kitti360"
    generate_sequence(root, seq=SYNTH_SEQ, frames=6, n_static=4, n_dynamic=1, seed=11, config=SynthConfig(rig=rig))
    return root


def world_corners(seq: Sequence, frame: int) -> dict[int, np.ndarray]:
    """Exact world corners (8, 3) of the cars of ``frame``, by instance-map value, from the XML."""
    out = {}
    for wb in read_world_boxes(seq.boxes_path):
        present = wb.timestamp == frame if wb.dynamic else wb.start_frame <= frame <= wb.end_frame
        if wb.kitti_id == CAR_KITTI_ID and present:
            out[car_instance_value(wb.instance_id)] = UNIT @ wb.transform[:3, :3].T + wb.transform[:3, 3]
    return out


def exact_box2d(corners_world: np.ndarray, world_to_cam: np.ndarray, K: np.ndarray, size) -> np.ndarray | None:
    """2D footprint of exact world corners in a camera (the way autolabel's labels get theirs)."""
    cam = transform_points(world_to_cam, corners_world)
    x1, y1, x2, y2, valid = footprint([tuple(c) for c in cam], K, image_bounds(size))
    return np.array([x1, y1, x2, y2]) if valid else None


def ground_truth_run(root: Path, seq_no: int, out: Path) -> Path:
    """A run folder whose labels are the ground truth written as autolabel writes its labels
    (3D box in the camera frame, 2D box the exact projection through the pose), scores 0.3 / 0.6 / 0.9."""
    seq = Sequence(root, seq_no)
    K, size = seq.calibration.K, seq.calibration.image_size
    labels_dir = out / seq.name / "labels"
    for f in seq.frames:
        corners = world_corners(seq, f)
        labels = []
        for k, box in enumerate(seq.ground_truth(f)):
            b2 = exact_box2d(corners[box.instance_id], np.linalg.inv(seq.cam0_to_world(f)), K, size)
            if b2 is not None:
                labels.append(label_from_box(box, b2, score=0.3 + 0.3 * (k % 3)))
        write_labels(labels_dir / f"{f:010d}.txt", labels)
    return out


@pytest.fixture(scope="module")
def synth_run(synth_root, tmp_path_factory) -> Path:
    return ground_truth_run(synth_root, SYNTH_SEQ, tmp_path_factory.mktemp("synth_run") / "run")


# ----------------------------------------------------------------------------------------------
# Reading the export back as the KITTI object devkit's readme specifies it
# ----------------------------------------------------------------------------------------------


def parse_devkit_label_line(line: str) -> dict:
    """One object line: type, truncated (float), occluded (int 0-3), alpha, bbox (4), dimensions
    (h, w, l), location (x, y, z), rotation_y, and for results a 16th value, the score."""
    v = line.split(" ")
    assert len(v) in (15, 16), line
    assert v[0] in ("Car", "Van", "Truck", "Pedestrian", "Person_sitting", "Cyclist", "Tram", "Misc", "DontCare")
    out = {"type": v[0], "truncated": float(v[1]), "occluded": int(v[2]), "alpha": float(v[3]),
           "bbox": [float(x) for x in v[4:8]], "dimensions": [float(x) for x in v[8:11]],
           "location": [float(x) for x in v[11:14]], "rotation_y": float(v[14]),
           "score": float(v[15]) if len(v) == 16 else None}
    assert 0.0 <= out["truncated"] <= 1.0 and out["occluded"] in (0, 1, 2, 3)
    assert -math.pi <= out["alpha"] <= math.pi and -math.pi <= out["rotation_y"] <= math.pi
    x1, y1, x2, y2 = out["bbox"]
    assert x1 <= x2 and y1 <= y2 and min(out["dimensions"]) > 0
    return out


def parse_devkit_calib(path: Path) -> dict[str, np.ndarray]:
    """``KEY: values`` lines with 12 floats for P0-P3, Tr_velo_to_cam, Tr_imu_to_velo and 9 for R0_rect,
    read by line number as MonoDETR's ``get_calib_from_file`` does for P2 (line 3) and P3 (line 4)."""
    lines = path.read_text().splitlines()
    keys = [line.split(":")[0] for line in lines if line]
    assert keys == ["P0", "P1", "P2", "P3", "R0_rect", "Tr_velo_to_cam", "Tr_imu_to_velo"]
    out = {}
    for line in lines:
        if line:
            key, values = line.split(": ")
            numbers = [float(x) for x in values.split(" ")]
            assert len(numbers) == (9 if key == "R0_rect" else 12), key
            out[key] = np.array(numbers)
    assert np.array_equal(np.array(lines[2].split(" ")[1:], dtype=float), out["P2"])
    return out


def read_export(out: Path) -> dict:
    """Every file of an export, parsed (and checked to exist) through its indices."""
    mapping = [line.split(" ") for line in (out / "mapping.txt").read_text().splitlines()]
    sets = {name: (out / "ImageSets" / f"{name}.txt").read_text().split()
            for name in ("train", "val", "trainval", "test")}
    indices = [f"{i:06d}" for i in range(len(mapping))]
    assert sorted(sets["train"] + sets["val"]) == indices == sets["trainval"] and sets["test"] == []
    frames = {}
    for i, (seq, frame) in zip(indices, mapping):
        image = out / "training" / "image_2" / f"{i}.png"
        assert cv2.imread(str(image)) is not None, image
        labels = [parse_devkit_label_line(line) for line in
                  (out / "training" / "label_2" / f"{i}.txt").read_text().splitlines()]
        frames[i] = {"sequence": seq, "frame": int(frame), "image": image, "labels": labels,
                     "calib": parse_devkit_calib(out / "training" / "calib" / f"{i}.txt")}
    assert sorted(p.stem for p in (out / "training" / "label_2").iterdir()) == indices
    return {"frames": frames, "sets": sets}


def run_label_files(run: Path) -> dict[tuple[str, int], Path]:
    return {(p.parent.parent.name, int(p.stem)): p for p in run.glob("*/labels/*.txt")}


# ----------------------------------------------------------------------------------------------
# export-dataset
# ----------------------------------------------------------------------------------------------


def test_export_of_two_runs_reads_back_as_kitti(bundled_run, synth_run, synth_root, tmp_path, capsys):
    out = tmp_path / "kitti"
    assert main(["export-dataset", str(out), "--from", str(bundled_run), str(synth_run),
                 "--root", str(ROOT), str(synth_root)]) == 0
    assert "frames" in capsys.readouterr().out
    got = read_export(out)
    sources = {**run_label_files(bundled_run), **run_label_files(synth_run)}
    keys = [(f["sequence"], f["frame"]) for f in got["frames"].values()]
    assert keys == sorted(sources) and len(set(keys)) == len(keys)  # every labelled frame once, in order
    for i, f in got["frames"].items():
        run_lines = sources[(f["sequence"], f["frame"])].read_text().splitlines()
        assert [parse_devkit_label_line(line) for line in run_lines] == f["labels"]
        assert f["labels"] == [] or all(lab["score"] is not None for lab in f["labels"])
        root = ROOT if f["sequence"] == BUNDLED else synth_root
        link = os.readlink(f["image"])
        assert not os.path.isabs(link)  # relative symlink
        assert f["image"].resolve() == Sequence(root, f["sequence"]).image_path(f["frame"]).resolve()
        K = read_calibration(root).P_rect_00
        np.testing.assert_allclose(f["calib"]["P2"].reshape(3, 4), K)
        np.testing.assert_allclose(f["calib"]["R0_rect"], np.eye(3).ravel())
    # validation: the last 20 % of each sequence's frames
    for seq in (BUNDLED, sequence_name(SYNTH_SEQ)):
        idx = [i for i, f in got["frames"].items() if f["sequence"] == seq]
        n_val = round(0.2 * len(idx))
        assert [i for i in idx if i in got["sets"]["val"]] == idx[len(idx) - n_val:]
    summary = json.loads((out / "export.json").read_text())
    assert summary["n_frames"] == len(keys) and summary["frames"][0]["labels_from"]


def test_min_score_copy_and_split_by_sequences(bundled_run, synth_run, synth_root, tmp_path):
    out = tmp_path / "kitti"
    summary = export_dataset(out, [bundled_run, synth_run], [ROOT, synth_root],
                             ExportConfig(min_score=0.5, copy_images=True, split_by="sequences", val_fraction=0.5))
    got = read_export(out)
    for f in got["frames"].values():
        assert all(lab["score"] >= 0.5 for lab in f["labels"])
        assert not f["image"].is_symlink()
        root = ROOT if f["sequence"] == BUNDLED else synth_root
        assert f["image"].read_bytes() == Sequence(root, f["sequence"]).image_path(f["frame"]).read_bytes()
    synth_frames = [f for f in got["frames"].values() if f["sequence"] == sequence_name(SYNTH_SEQ)]
    assert sum(len(f["labels"]) for f in synth_frames) < sum(
        len(read_labels(p)) for p in run_label_files(synth_run).values())  # the 0.3 scores are gone
    val = {got["frames"][i]["sequence"] for i in got["sets"]["val"]}
    assert val == {sequence_name(SYNTH_SEQ)} and summary["n_val"] == len(synth_frames)
    with pytest.raises(DataError, match="already holds an export"):
        export_dataset(out, [bundled_run], [ROOT])
    summary = export_dataset(out, [bundled_run], [ROOT], ExportConfig(force=True, val_sequences=(BUNDLED,)))
    assert summary["n_train"] == 0 and read_export(out)["sets"]["val"] == [f"{i:06d}" for i in range(summary["n_frames"])]


def test_bad_input_names_the_problem(bundled_run, synth_root, tmp_path, capsys):
    empty = tmp_path / "not_a_run"
    empty.mkdir()
    assert main(["export-dataset", str(tmp_path / "o1"), "--from", str(empty), "--root", str(ROOT)]) == 1
    assert str(empty) in capsys.readouterr().err
    labels = tmp_path / "empty_labels" / BUNDLED / "labels"
    labels.mkdir(parents=True)
    with pytest.raises(DataError, match="no label files") as info:
        export_dataset(tmp_path / "o2", [labels.parent.parent], [ROOT])
    assert str(labels) in str(info.value)
    # a label file of a frame whose image is missing
    copy = tmp_path / "copy_run"
    shutil.copytree(bundled_run, copy)
    write_labels(copy / BUNDLED / "labels" / "0000000999.txt", [])
    with pytest.raises(DataError, match="missing image") as info:
        export_dataset(tmp_path / "o3", [copy], [ROOT])
    assert "0000000999.png" in str(info.value) and not (tmp_path / "o3").exists()  # nothing written
    (copy / BUNDLED / "labels" / "0000000999.txt").write_text("Car 0 0 0 1 2 3\n")
    with pytest.raises(DataError, match="line 1"):
        export_dataset(tmp_path / "o4", [copy], [ROOT])
    (copy / BUNDLED / "labels" / "0000000999.txt").unlink()
    with pytest.raises(DataError, match="also labelled by"):
        collect_frames([bundled_run, copy], [ROOT])
    assert len(collect_frames([bundled_run, copy], [ROOT], duplicates="first")) == len(run_label_files(bundled_run))
    with pytest.raises(DataError, match="two dataset roots"):
        collect_frames([bundled_run, copy], [ROOT, synth_root])
    with pytest.raises(ValueError, match="one per run"):
        collect_frames([bundled_run], [ROOT, synth_root])


# ----------------------------------------------------------------------------------------------
# Calib and --level
# ----------------------------------------------------------------------------------------------


def test_calib_round_trip_and_frames(synth_root, tmp_path):
    calibration = read_calibration(synth_root)
    seq = Sequence(synth_root, SYNTH_SEQ)
    R = level_rotation(seq.cam0_to_world(seq.frames[0]))
    for level in (None, R):
        calib = calib_for_frame(calibration, level)
        path = tmp_path / "c.txt"
        write_calib(path, calib)
        back = read_calib(path)
        for key in CALIB_KEYS:
            np.testing.assert_allclose(getattr(back, key), getattr(calib, key), rtol=1e-12, atol=1e-12)
        # P3 sees a level-frame point where the right camera, turned level about its centre, sees it
        p_rect = np.array([1.5, 0.8, 12.0])
        p = p_rect if level is None else R @ p_rect
        uv = calib.P3 @ np.append(p, 1.0)
        uv_rect = calibration.P_rect_01 @ np.append(p_rect, 1.0)
        uv_rect = uv_rect[:2] / uv_rect[2]
        if level is not None:
            uv_rect = apply_homography(level_homography(calibration.P_rect_01[:, :3], R), uv_rect)[0]
        np.testing.assert_allclose(uv[:2] / uv[2], uv_rect, atol=1e-9)
        # velodyne axes: x forward, y left, z up of the (level) camera; IMU chain as KITTI-360 states it
        np.testing.assert_allclose(calib.Tr_velo_to_cam[:, :3], VELO_TO_CAM)
        imu_to_cam = calib.Tr_velo_to_cam[:, :3] @ calib.Tr_imu_to_velo[:, :3]
        expected = imu_to_camera(calibration)[:3, :3]
        np.testing.assert_allclose(imu_to_cam, expected if level is None else R @ expected, atol=1e-12)
    (tmp_path / "bad.txt").write_text(path.read_text().replace("P2:", "P9:"))
    with pytest.raises(DataError, match="line 3: expected key 'P2'"):
        read_calib(tmp_path / "bad.txt")


def test_level_box_is_the_upright_box_of_a_pitched_rolled_camera():
    """A box upright in the world, seen by a camera pitched 6 deg and rolled 1 deg: the label box
    (yaw only) stands along the camera's y axis; its level box has the world box's exact corners."""
    pitch, roll = math.radians(6.0), math.radians(1.0)
    Rx = np.array([[1, 0, 0], [0, math.cos(pitch), -math.sin(pitch)], [0, math.sin(pitch), math.cos(pitch)]])
    Rz = np.array([[math.cos(roll), -math.sin(roll), 0], [math.sin(roll), math.cos(roll), 0], [0, 0, 1]])
    cam_to_level = (Rz @ Rx).T  # level -> camera is Rz @ Rx (rows of the level rotation)
    g_to_world = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])  # y-down level frame -> z-up world
    cam_to_world = np.eye(4)
    cam_to_world[:3, :3] = g_to_world @ cam_to_level
    R = level_rotation(cam_to_world)
    np.testing.assert_allclose(R, cam_to_level, atol=1e-12)
    upright = Box3D(centre=(3.0, 1.1, 18.0), size=(1.8, 1.5, 4.3), yaw=0.7)  # in the level frame
    to_cam = np.eye(4)
    to_cam[:3, :3] = cam_to_level.T
    label_box = upright.transformed(to_cam)  # what a label can hold (heading projected)
    assert np.abs(label_box.corners() - transform_points(to_cam, upright.corners())).max() > 0.05
    np.testing.assert_allclose(level_box(label_box, R).corners(), upright.corners(), atol=1e-9)


def test_level_export_labels_land_on_their_boxes(synth_run, synth_root, tmp_path):
    out = tmp_path / "level"
    plain = tmp_path / "plain"
    export_dataset(out, [synth_run], [synth_root], ExportConfig(level=True))
    export_dataset(plain, [synth_run], [synth_root])
    seq = Sequence(synth_root, SYNTH_SEQ)
    K, size = seq.calibration.K, seq.calibration.image_size
    level_ious, plain_ious, exact_ious = [], [], []
    for (i, f), (_, p) in zip(read_export(out)["frames"].items(), read_export(plain)["frames"].items()):
        R = level_rotation(seq.cam0_to_world(f["frame"]))
        P2 = f["calib"]["P2"].reshape(3, 4)
        np.testing.assert_allclose(P2[:, :3], K)
        np.testing.assert_allclose(P2[:, 3], 0.0)
        labels = read_labels(out / "training" / "label_2" / f"{i}.txt")
        corners = world_corners(seq, f["frame"])
        world_to_level = np.eye(4)
        world_to_level[:3, :3] = R
        world_to_level = world_to_level @ np.linalg.inv(seq.cam0_to_world(f["frame"]))
        for lab in labels:
            projected = box_to_2d(box_from_label(lab), P2[:, :3], image_size=size)
            level_ious.append(iou_matrix(projected[None], np.array(lab.box2d)[None])[0, 0])
            # against the exact world box seen by the level camera: the car it labels
            exact = [exact_box2d(c, world_to_level, K, size) for c in corners.values()]
            exact_ious.append(max(iou_matrix(projected[None], e[None])[0, 0] for e in exact if e is not None))
        for lab in read_labels(plain / "training" / "label_2" / f"{i}.txt"):
            projected = box_to_2d(box_from_label(lab), K, image_size=size)
            plain_ious.append(iou_matrix(projected[None], np.array(lab.box2d)[None])[0, 0])
        image = cv2.imread(str(f["image"]))
        assert image.shape[:2] == (size[1], size[0]) and not f["image"].is_symlink()
        assert image[0].max() == 0  # the band above the original image's top edge is black
    assert len(level_ious) >= 10 and min(level_ious) >= 0.95 and min(exact_ious) >= 0.95, (level_ious, exact_ious)
    assert np.median(plain_ious) < 0.95  # without --level the labels' boxes miss their 2D boxes
    summary = json.loads((out / "export.json").read_text())
    assert all(5.0 < e["pitch_deg"] < 7.0 for e in summary["frames"])


def test_level_image_warp_matches_the_homography(synth_root):
    seq = Sequence(synth_root, SYNTH_SEQ)
    f = seq.frames[2]
    K = seq.calibration.K
    R = level_rotation(seq.cam0_to_world(f))
    inst = seq.instance_map(f)
    warped = level_image(inst, K, R, nearest=True)
    H = level_homography(K, R)
    checked = 0
    for value in np.unique(inst):
        if value < 26001 or (inst == value).sum() < 400:
            continue
        ys, xs = np.nonzero(inst == value)
        mapped = apply_homography(H, np.stack([xs, ys], 1))
        expected = np.array([mapped[:, 0].min() - 0.5, mapped[:, 1].min() - 0.5,
                             mapped[:, 0].max() + 0.5, mapped[:, 1].max() + 0.5])
        bounds = image_bounds(seq.calibration.image_size)  # the warp pushes part of some cars out of the image
        expected = np.concatenate([np.maximum(expected[:2], bounds[:2]), np.minimum(expected[2:], bounds[2:])])
        got = tight_box(warped == value)
        assert iou_matrix(got[None], expected[None])[0, 0] > 0.9, value
        checked += 1
    assert checked >= 2


# ----------------------------------------------------------------------------------------------
# report
# ----------------------------------------------------------------------------------------------


class _Refs(html.parser.HTMLParser):
    def __init__(self):
        super().__init__()
        self.refs: list[tuple[str, str]] = []

    def handle_starttag(self, tag, attrs):
        for name, value in attrs:
            if (tag, name) in (("img", "src"), ("a", "href")):
                self.refs.append((tag, value))


def page_refs(page: Path) -> list[tuple[str, str]]:
    parser = _Refs()
    parser.feed(page.read_text())
    return parser.refs


def assert_refs_resolve(page: Path) -> int:
    refs = page_refs(page)
    for tag, ref in refs:
        if ref.startswith("#"):
            continue
        assert "://" not in ref and not ref.startswith("/"), ref  # relative only
        assert (page.parent / ref).is_file(), ref
    return sum(1 for tag, _ in refs if tag == "img")


def test_report_of_a_run_with_visuals(bundled_run, capsys):
    assert main(["report", str(bundled_run), "--root", str(ROOT), "--review-below", "0.99"]) == 0
    page = Path(capsys.readouterr().out.strip())
    assert page == bundled_run / "report" / "index.html"
    assert assert_refs_resolve(page) == 5  # target, sources, masks, bev, loss
    text = page.read_text()
    assert "1</b> target(s): done 1" in text and "mask</b>" in text and "AP_3D@0.5" in text
    result = json.loads(next((bundled_run / BUNDLED / "boxes").glob("*.json")).read_text())
    n_boxes = len(result["boxes"])
    assert text.count('<tr class="review">') == sum(b["confidence"] < 0.99 for b in result["boxes"]) > 0
    assert text.count("<td>parked</td>") + text.count("<td>moving</td>") == n_boxes
    assert "meshes (PLY)" in text


def test_report_without_visuals_renders_them(synth_root, tmp_path):
    """A synthetic run without --vis: the report draws boxes and the bird's-eye view itself; without
    the dataset it says what is missing."""
    out = tmp_path / "run"
    assert main(["autolabel", str(synth_root), "--sequence", str(SYNTH_SEQ), "--out", str(out), "--frames", "2-3",
                 "--steps", "2", "--no-residual", "--no-init"]) == 0
    page = write_report(out, synth_root, ReportConfig(rendered_sources=2))
    n_images = assert_refs_resolve(page)
    n_targets = len(list((out / sequence_name(SYNTH_SEQ) / "boxes").glob("*.json")))
    assert n_targets >= 1 and n_images == 3 * n_targets
    text = page.read_text()
    assert "No <code>vis/</code> folder: rendered" in text
    page = write_report(out, None)
    assert assert_refs_resolve(page) == 0
    assert "no dataset was given" in page.read_text() and "No evaluation: no dataset given" in page.read_text()
    with pytest.raises(DataError, match="no labels/ folder"):
        write_report(tmp_path)


CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync"]


@pytest.mark.slow
def test_report_draws_in_a_browser(bundled_run, tmp_path):
    """Headless Chromium opens the page from disk: the screenshot is not blank and the page's own
    check finds every image drawn (naturalWidth > 0)."""
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        pytest.skip("chromium is not installed (Debian: apt-get install -y chromium)")
    page = write_report(bundled_run, ROOT)
    url = page.resolve().as_uri()
    shot = tmp_path / "shot.png"
    base = [chromium, *CHROMIUM_FLAGS]
    subprocess.run(base + [f"--user-data-dir={tmp_path / 'profile1'}", "--window-size=1400,3000",
                           f"--screenshot={shot}", url], check=True, capture_output=True, timeout=120)
    img = cv2.imread(str(shot))
    assert img is not None and img.shape[:2] == (3000, 1400)
    assert img.std() > 20 and len(np.unique(img.reshape(-1, 3), axis=0)) > 1000  # pictures, not a blank page
    dom = subprocess.run(base + [f"--user-data-dir={tmp_path / 'profile2'}", "--virtual-time-budget=10000",
                                 "--dump-dom", url], check=True, capture_output=True, timeout=120, text=True).stdout
    check = dom[dom.index('id="image-check"'):].split(">")[0]
    total = int(check.split('data-total="')[1].split('"')[0])
    drawn = int(check.split('data-drawn="')[1].split('"')[0])
    assert total == 5 and drawn == total, check


def test_eval_of_a_ground_truth_run_on_a_generated_sequence(synth_run, synth_root, capsys):
    """The ground truth written as labels, evaluated under the mask protocol: every counted car
    found, AP and AOS 100, headings right; the projection protocol counts hidden cars too."""
    assert main(["eval", "--pred", str(synth_run), "--gt", str(synth_root), "--sequence", str(SYNTH_SEQ),
                 "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    hard = result["ap"]["3d"]["0.7"]["hard"]
    assert hard["n_gt"] > 0 and hard["R40"] == pytest.approx(100.0) and hard["AOS_R40"] == pytest.approx(100.0, abs=1e-3)
    assert result["pairs"]["all"]["heading_accuracy"] == 1.0 and result["pairs"]["all"]["missed_share"] == 0.0
    assert result["pairs"]["all"]["mean_iou_3d"] == pytest.approx(1.0, abs=1e-5)
    assert main(["eval", "--pred", str(synth_run), "--gt", str(synth_root), "--sequence", str(SYNTH_SEQ),
                 "--json", "--gt-boxes", "projected"]) == 0
    projected = json.loads(capsys.readouterr().out)
    assert projected["counts"]["hard"]["n_gt"] >= result["counts"]["hard"]["n_gt"]


def test_report_lists_failures_and_differing_settings(bundled_run, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(bundled_run, run)
    seq_dir = run / BUNDLED
    shutil.rmtree(run / "report", ignore_errors=True)
    result_path = next((seq_dir / "boxes").glob("*.json"))
    other = json.loads(result_path.read_text())
    other.update(target=15, config={**other["config"], "steps": 7})
    (seq_dir / "boxes" / "0000000015.json").write_text(json.dumps(other))
    manifest = json.loads((seq_dir / "manifest.json").read_text())
    manifest["targets"]["0000000016"] = {"frame": 16, "status": "failed", "seconds": 1.5,
                                         "error": {"type": "RuntimeError", "message": "out of memory"}}
    (seq_dir / "manifest.json").write_text(json.dumps(manifest))
    page = write_report(run, None)
    text = page.read_text()
    assert "3</b> target(s): done 2, failed 1" in text
    assert "Failed targets" in text and "out of memory" in text and "No result file. Error:" in text
    assert "settings that differ between targets</td><td>steps" in text
    assert assert_refs_resolve(page) == 5  # the one target with vis/; the copied result has none
