"""Metric depth for the initialisation: stereo matching, precomputed maps, or none.

* :func:`stereo_disparity` / :func:`stereo_depth`: OpenCV semi-global matching (optionally WLS
  filtered) on a rectified pair; ``depth = f * B / disparity``; invalid pixels are NaN.
* :func:`load_depth_map` / :class:`DepthDirectory`: ``%010d.png`` (uint16, metres * 256, 0 =
  invalid, the KITTI depth convention) or ``%010d.npy`` (float metres, 0 = invalid).
* :func:`make_depth_source`: picks one of the above from :class:`~vsrd_mi.init.config.InitConfig`
  (``"none"`` gives no source: the caller falls back to its default box).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from ..errors import DataError
from .config import InitConfig, StereoConfig

#: Scale of 16-bit PNG depth maps: stored value = metres * DEPTH_PNG_SCALE (0 = invalid).
DEPTH_PNG_SCALE = 256.0

#: OpenCV's fixed-point disparity scale (``StereoSGBM.compute`` returns disparity * 16).
_SGBM_DISP_SCALE = 16.0

_SGBM_MODES = {
    "sgbm": cv2.STEREO_SGBM_MODE_SGBM,
    "hh": cv2.STEREO_SGBM_MODE_HH,
    "sgbm_3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    "hh4": cv2.STEREO_SGBM_MODE_HH4,
}


def _make_sgbm(cfg: StereoConfig, channels: int, min_disparity: int) -> cv2.StereoSGBM:
    if cfg.mode not in _SGBM_MODES:
        raise ValueError(f"unknown SGBM mode {cfg.mode!r}; choose one of {sorted(_SGBM_MODES)}")
    if cfg.num_disparities <= 0 or cfg.num_disparities % 16:
        raise ValueError(f"num_disparities must be a positive multiple of 16, got {cfg.num_disparities}")
    b2 = cfg.block_size * cfg.block_size
    return cv2.StereoSGBM_create(
        minDisparity=min_disparity, numDisparities=cfg.num_disparities, blockSize=cfg.block_size,
        P1=cfg.p1_factor * channels * b2, P2=cfg.p2_factor * channels * b2,
        disp12MaxDiff=cfg.disp12_max_diff, preFilterCap=cfg.pre_filter_cap,
        uniquenessRatio=cfg.uniqueness_ratio, speckleWindowSize=cfg.speckle_window_size,
        speckleRange=cfg.speckle_range, mode=_SGBM_MODES[cfg.mode])


def stereo_disparity(left: np.ndarray, right: np.ndarray,
                     cfg: StereoConfig | None = None) -> np.ndarray:
    """Disparity (px, float32) of the left image of a rectified pair; NaN where invalid.

    Args:
        left, right: HxWx3 uint8 images (same channel order) or HxW uint8 grey images.
        cfg: matcher settings (defaults: :class:`StereoConfig`).
    """
    cfg = cfg or StereoConfig()
    if left.shape != right.shape or left.dtype != np.uint8 or right.dtype != np.uint8:
        raise ValueError(f"stereo pair must be two uint8 images of one shape, got {left.shape} "
                         f"{left.dtype} and {right.shape} {right.dtype}")
    width = left.shape[1]
    if width <= cfg.num_disparities + cfg.min_disparity:
        raise ValueError(f"image width {width} must exceed the disparity range "
                         f"{cfg.min_disparity}+{cfg.num_disparities}")
    channels = 1 if left.ndim == 2 else left.shape[2]
    matcher = _make_sgbm(cfg, channels, cfg.min_disparity)
    raw = matcher.compute(left, right)
    invalid_raw = (cfg.min_disparity - 1) * _SGBM_DISP_SCALE
    if cfg.wls:
        right_matcher = cv2.ximgproc.createRightMatcher(matcher)
        raw_right = right_matcher.compute(right, left)
        wls = cv2.ximgproc.createDisparityWLSFilter(matcher)
        wls.setLambda(cfg.wls_lambda)
        wls.setSigmaColor(cfg.wls_sigma_color)
        raw = wls.filter(raw, left, disparity_map_right=raw_right)
    disp = raw.astype(np.float32) / _SGBM_DISP_SCALE
    disp[(raw <= invalid_raw) | (disp <= 0)] = np.nan
    return disp


def bounding_region(mask: np.ndarray, margin: int, left_margin: int = 0) -> tuple[slice, slice]:
    """Rows and columns of ``mask``'s bounding box widened by ``margin`` px (and to the left by
    ``left_margin`` more), clipped to the image; the whole image for an empty mask."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return slice(0, mask.shape[0]), slice(0, mask.shape[1])
    return (slice(max(int(rows[0]) - margin, 0), min(int(rows[-1]) + 1 + margin, mask.shape[0])),
            slice(max(int(cols[0]) - margin - left_margin, 0), min(int(cols[-1]) + 1 + margin, mask.shape[1])))


def matching_region(mask: np.ndarray, cfg: StereoConfig) -> tuple[slice, slice]:
    """Part of the left image to match so that ``mask``'s pixels get a disparity:
    :func:`bounding_region` with ``cfg.region_margin``, widened to the left by the disparity range
    (a pixel matches the right image up to ``min_disparity + num_disparities`` columns to its
    left, and SGBM leaves that many columns at a region's left edge without a disparity)."""
    if cfg.region_margin is None:
        return slice(0, mask.shape[0]), slice(0, mask.shape[1])
    reach = cfg.min_disparity + cfg.num_disparities
    rows, cols = bounding_region(mask, cfg.region_margin, reach)
    if cols.stop - cols.start <= reach:  # only at the left border: the matcher needs more width
        cols = slice(0, min(reach + 1, mask.shape[1]))
    return rows, cols


def disparity_to_depth(disparity: np.ndarray, focal: float, baseline: float,
                       max_depth: float = np.inf) -> np.ndarray:
    """``depth = focal * baseline / disparity`` (float32); NaN where the disparity is invalid
    (NaN or <= 0) or the depth exceeds ``max_depth``."""
    disparity = np.asarray(disparity, dtype=np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.float32(focal * baseline) / disparity
    depth[~(disparity > 0) | ~(depth <= max_depth)] = np.nan
    return depth


def depth_to_disparity(depth: np.ndarray, focal: float, baseline: float) -> np.ndarray:
    """Inverse of :func:`disparity_to_depth`; NaN where the depth is invalid (NaN or <= 0)."""
    depth = np.asarray(depth, dtype=np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        disp = np.float32(focal * baseline) / depth
    disp[~(depth > 0)] = np.nan
    return disp


def stereo_depth(left: np.ndarray, right: np.ndarray, K: np.ndarray, baseline: float,
                 cfg: StereoConfig | None = None) -> np.ndarray:
    """Metric depth (m, float32, NaN = invalid) of the left image of a rectified stereo pair."""
    cfg = cfg or StereoConfig()
    disp = stereo_disparity(left, right, cfg)
    return disparity_to_depth(disp, float(np.asarray(K)[0, 0]), baseline, cfg.max_depth)


def stereo_depth_in(left: np.ndarray, right: np.ndarray, K: np.ndarray, baseline: float,
                    region: tuple[slice, slice], cfg: StereoConfig | None = None) -> np.ndarray:
    """:func:`stereo_depth` of the rows and columns ``region`` only (NaN elsewhere, full size)."""
    rows, cols = region
    depth = np.full(left.shape[:2], np.nan, dtype=np.float32)
    depth[rows, cols] = stereo_depth(np.ascontiguousarray(left[rows, cols]),
                                     np.ascontiguousarray(right[rows, cols]), K, baseline, cfg)
    return depth


def load_depth_map(path: str | Path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Read a depth map: ``.png`` (single-channel uint16, metres * 256) or ``.npy`` (float metres).

    Zero marks an invalid pixel in both formats; the result is float32 metres with NaN there.
    Raises :class:`~vsrd_mi.errors.DataError` (naming the file) for a missing or unreadable file,
    a wrong bit depth / channel count / dtype, a shape other than ``shape`` (H, W), or (npy)
    negative or non-finite values.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "depth map not found")
    if path.suffix == ".png":
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise DataError(path, "not a readable PNG image")
        if raw.ndim != 2 or raw.dtype != np.uint16:
            raise DataError(path, f"depth PNG must be single-channel 16-bit, got "
                                  f"{raw.shape[2] if raw.ndim == 3 else 1} channel(s) of {raw.dtype}")
        depth = raw.astype(np.float32) / np.float32(DEPTH_PNG_SCALE)
        depth[raw == 0] = np.nan
    elif path.suffix == ".npy":
        try:
            raw = np.load(path, allow_pickle=False)
        except (ValueError, OSError, EOFError) as exc:
            raise DataError(path, f"not a readable .npy array ({exc})") from None
        if raw.ndim != 2 or raw.dtype.kind != "f":
            raise DataError(path, f"depth .npy must be a 2-D float array, got shape {raw.shape} "
                                  f"dtype {raw.dtype}")
        if not np.all(np.isfinite(raw)):
            raise DataError(path, "depth contains non-finite values (mark invalid pixels with 0)")
        if np.any(raw < 0):
            raise DataError(path, "depth contains negative values")
        depth = raw.astype(np.float32)
        depth[raw == 0] = np.nan
    else:
        raise DataError(path, "depth map must be a .png or .npy file")
    if shape is not None and depth.shape != tuple(shape):
        raise DataError(path, f"depth map is {depth.shape[1]}x{depth.shape[0]}, expected "
                              f"{shape[1]}x{shape[0]}")
    return depth


def save_depth_png(path: str | Path, depth: np.ndarray) -> None:
    """Write depth (m, NaN/<=0 invalid) as a uint16 PNG of metres * 256 (saturating at 255.99 m)."""
    depth = np.asarray(depth, dtype=np.float64)
    valid = np.isfinite(depth) & (depth > 0)
    raw = np.zeros(depth.shape, dtype=np.uint16)
    raw[valid] = np.clip(np.round(depth[valid] * DEPTH_PNG_SCALE), 1, np.iinfo(np.uint16).max)
    if not cv2.imwrite(str(path), raw):
        raise OSError(f"{path}: could not write depth PNG")


class DepthDirectory:
    """Precomputed depth maps named by absolute frame index: ``%010d.png`` or ``%010d.npy``."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise DataError(self.root, "depth directory not found")

    def path(self, frame: int) -> Path:
        """The depth file of ``frame`` (PNG preferred when both exist)."""
        for suffix in (".png", ".npy"):
            p = self.root / f"{frame:010d}{suffix}"
            if p.is_file():
                return p
        raise DataError(self.root / f"{frame:010d}.png", "depth map not found (nor .npy)")

    def depth(self, frame: int, shape: tuple[int, int] | None = None) -> np.ndarray:
        """Depth of ``frame`` in metres (NaN = invalid); see :func:`load_depth_map`."""
        return load_depth_map(self.path(frame), shape)


#: A depth source maps (absolute frame index, left, right, K, baseline) to depth (m, NaN invalid).
DepthSource = Callable[[int, np.ndarray, np.ndarray | None, np.ndarray, float], np.ndarray]


def make_depth_source(cfg: InitConfig) -> DepthSource | None:
    """The depth source selected by ``cfg.depth_mode`` (None for ``"none"``)."""
    if cfg.depth_mode == "none":
        return None
    if cfg.depth_mode == "dir":
        directory = DepthDirectory(cfg.depth_dir)

        def from_dir(frame: int, left: np.ndarray, right: np.ndarray | None,
                     K: np.ndarray, baseline: float) -> np.ndarray:
            return directory.depth(frame, left.shape[:2])
        return from_dir

    def from_stereo(frame: int, left: np.ndarray, right: np.ndarray | None,
                    K: np.ndarray, baseline: float) -> np.ndarray:
        if right is None:
            raise ValueError(f"frame {frame}: stereo depth needs the right image")
        return stereo_depth(left, right, K, baseline, cfg.stereo)
    return from_stereo
