"""Robust ground-plane fit to stereo points (a sanity check of metric depth, and a diagnostic).

A car-mounted camera sees the road in the lower image half; the points there should lie on a
plane about the camera height (~1.55 m on KITTI-360) below the camera with a normal close to the
camera's -y axis. :func:`road_points` picks those pixels and :func:`fit_ground_plane` fits the plane
with RANSAC followed by a least-squares refit on the inliers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .pointcloud import back_project


@dataclass
class GroundConfig:
    """Settings of the road-pixel selection and of the RANSAC plane fit."""

    #: Road pixels are taken below this fraction of the image height ...
    min_row_fraction: float = 0.75
    #: ... and within this fraction of the image width around the principal point (the ego lane).
    max_column_fraction: float = 0.3
    #: Only points closer than this (m) are used (stereo depth noise grows with depth squared).
    max_depth: float = 30.0
    #: RANSAC hypotheses.
    iterations: int = 300
    #: Inlier distance to the plane (m).
    inlier_threshold: float = 0.05
    #: Seed of the RANSAC sampler (results are reproducible).
    seed: int = 0


@dataclass(frozen=True)
class GroundPlane:
    """Plane ``normal . p + offset = 0`` with a unit ``normal`` pointing up (camera -y side)."""

    normal: np.ndarray
    offset: float
    #: Fraction of the input points within the inlier threshold.
    inlier_fraction: float
    #: Points used.
    n_points: int

    @property
    def camera_height(self) -> float:
        """Distance (m) of the camera centre (the origin) from the plane."""
        return abs(self.offset)

    def tilt_deg(self, up: np.ndarray = np.array([0.0, -1.0, 0.0])) -> float:
        """Angle (degrees) between the plane normal and ``up`` (default: camera -y)."""
        return float(np.degrees(np.arccos(np.clip(self.normal @ up, -1.0, 1.0))))


def road_points(depth: np.ndarray, K: np.ndarray, cfg: GroundConfig | None = None) -> np.ndarray:
    """Camera-frame points (N, 3) of the valid depth pixels in the lower central image region."""
    cfg = cfg or GroundConfig()
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w]
    sel = ((v >= cfg.min_row_fraction * h) & (np.abs(u - K[0, 2]) <= cfg.max_column_fraction * w)
           & np.isfinite(depth) & (depth > 0) & (depth <= cfg.max_depth))
    return back_project(sel, depth, K)


def fit_ground_plane(points: np.ndarray, cfg: GroundConfig | None = None) -> GroundPlane:
    """RANSAC plane through ``points`` (N, 3), refined by least squares (SVD) on the inliers."""
    cfg = cfg or GroundConfig()
    points = np.asarray(points, dtype=np.float64)
    if len(points) < 3:
        raise ValueError(f"a plane fit needs at least 3 points, got {len(points)}")
    rng = np.random.default_rng(cfg.seed)
    best = np.zeros(len(points), dtype=bool)
    for _ in range(cfg.iterations):
        p0, p1, p2 = points[rng.choice(len(points), 3, replace=False)]
        n = np.cross(p1 - p0, p2 - p0)
        norm = np.linalg.norm(n)
        if norm < 1e-9:
            continue
        n /= norm
        inliers = np.abs((points - p0) @ n) < cfg.inlier_threshold
        if inliers.sum() > best.sum():
            best = inliers
    if best.sum() < 3:
        raise ValueError("RANSAC found no plane (all samples degenerate)")
    inl = points[best]
    centroid = inl.mean(axis=0)
    normal = np.linalg.svd(inl - centroid, full_matrices=False)[2][-1]
    if normal[1] > 0:          # point up, i.e. towards camera -y
        normal = -normal
    offset = -float(normal @ centroid)
    frac = float(np.mean(np.abs(points @ normal + offset) < cfg.inlier_threshold))
    return GroundPlane(normal=normal, offset=offset, inlier_fraction=frac, n_points=len(points))
