"""Visual outputs of ``vsrd-mi autolabel --vis`` (vsrd_mi.autolabel.visualise)."""

from __future__ import annotations

import dataclasses

import json
from pathlib import Path

import cv2
import mitsuba as mi
import numpy as np
import pytest
import trimesh
from skimage.measure import label as connected_components
import vsrd_mi  # noqa: F401
from vsrd_plugins import box_properties

from vsrd_mi.autolabel import visualise as V
from vsrd_mi.autolabel.job import process_target
from vsrd_mi.batch.tasks import TargetTask
from vsrd_mi.data.kitti360 import Sequence
from vsrd_mi.data.observations import load_observations
from vsrd_mi.data.selection import SelectionConfig, select_targets
from vsrd_mi.geometry.boxes import Box3D
from vsrd_mi.geometry.camera import NEAR_PLANE, project
from vsrd_mi.optimise.config import default_config
from vsrd_mi.optimise.optimiser import BoxOptimiser
from vsrd_mi.scene.initial import default_initial_boxes

ROOT = Path(__file__).resolve().parents[1] / "scenes" / "kitti360-synth"
K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 120.0], [0.0, 0.0, 1.0]])
#: Few steps, box-only warm-up shorter than the run so the residual field is on at the end.
TINY = default_config().replace(steps=4, warmup_steps=2, init=False, residual=True,
                                weights=dataclasses.replace(default_config().weights, silhouette=1.0))
#: Small visuals for the tests.
SMALL = V.VisualConfig(sheet_scale=0.25, mask_scale=0.1, mask_sources=1, mesh_cells=24)


def read_rgb(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert img is not None, f"{path} does not decode"
    return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB if img.shape[2] == 4 else cv2.COLOR_BGR2RGB)


def colour_mask(img: np.ndarray, colour) -> np.ndarray:
    return np.all(img == np.array(colour, dtype=np.uint8), axis=-1)


# ----------------------------------------------------------------------------------------------
# Drawing primitives on hand-made boxes
# ----------------------------------------------------------------------------------------------


def test_edge_segments_clip_at_near_plane():
    box = Box3D(centre=(0.0, 0.0, 0.0), size=(2.0, 2.0, 2.0), yaw=0.0)  # straddles the camera plane
    seg = V.box_edge_segments(box, K)
    # front face (z = +1): 4 edges kept whole; back face dropped; 4 edges cut at the near plane
    assert seg.shape == (8, 2, 2)
    cut = {(round(float(x), 6), round(float(y), 6)) for x, y in seg.reshape(-1, 2)}
    for sx in (-1.0, 1.0):
        for sy in (-1.0, 1.0):
            at_plane = project(K, np.array([sx, sy, NEAR_PLANE]))
            assert (round(at_plane[0], 6), round(at_plane[1], 6)) in cut
    behind = Box3D(centre=(0.0, 0.0, -5.0), size=(2.0, 2.0, 2.0), yaw=0.3)
    assert V.box_edge_segments(behind, K).shape == (0, 2, 2)
    ahead = Box3D(centre=(0.5, 0.2, 10.0), size=(1.8, 1.5, 4.2), yaw=0.4)
    assert V.box_edge_segments(ahead, K).shape == (12, 2, 2)


def test_projected_box_edges_drawn_in_box_colour():
    image = np.zeros((240, 640, 3), np.uint8)
    box = Box3D(centre=(0.0, 0.0, 10.0), size=(2.0, 2.0, 2.0), yaw=0.0)
    colour = (250, 40, 30)
    out = V.draw_projected_boxes(image, [box], K, [colour], ["26001: 0.90"])
    assert out.shape == image.shape and not np.shares_memory(out, image) and image.max() == 0
    for a, b in ([-1, -1, 9], [1, -1, 9]), ([1, -1, 9], [1, 1, 9]), ([-1, 1, 11], [-1, -1, 11]):
        u, v = project(K, 0.5 * (np.array(a, float) + np.array(b, float)))  # edge midpoint
        assert tuple(out[int(round(v)), int(round(u))]) == colour
    assert tuple(out[120, 320]) == (0, 0, 0)  # box centre: no face fill


def test_bev_draws_each_box_once():
    pred = [Box3D((-8.0, 0.0, 15.0), (1.8, 1.5, 4.3), 0.2), Box3D((6.0, 0.0, 25.0), (1.9, 1.6, 4.6), -0.5),
            Box3D((0.0, 0.0, 40.0), (2.0, 1.7, 5.0), 1.2)]
    gt = [Box3D((-14.0, 0.0, 12.0), (1.8, 1.5, 4.3), 0.0), Box3D((12.0, 0.0, 30.0), (1.8, 1.5, 4.3), 0.7)]
    colours = V.box_colours(len(pred))
    cfg = V.VisualConfig()
    img = V.draw_bev(pred, gt, colours, [], cfg)
    for c in colours:
        assert connected_components(colour_mask(img, c), connectivity=2).max() == 1
    assert connected_components(colour_mask(img, V.BEV_GT), connectivity=2).max() == 2
    # the region covers the boxes and the camera plus the margin
    frame = V.bev_frame(pred + gt, cfg)
    assert img.shape == (frame.height, frame.width, 3)
    col, row = frame.to_pixels(np.array([0.0, 0.0]))
    assert 0 <= col < frame.width and 0 <= row < frame.height
    no_gt = V.draw_bev(pred, [], colours, [f"{i}: 0.5" for i in range(3)], cfg)
    assert not colour_mask(no_gt, V.BEV_GT).any()
    assert all(colour_mask(no_gt, c).any() for c in colours)


def test_box_only_mesh_fills_its_box():
    box = Box3D(centre=(1.0, 0.5, 12.0), size=(1.8, 1.5, 4.4), yaw=0.6)
    props = box_properties(box.centre[None], box.size[None], [box.yaw])
    field = mi.load_dict({"type": "vsrd_silhouette", **props}).field
    mesh, spacing = V.instance_mesh(field, box, 0, (255, 0, 0), V.VisualConfig(mesh_cells=32))
    assert mesh.is_watertight
    local = (np.asarray(mesh.vertices) - box.centre) @ box.rotation
    assert np.all(np.abs(local) <= 0.5 * box.size + spacing)
    assert np.abs(local).max(0) == pytest.approx(0.5 * box.size, abs=spacing)
    # marching cubes rounds the edges by about one cell
    assert 0.85 * np.prod(box.size) < mesh.volume <= np.prod(box.size)


# ----------------------------------------------------------------------------------------------
# The writer on a tiny optimisation of the bundled scene
# ----------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    seq = Sequence(ROOT, 0)
    spec = select_targets(seq, SelectionConfig())[0]
    obs = load_observations(seq, spec)
    optimiser = BoxOptimiser(obs, default_initial_boxes(obs), TINY)
    result = optimiser.run()
    conf = np.linspace(0.2, 0.9, len(result.boxes))
    out = tmp_path_factory.mktemp("vis") / "target"
    report = V.write_visuals(out, seq, optimiser, result, conf, SMALL)
    return seq, obs, optimiser, result, out, report


def test_writer_files_and_image_sizes(tiny_run):
    seq, obs, optimiser, result, out, report = tiny_run
    assert report.warnings == []
    names = {p.relative_to(out).as_posix() for p in report.files}
    meshes = {f"meshes/instance_{b.instance_id}.ply" for b in result.boxes}
    assert names == {"boxes_target.png", "boxes_sources.png", "masks.png", "bev.png", "loss.png"} | meshes
    assert all(p.is_file() for p in report.files)
    W, H = obs.image_size
    target = read_rgb(out / "boxes_target.png")
    assert target.shape == (H, W, 3)
    assert not np.array_equal(target, seq.image(int(obs.frames[0])))  # boxes were drawn
    w, h = V.scaled_size(obs.image_size, SMALL.sheet_scale)
    n_src = len(V.source_indices(obs))
    rows = -(-n_src // SMALL.sheet_columns)
    assert read_rgb(out / "boxes_sources.png").shape == (rows * h, SMALL.sheet_columns * w, 3)
    w, h = V.scaled_size(obs.image_size, SMALL.mask_scale)
    frames_shown = 1 + SMALL.mask_sources
    assert read_rgb(out / "masks.png").shape == (frames_shown * h + 4 * (frames_shown - 1), 2 * w + 4, 3)
    fw, fh = SMALL.loss_figsize
    assert read_rgb(out / "loss.png").shape == (round(fh * SMALL.loss_dpi), round(fw * SMALL.loss_dpi), 3)
    assert len(report.mask_iou) == frames_shown and int(obs.frames[0]) in report.mask_iou
    assert all(0.0 <= v <= 1.0 for v in report.mask_iou.values())
    summary = report.to_dict(relative_to=out)
    assert sorted(summary["files"]) == sorted(names) and summary["warnings"] == []


def test_writer_bev_shows_boxes_and_ground_truth(tiny_run):
    _, obs, _, result, out, _ = tiny_run
    bev = read_rgb(out / "bev.png")
    for c in V.box_colours(len(result.boxes)):
        assert colour_mask(bev, c).sum() > 20
    assert colour_mask(bev, V.BEV_GT).sum() > 20  # the bundled sequence has ground truth


def test_writer_meshes_lie_in_their_boxes(tiny_run):
    _, _, optimiser, result, out, report = tiny_run
    assert optimiser.integrator.field.use_residual  # the meshes include the residual field
    for box in result.boxes:
        mesh = trimesh.load(out / "meshes" / f"instance_{box.instance_id}.ply")
        assert len(mesh.faces) > 100 and mesh.volume > 0
        spacing = report.mesh_spacing[box.instance_id]
        local = (np.asarray(mesh.vertices) - box.centre) @ box.rotation
        assert np.all(np.abs(local) <= 0.5 * box.size + spacing), box.instance_id
        assert mesh.volume <= np.prod(box.size)


def test_autolabel_vis_failure_is_a_warning(tmp_path, monkeypatch):
    """``--vis`` writes labels first; a visual that fails is a warning, not a failed target."""

    def broken(*args, **kwargs):
        raise RuntimeError("no BEV today")

    monkeypatch.setattr(V, "write_bev", broken)
    seq = Sequence(ROOT, 0)
    frame = select_targets(seq, SelectionConfig())[0].target
    cfg = TINY.replace(steps=3, residual=False)  # box-only: fast soft-mask renders
    task = TargetTask(root=str(ROOT), sequence=seq.name, frame=frame, output_dir=str(tmp_path),
                      config={**cfg.to_dict(), "vis": True})
    result = process_target(task)
    assert result.status == "done"
    seq_dir = task.sequence_dir
    assert (seq_dir / f"labels/{frame:010d}.txt").is_file()
    summary = json.loads((seq_dir / f"boxes/{frame:010d}.json").read_text())
    assert "vis" not in summary["config"]
    vis = summary["visuals"]
    assert len(vis["warnings"]) == 1 and vis["warnings"][0].startswith("bev: RuntimeError: no BEV today")
    assert f"vis/{frame:010d}/masks.png" in vis["files"] and f"vis/{frame:010d}/bev.png" not in vis["files"]
    assert set(vis["files"]) <= set(result.outputs)
    assert all((seq_dir / p).is_file() for p in result.outputs)
