"""Depth -> pseudo point cloud of one instance (VSRD++ Algorithm 1, docs/method.md §6 steps 1-4).

1. erode the instance mask with a square kernel of ``int(sqrt(area) * 0.25)`` px;
2. keep the pixels whose left-right photometric warp error is within the mask's 40th percentile;
3. back-project them with K and the frame pose into the optimisation frame;
4. density filter (neighbours within 0.5 m; drop the lowest 1 %), then keep the main cluster of a
   single-linkage (DBSCAN with ``min_samples = 1``) clustering with linkage distance 0.8 m
   (:func:`cluster_labels`).
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..geometry.camera import transform_points
from .config import PointCloudConfig


def erosion_kernel_size(area: int, factor: float) -> int:
    """Side of the square erosion kernel for a mask of ``area`` pixels: ``int(sqrt(area) * factor)``."""
    return int(np.sqrt(max(area, 0)) * factor)


def erode_mask(mask: np.ndarray, factor: float) -> np.ndarray:
    """Erode a boolean mask with a square kernel of :func:`erosion_kernel_size` px.

    Pixels outside the image count as inside the mask, so a mask cut by the image border is not
    eroded from that side (the border is no object boundary).
    """
    k = erosion_kernel_size(int(mask.sum()), factor)
    if k < 2:
        return mask.copy()
    eroded = cv2.erode(mask.astype(np.uint8), np.ones((k, k), np.uint8),
                       borderType=cv2.BORDER_CONSTANT, borderValue=1)
    return eroded.astype(bool)


def warp_error(left: np.ndarray, right: np.ndarray, disparity: np.ndarray,
               window: int = 1) -> np.ndarray:
    """Left-right photometric error of a disparity map: ``|I_l(u, v) - I_r(u - d, v)|``.

    The right image is sampled bilinearly; the absolute difference is averaged over the colour
    channels and then over a ``window`` x ``window`` box. Returns float32 HxW, ``inf`` where the
    disparity is invalid or the warped position leaves the right image.
    """
    h, w = disparity.shape
    valid = np.isfinite(disparity)
    u = np.arange(w, dtype=np.float32)[None, :].repeat(h, 0)
    v = np.arange(h, dtype=np.float32)[:, None].repeat(w, 1)
    map_x = u - np.where(valid, disparity, 0).astype(np.float32)
    warped = cv2.remap(right, map_x, v, interpolation=cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    diff = np.abs(left.astype(np.float32) - warped.astype(np.float32))
    err = diff.mean(axis=2) if diff.ndim == 3 else diff
    if window > 1:
        err = cv2.blur(err, (window, window), borderType=cv2.BORDER_REPLICATE)
    err[~valid | (map_x < 0) | (map_x > w - 1)] = np.inf
    return err.astype(np.float32)


def select_pixels(mask: np.ndarray, depth: np.ndarray, error: np.ndarray | None,
                  cfg: PointCloudConfig) -> np.ndarray:
    """Boolean map of the mask pixels that become points: eroded mask, valid depth and (when
    ``error`` is given) a warp error within the ``cfg.warp_percentile`` of those pixels."""
    keep = erode_mask(mask, cfg.erosion_factor) & np.isfinite(depth) & (depth > 0)
    if error is not None:
        keep &= np.isfinite(error)
        if keep.any():
            keep &= error <= np.percentile(error[keep], cfg.warp_percentile)
    return keep


def back_project(pixels: np.ndarray, depth: np.ndarray, K: np.ndarray,
                 cam_to_opt: np.ndarray | None = None) -> np.ndarray:
    """3D points (N, 3) of the pixels where ``pixels`` is true: ``T * K^-1 [u, v, 1]^T * depth``.

    Pixel (0, 0) is the centre of the top-left pixel; ``cam_to_opt`` (4x4) maps the camera frame
    to the output frame (identity if None).
    """
    v, u = np.nonzero(pixels)
    z = depth[v, u].astype(np.float64)
    rays = np.stack([u, v, np.ones_like(u)], axis=1).astype(np.float64) @ np.linalg.inv(K).T
    pts = rays * z[:, None]
    return pts if cam_to_opt is None else transform_points(cam_to_opt, pts)


def density_filter(points: np.ndarray, radius: float, drop_fraction: float) -> np.ndarray:
    """Drop the ``floor(drop_fraction * N)`` points with the fewest neighbours within ``radius``.

    Ties are broken by point order (stable), so exactly that many points are dropped.
    """
    n_drop = int(np.floor(drop_fraction * len(points)))
    if n_drop == 0:
        return points
    counts = cKDTree(points).query_ball_point(points, r=radius, return_length=True)
    order = np.argsort(counts, kind="stable")
    keep = np.ones(len(points), dtype=bool)
    keep[order[:n_drop]] = False
    return points[keep]


def cluster_labels(points: np.ndarray, eps: float) -> np.ndarray:
    """Labels of the connected components of the graph linking points closer than ``eps``.

    This is single-linkage clustering (DBSCAN with ``min_samples = 1``), computed exactly with
    ``cKDTree.query_pairs`` and ``scipy.sparse.csgraph.connected_components``. The number of
    pairs grows with the square of the cloud size: callers bound it
    (:attr:`PointCloudConfig.max_points`).
    """
    n = len(points)
    pairs = cKDTree(points).query_pairs(r=eps, output_type="ndarray").reshape(-1, 2)
    graph = coo_matrix((np.ones(len(pairs), dtype=np.int8), (pairs[:, 0], pairs[:, 1])),
                       shape=(n, n))
    return connected_components(graph, directed=False)[1]


def main_cluster(points: np.ndarray, eps: float) -> np.ndarray:
    """The points of the largest :func:`cluster_labels` component (ties: the first found)."""
    if len(points) <= 1:
        return points
    labels = cluster_labels(points, eps)
    return points[labels == np.bincount(labels).argmax()]


def subsample(points: np.ndarray, max_points: int, seed: int = 0) -> np.ndarray:
    """At most ``max_points`` of ``points``, drawn without replacement with a fixed seed (order kept)."""
    if len(points) <= max_points:
        return points
    idx = np.sort(np.random.default_rng(seed).choice(len(points), max_points, replace=False))
    return points[idx]


def filter_cloud(points: np.ndarray, cfg: PointCloudConfig) -> np.ndarray:
    """Steps 4 of Algorithm 1: subsample to ``cfg.max_points``, density filter, main cluster."""
    points = subsample(points, cfg.max_points)
    points = density_filter(points, cfg.density_radius, cfg.density_drop_fraction)
    return main_cluster(points, cfg.cluster_eps)


def instance_cloud(mask: np.ndarray, depth: np.ndarray, K: np.ndarray, cam_to_opt: np.ndarray,
                   cfg: PointCloudConfig, error: np.ndarray | None = None) -> np.ndarray:
    """Pseudo point cloud (N, 3) of one instance in the optimisation frame (Algorithm 1).

    Args:
        mask: HxW bool instance mask in the left image.
        depth: HxW depth (m; NaN or <= 0 invalid).
        K: 3x3 intrinsics; cam_to_opt: 4x4 camera -> optimisation frame.
        cfg: thresholds.
        error: optional HxW photometric warp error (:func:`warp_error`); None skips step 2.
    Returns an empty (0, 3) array when fewer than ``cfg.min_pixels`` pixels survive.
    """
    pixels = select_pixels(mask, depth, error, cfg)
    if pixels.sum() < cfg.min_pixels:
        return np.zeros((0, 3))
    return filter_cloud(back_project(pixels, depth, K, cam_to_opt), cfg)
