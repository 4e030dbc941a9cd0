"""Depth for the initialisation: SGBM on synthetic and real stereo, depth-map files, ground plane."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from vsrd_mi.errors import DataError
from vsrd_mi.init.config import InitConfig, StereoConfig
from vsrd_mi.init.depth import (DepthDirectory, depth_to_disparity, disparity_to_depth,
                                load_depth_map, make_depth_source, matching_region, save_depth_png,
                                stereo_depth, stereo_depth_in, stereo_disparity)
from vsrd_mi.init.ground import GroundConfig, fit_ground_plane, road_points
from vsrd_mi.init.pointcloud import warp_error

REAL = Path("/work/shared/data/kitti360-real-0000")
SEQ = "2013_05_28_drive_0000_sync"


def textured_pair(disparity: int, h: int = 120, w: int = 320, seed: int = 0):
    """A random-texture left image and the right image of a fronto-parallel plane at depth
    f*B/disparity: a scene point at left column u appears at right column u - disparity."""
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, (h // 2, (w + disparity) // 2, 3), dtype=np.uint8)
    wide = cv2.resize(small, ((w + disparity), h), interpolation=cv2.INTER_LINEAR)
    left = np.ascontiguousarray(wide[:, :w])
    right = np.ascontiguousarray(wide[:, disparity:disparity + w])
    return left, right


def test_disparity_depth_round_trip_and_invalid():
    disp = np.array([[10.0, 0.0], [np.nan, 2.5]], dtype=np.float32)
    depth = disparity_to_depth(disp, focal=500.0, baseline=0.5)
    assert depth[0, 0] == pytest.approx(25.0)
    assert depth[1, 1] == pytest.approx(100.0)
    assert np.isnan(depth[0, 1]) and np.isnan(depth[1, 0])
    back = depth_to_disparity(depth, focal=500.0, baseline=0.5)
    assert back[0, 0] == pytest.approx(10.0) and np.isnan(back[0, 1])
    capped = disparity_to_depth(disp, focal=500.0, baseline=0.5, max_depth=50.0)
    assert np.isnan(capped[1, 1]) and capped[0, 0] == pytest.approx(25.0)


@pytest.mark.parametrize("d_true", [7, 23])
def test_sgbm_recovers_known_disparity(d_true):
    left, right = textured_pair(d_true)
    cfg = StereoConfig(num_disparities=32)
    disp = stereo_disparity(left, right, cfg)
    interior = disp[10:-10, 40:-10]
    valid = np.isfinite(interior)
    assert valid.mean() > 0.8
    assert np.median(interior[valid]) == pytest.approx(d_true, abs=0.25)
    K = np.array([[400.0, 0, 160], [0, 400.0, 60], [0, 0, 1]])
    depth = stereo_depth(left, right, K, baseline=0.5, cfg=cfg)
    assert np.nanmedian(depth[10:-10, 40:-10]) == pytest.approx(200.0 / d_true, rel=0.03)


def test_sgbm_wls_option_runs():
    left, right = textured_pair(11)
    disp = stereo_disparity(left, right, StereoConfig(num_disparities=32, wls=True))
    assert np.nanmedian(disp[10:-10, 40:-10]) == pytest.approx(11, abs=0.5)


def test_sgbm_rejects_bad_inputs():
    left, right = textured_pair(5)
    with pytest.raises(ValueError, match="disparity range"):
        stereo_disparity(left[:, :100], right[:, :100], StereoConfig(num_disparities=128))
    with pytest.raises(ValueError, match="multiple of 16"):
        stereo_disparity(left, right, StereoConfig(num_disparities=30))
    with pytest.raises(ValueError, match="uint8"):
        stereo_disparity(left.astype(np.float32), right)


def test_depth_png_and_npy_round_trip(tmp_path):
    depth = np.array([[1.5, 0.0], [12.25, 80.0]], dtype=np.float32)
    save_depth_png(tmp_path / "0000000003.png", depth)
    got = load_depth_map(tmp_path / "0000000003.png", shape=(2, 2))
    assert np.isnan(got[0, 1])
    np.testing.assert_allclose(got[[0, 1, 1], [0, 0, 1]], [1.5, 12.25, 80.0], atol=1 / 256)
    np.save(tmp_path / "0000000004.npy", depth)
    got = load_depth_map(tmp_path / "0000000004.npy")
    assert np.isnan(got[0, 1]) and got[1, 0] == pytest.approx(12.25)
    directory = DepthDirectory(tmp_path)
    assert directory.path(3).suffix == ".png" and directory.path(4).suffix == ".npy"
    assert directory.depth(4)[1, 1] == pytest.approx(80.0)
    src = make_depth_source(InitConfig(depth_mode="dir", depth_dir=str(tmp_path)))
    img = np.zeros((2, 2, 3), np.uint8)
    assert src(3, img, None, np.eye(3), 0.5)[1, 0] == pytest.approx(12.25, abs=1 / 256)
    assert make_depth_source(InitConfig(depth_mode="none")) is None


def _write_bytes(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


@pytest.mark.parametrize("case, message", [
    ("missing", "not found"),
    ("corrupt_png", "not a readable PNG"),
    ("png_8bit", "16-bit"),
    ("png_rgb16", "single-channel"),
    ("npy_nan", "non-finite"),
    ("npy_negative", "negative"),
    ("npy_int", "float"),
    ("npy_3d", "2-D"),
    ("npy_corrupt", "not a readable .npy"),
    ("wrong_shape", "expected"),
    ("suffix", ".png or .npy"),
])
def test_bad_depth_files_raise_data_error(tmp_path, case, message):
    p = tmp_path / "0000000001.png"
    if case == "corrupt_png":
        _write_bytes(p, b"\x89PNG\r\n\x1a\n this is not a png")
    elif case == "png_8bit":
        cv2.imwrite(str(p), np.full((4, 4), 7, np.uint8))
    elif case == "png_rgb16":
        cv2.imwrite(str(p), np.full((4, 4, 3), 700, np.uint16))
    elif case == "wrong_shape":
        cv2.imwrite(str(p), np.full((4, 5), 700, np.uint16))
    elif case.startswith("npy"):
        p = tmp_path / "0000000001.npy"
        arrays = {"npy_nan": np.array([[1.0, np.nan]]), "npy_negative": np.array([[1.0, -2.0]]),
                  "npy_int": np.array([[1, 2]]), "npy_3d": np.ones((2, 2, 2))}
        if case == "npy_corrupt":
            _write_bytes(p, b"garbage")
        else:
            np.save(p, arrays[case])
    elif case == "suffix":
        p = _write_bytes(tmp_path / "0000000001.tif", b"x")
    with pytest.raises(DataError, match=message) as err:
        load_depth_map(p, shape=(4, 4))
    assert str(p) in str(err.value)


def test_depth_directory_errors(tmp_path):
    with pytest.raises(DataError, match="directory not found"):
        DepthDirectory(tmp_path / "nope")
    with pytest.raises(DataError, match="0000000042.png") as err:
        DepthDirectory(tmp_path).depth(42)
    assert "not found" in str(err.value)


def _read_real_calibration() -> tuple[np.ndarray, float]:
    """K and baseline from the real sample's perspective.txt (P_rect_01[0, 3] = -fx * B)."""
    rows = {}
    for line in (REAL / "calibration" / "perspective.txt").read_text().splitlines():
        key, _, vals = line.partition(":")
        rows[key.strip()] = np.array(vals.split(), dtype=float)
    p0, p1 = rows["P_rect_00"].reshape(3, 4), rows["P_rect_01"].reshape(3, 4)
    return p0[:, :3], -p1[0, 3] / p1[0, 0]


def _read_real_up(frame: int) -> np.ndarray:
    """World up (world is z-up) in the camera frame of ``frame``, from cam0_to_world.txt."""
    for line in (REAL / "data_poses" / SEQ / "cam0_to_world.txt").read_text().splitlines():
        vals = line.split()
        if int(vals[0]) == frame:
            T = np.array(vals[1:], dtype=float).reshape(4, 4)
            return T[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    raise KeyError(frame)


@pytest.mark.skipif(not REAL.is_dir(), reason="real KITTI-360 sample not available")
@pytest.mark.parametrize("frame", range(700, 705))
def test_real_sgbm_depth_sees_ground_plane(frame):
    """SGBM depth of the road in front of the car lies on a plane ~1.55 m below the camera whose
    normal is the camera's -y (within 10 deg) and agrees with gravity from the recorded pose."""
    K, baseline = _read_real_calibration()
    assert baseline == pytest.approx(0.594, abs=0.002)
    img = {}
    for cam in ("image_00", "image_01"):
        bgr = cv2.imread(str(REAL / "data_2d_raw" / SEQ / cam / "data_rect" / f"{frame:010d}.png"))
        assert bgr is not None
        img[cam] = np.ascontiguousarray(bgr[..., ::-1])
    depth = stereo_depth(img["image_00"], img["image_01"], K, baseline)
    assert depth.shape == img["image_00"].shape[:2]
    assert not np.any(np.isinf(depth)) and np.nanmin(depth) > 0
    assert np.isfinite(depth).mean() > 0.5
    plane = fit_ground_plane(road_points(depth, K, GroundConfig()))
    assert np.all(np.isfinite(plane.normal)) and np.isfinite(plane.offset)
    print(f"frame {frame}: camera height {plane.camera_height:.3f} m, tilt from -y "
          f"{plane.tilt_deg():.2f} deg, inliers {plane.inlier_fraction:.2f} of {plane.n_points}")
    assert 1.4 <= plane.camera_height <= 1.7
    assert plane.tilt_deg() < 10.0
    assert plane.inlier_fraction > 0.5
    assert plane.tilt_deg(_read_real_up(frame)) < 3.0


def test_warp_error_of_a_region_is_the_whole_images_there():
    left, right = textured_pair(9, h=80, w=200, seed=3)
    disp = stereo_disparity(left, right, StereoConfig(num_disparities=32))
    full = warp_error(left, right, disp, window=3)
    region = (slice(20, 60), slice(70, 150))
    part = warp_error(left, right, disp, window=3, region=region)
    inner = (slice(21, 59), slice(71, 149))          # the box filter's reach inside the region
    np.testing.assert_array_equal(part[inner], full[inner])
    outside = np.ones(part.shape, bool)
    outside[region] = False
    assert np.all(np.isinf(part[outside])) and np.isfinite(full[inner]).mean() > 0.8


def test_matching_region_covers_the_masks_and_the_disparity_range():
    cfg = StereoConfig(num_disparities=32, region_margin=4)
    mask = np.zeros((80, 200), bool)
    mask[30:40, 100:120] = True
    rows, cols = matching_region(mask, cfg)
    assert (rows.start, rows.stop) == (26, 44) and (cols.start, cols.stop) == (100 - 4 - 32, 124)
    mask[:] = False
    mask[5:10, 3:8] = True                          # at the left border: widened to the right
    rows, cols = matching_region(mask, cfg)
    assert (rows.start, rows.stop) == (1, 14) and (cols.start, cols.stop) == (0, 33)
    assert matching_region(mask, StereoConfig(region_margin=None)) == (slice(0, 80), slice(0, 200))


def test_region_depth_agrees_with_whole_image_depth_on_the_region():
    left, right = textured_pair(12, h=100, w=240, seed=4)
    K = np.array([[400.0, 0, 120], [0, 400.0, 50], [0, 0, 1]])
    cfg = StereoConfig(num_disparities=32, region_margin=8)
    mask = np.zeros((100, 240), bool)
    mask[40:70, 120:200] = True
    whole = stereo_depth(left, right, K, 0.5, cfg)
    np.testing.assert_array_equal(stereo_depth_in(left, right, K, 0.5, (slice(0, 100), slice(0, 240)), cfg),
                                  whole)
    part = stereo_depth_in(left, right, K, 0.5, matching_region(mask, cfg), cfg)
    assert np.all(np.isnan(part[:20])) and np.all(np.isnan(part[:, :80]))
    both = np.isfinite(part[mask]) & np.isfinite(whole[mask])
    assert both.mean() > 0.9
    # SGBM's paths start at the region's edges: depths agree, not necessarily bit for bit
    np.testing.assert_allclose(part[mask][both], whole[mask][both], rtol=0.02)
