"""3D attribute initialisation from stereo depth (VSRD++ §III-D, docs/method.md §6).

For every instance of the target frame: pseudo point clouds per frame (:mod:`.pointcloud`),
velocity by translation-only ICP between frames (:mod:`.icp`, eq. 11-12), a dynamic flag,
a location (eq. 13, with the sign of the motion compensation right: a cloud seen at frame offset
``dt`` is moved by ``-v * dt`` to reach the target time), an orientation (velocity heading for
moving cars, an L-shape / rectangle fit for parked ones) and a centre corrected for the fact that
a stereo cloud only covers the surfaces facing the camera (:func:`fit_footprint`).
No ground truth is read anywhere.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial import cKDTree
from scipy.special import ndtr, stdtrit

from ..geometry.boxes import Box3D, wrap_angle, yaw_from_direction, yaw_matrix
from ..geometry.surface import footprint_ray_residuals, quantile_soft_l1, range_quantile
from .config import FootprintConfig, InitConfig, OrientationConfig, VelocityConfig
from .depth import bounding_region, depth_to_disparity, make_depth_source, matching_region, stereo_depth_in
from .frames import StereoFrame
from .icp import register_translation
from .pointcloud import instance_cloud, warp_error

#: Index of the vertical (gravity) axis of the optimisation frame.
_UP_AXIS = 1


@dataclass
class InstanceInit:
    """Initial 3D attributes of one instance, in the optimisation frame at the target time.

    Attributes:
        instance_id: dataset instance id.
        centre: (3,) box centre (m).
        yaw: yaw about +y (length axis ``(sin yaw, 0, cos yaw)``).
        velocity: (3,) metres per frame index (the estimate, also for static instances).
        dynamic: whether the speed exceeds the dynamic threshold.
        size: (3,) full size (w, h, l) used by the footprint fit, or None when not fitted.
        n_points: points of the reference cloud that located the instance.
        clouds: frame offset -> the instance's cloud in that frame (optimisation frame, at that
            frame's time; not motion compensated).
        reference_offset: frame offset whose cloud located the instance (0 when the target
            frame's cloud was large enough).
        cloud_mean: (3,) mean of the motion-compensated reference cloud (the paper's location,
            before the visible-surface correction).
        n_velocity_pairs: frame pairs whose ICP estimates were averaged into the velocity.
        velocity_standard_error: standard error (m per frame index) of that average.
        velocity_effective_pairs: effective number of pairs behind it (the dynamic flag's
            significance test, :func:`is_dynamic`).
        truncated: frame offsets where the instance's mask touches the image border.
        axis_seen: whether the yaw's length axis came from evidence (the velocity, or a cloud
            longer than a car is wide along it) rather than the road prior.
        fit_points: (M, 3) the merged cloud the footprint was fitted to (target time,
            optimisation frame; :func:`merged_cloud`), or None.
        fit_cameras: (M, 3) the centre of the camera that saw each of ``fit_points``.
    """

    instance_id: int
    centre: np.ndarray
    yaw: float
    velocity: np.ndarray
    dynamic: bool
    size: np.ndarray | None
    n_points: int
    clouds: dict[int, np.ndarray] = field(repr=False)
    reference_offset: int = 0
    cloud_mean: np.ndarray | None = None
    n_velocity_pairs: int = 0
    velocity_standard_error: float = 0.0
    velocity_effective_pairs: float = 0.0
    truncated: tuple[int, ...] = ()
    axis_seen: bool = True
    fit_points: np.ndarray | None = field(default=None, repr=False)
    fit_cameras: np.ndarray | None = field(default=None, repr=False)

    def to_box(self, default_size: tuple[float, float, float] = FootprintConfig.typical_size) -> Box3D:
        """The initial box (``default_size`` when no size was fitted); velocity kept as estimated."""
        size = self.size if self.size is not None else np.asarray(default_size, float)
        return Box3D(centre=self.centre, size=size, yaw=self.yaw, velocity=self.velocity,
                     dynamic=self.dynamic, instance_id=self.instance_id)

    def turned(self, yaw: float, cfg: FootprintConfig) -> InstanceInit:
        """This instance with ``yaw`` and its footprint fitted again for it (:func:`fit_footprint`
        on ``fit_points``; only the yaw changes where the footprint was not fitted). Where the
        axis hypotheses turn a box (:mod:`vsrd_mi.optimise.axis`), the centre must move with the
        length: a footprint fitted along the wrong axis puts the centre half a width behind the
        seen faces instead of half a length, where the init anchor would hold it (a car in a
        perpendicular bay seen nose first would stand a metre out in the road; docs/accuracy.md)."""
        if self.fit_points is None or self.fit_cameras is None or not cfg.enabled:
            return replace(self, yaw=float(yaw))
        centre, size = fit_footprint(self.fit_points, float(yaw), self.fit_cameras, cfg,
                                     cfg.fit_quantile_for(self.dynamic))
        return replace(self, yaw=float(yaw), centre=centre, size=size)


# --------------------------------------------------------------------------------------------
# Per-frame clouds
# --------------------------------------------------------------------------------------------

def masks_union(frame: StereoFrame) -> np.ndarray:
    """HxW bool: the pixels of any of the frame's instance masks."""
    union = np.zeros(frame.left.shape[:2], dtype=bool)
    for mask in frame.masks.values():
        union |= mask
    return union


def frame_depth(frame: StereoFrame, cfg: InitConfig) -> np.ndarray:
    """Depth (m, NaN invalid) of a frame: its precomputed map, else ``cfg``'s depth source
    (SGBM only around the frame's masks, :func:`~vsrd_mi.init.depth.matching_region`, unless
    ``cfg.stereo.region_margin`` is None)."""
    if frame.depth is not None:
        depth = np.asarray(frame.depth, dtype=np.float32).copy()
        depth[~(depth > 0)] = np.nan
        return depth
    if cfg.depth_mode == "sgbm" and frame.right is not None and cfg.stereo.region_margin is not None:
        region = matching_region(masks_union(frame), cfg.stereo)
        return stereo_depth_in(frame.left, frame.right, frame.K, frame.baseline, region, cfg.stereo)
    source = make_depth_source(cfg)
    if source is None:
        raise ValueError("depth_mode 'none' computes no depth")
    if cfg.depth_mode == "dir" and frame.frame_index is None:
        raise ValueError(f"frame at offset {frame.frame_offset} has no frame_index to look up "
                         f"in the depth directory")
    index = frame.frame_index if frame.frame_index is not None else frame.frame_offset
    return source(index, frame.left, frame.right, frame.K, frame.baseline)


def frame_clouds(frame: StereoFrame, depth: np.ndarray, cfg: InitConfig) -> dict[int, np.ndarray]:
    """Pseudo point cloud of every instance of ``frame`` (empty instances left out)."""
    error = None
    if frame.right is not None:
        disparity = depth_to_disparity(depth, frame.K[0, 0], frame.baseline)
        # the error is read on the masks only: its box filter reaches window // 2 px beyond them
        region = bounding_region(masks_union(frame), cfg.cloud.warp_window // 2 + 1)
        error = warp_error(frame.left, frame.right, disparity, cfg.cloud.warp_window, region)
    out = {}
    for iid, mask in frame.masks.items():
        cloud = instance_cloud(mask, depth, frame.K, frame.cam_to_opt, cfg.cloud, error)
        if len(cloud):
            out[int(iid)] = cloud
    return out


# --------------------------------------------------------------------------------------------
# Velocity and dynamic flag
# --------------------------------------------------------------------------------------------

def robust_weighted_mean(estimates: np.ndarray, weights: np.ndarray, mad_factor: float,
                         floor: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Weighted mean of vector ``estimates`` (N, D) after dropping extreme ones.

    The centre is the component-wise median; an estimate is extreme when its distance to it
    exceeds ``max(mad_factor * 1.4826 * MAD, floor)``. Centre and MAD are unweighted: with
    weighted ones, an estimate holding half the weight would be the centre with a MAD of 0 and
    every other estimate beyond ``floor`` would be dropped, however well they agree. Returns
    (mean, kept mask, standard error of the mean), the standard error being
    ``sqrt(sum w_i^2 |x_i - mean|^2) / sum w_i`` over the kept estimates (0 for a single one).
    """
    med = np.median(estimates, axis=0)
    dist = np.linalg.norm(estimates - med, axis=1)
    mad = float(np.median(dist))
    keep = dist <= max(mad_factor * 1.4826 * mad, floor)
    w, x = weights[keep], estimates[keep]
    mean = np.average(x, axis=0, weights=w)
    sq = np.sum((x - mean) ** 2, axis=1)
    se = float(np.sqrt(np.sum(w ** 2 * sq)) / np.sum(w)) if len(w) > 1 else 0.0
    return mean, keep, se


def effective_count(weights: np.ndarray) -> float:
    """Kish's effective sample size ``(sum w)^2 / sum w^2`` (n for equal weights, 1 when one
    weight dominates; 0 for none)."""
    w = np.asarray(weights, dtype=float)
    return float(w.sum() ** 2 / np.sum(w ** 2)) if len(w) and np.any(w) else 0.0


def critical_value(significance: float, effective_pairs: float) -> float:
    """Standard errors a mean must lie from zero to be significant at the one-sided level of
    ``significance`` normal standard deviations, given that the standard error itself was
    estimated from ``effective_pairs`` estimates: Student's t quantile with
    ``effective_pairs - 1`` degrees of freedom (``significance`` itself for infinitely many,
    infinite for one or fewer: a lone estimate shows no spread to test against)."""
    if not np.isfinite(effective_pairs):
        return float(significance)
    if effective_pairs <= 1.0:
        return float("inf")
    return float(stdtrit(effective_pairs - 1.0, ndtr(significance)))


def velocity_pairs(offsets: list[int], cfg: VelocityConfig) -> list[tuple[int, int]]:
    """Frame-offset pairs ``(a, b)``: each offset with its next ``cfg.pair_neighbours`` offsets
    in time, keeping ``0 < b - a <= cfg.max_gap``."""
    if cfg.pair_neighbours < 1:
        raise ValueError(f"pair_neighbours must be >= 1, got {cfg.pair_neighbours}")
    offsets = sorted(offsets)
    return [(a, b) for i, a in enumerate(offsets)
            for b in offsets[i + 1:i + 1 + cfg.pair_neighbours] if 0 < b - a <= cfg.max_gap]


@dataclass(frozen=True)
class VelocityEstimate:
    """Outcome of :func:`estimate_velocity`."""

    #: Velocity (3,), metres per frame index (zero when no pair was usable).
    velocity: np.ndarray
    #: Frame pairs averaged (after dropping extreme estimates).
    n_pairs: int
    #: Standard error (m per frame index) of the mean over the pairs (0 for fewer than two).
    standard_error: float
    #: Effective number of pairs behind the mean (:func:`effective_count` of the kept pairs'
    #: weights): the standard error's own reliability.
    effective_pairs: float = 0.0


def estimate_velocity(clouds: dict[int, np.ndarray], cfg: VelocityConfig) -> VelocityEstimate:
    """Velocity (m per frame index) of one instance from its clouds per frame offset (eq. 11-12).

    Every frame pair of :func:`velocity_pairs` among the frames with more than ``cfg.min_points``
    points gives ``ICP translation / gap`` (:func:`~vsrd_mi.init.icp.register_translation`);
    extreme estimates are dropped and the rest averaged with weight ``min(M_a, M_b)`` (point
    counts), times ``(b - a)^2`` with ``cfg.gap_weighted`` (a pair's translation error hardly
    depends on its gap, so its velocity error falls as ``1 / gap``), by
    :func:`robust_weighted_mean`.
    """
    usable = {o: c for o, c in clouds.items() if len(c) > cfg.min_points}
    pairs = velocity_pairs(list(usable), cfg)
    if not pairs:
        return VelocityEstimate(np.zeros(3), 0, 0.0)
    trees = {o: cKDTree(c) for o, c in usable.items()}
    estimates, weights = [], []
    for a, b in pairs:
        t_ab = register_translation(
            usable[a], usable[b], trees[a], trees[b], max_source_points=cfg.icp_max_points,
            rms_tolerance_abs=cfg.icp_rms_tolerance_abs, rms_tolerance_rel=cfg.icp_rms_tolerance_rel,
            max_iterations=cfg.icp_max_iterations, tolerance=cfg.icp_tolerance,
            trim_fraction=cfg.icp_trim_fraction).translation
        v = t_ab / (b - a)
        if cfg.horizontal_only:
            v[_UP_AXIS] = 0.0
        estimates.append(v)
        weights.append(min(len(usable[a]), len(usable[b])) * ((b - a) ** 2 if cfg.gap_weighted else 1))
    weights = np.array(weights, float)
    mean, keep, se = robust_weighted_mean(np.array(estimates), weights,
                                          cfg.outlier_mad_factor, cfg.outlier_floor)
    return VelocityEstimate(mean, int(keep.sum()), se, effective_count(weights[keep]))


def speed_mps(velocity: np.ndarray, frame_rate_hz: float) -> float:
    """Speed in m/s of a velocity in metres per frame index."""
    return float(np.linalg.norm(velocity) * frame_rate_hz)


def is_dynamic(velocity: np.ndarray, cfg: VelocityConfig, standard_error: float = 0.0,
               effective_pairs: float = float("inf")) -> bool:
    """Whether an instance moves: its speed exceeds ``cfg.dynamic_speed_threshold`` (m/s) and its
    velocity (m per frame index) is significantly away from zero: more than
    :func:`critical_value` ``(cfg.significance, effective_pairs)`` standard errors (the pair
    estimates agree on a motion rather than scatter around none). ``effective_pairs`` is
    :attr:`VelocityEstimate.effective_pairs`; left infinite, the test is ``cfg.significance``
    standard errors."""
    speed = float(np.linalg.norm(velocity))
    if speed * cfg.frame_rate_hz <= cfg.dynamic_speed_threshold:
        return False
    critical = critical_value(cfg.significance, effective_pairs)
    return bool(np.isfinite(critical) and speed > critical * standard_error)


# --------------------------------------------------------------------------------------------
# Location
# --------------------------------------------------------------------------------------------

def to_target_time(points: np.ndarray, offset: int, motion: np.ndarray) -> np.ndarray:
    """Move a cloud seen at frame ``offset`` to the target time: ``points - motion * offset``.

    ``motion`` is the velocity for dynamic instances and zero for static ones; the box centre at
    offset ``dt`` is ``l + v * dt`` (docs/method.md §1), so going back to ``dt = 0`` subtracts ``v * dt``.
    """
    return points - np.asarray(motion, float) * offset


def reference_offset(clouds: dict[int, np.ndarray], min_points: int) -> int:
    """Frame offset that locates the instance: the target (0) when its cloud has at least
    ``min_points`` points, else the nearest such frame (earlier one on ties), else the frame with
    the most points."""
    good = [o for o, c in clouds.items() if len(c) >= min_points]
    if good:
        return min(good, key=lambda o: (abs(o), o))
    return max(clouds, key=lambda o: (len(clouds[o]), -abs(o)))


def consistent_views(clouds: dict[int, np.ndarray], motion: np.ndarray, min_points: int,
                     share: float, distance: float) -> dict[int, np.ndarray]:
    """The clouds that agree with the other frames' clouds once moved to the target time.

    Stereo matching near the image border or on a thin mask can put a whole frame's cloud
    metres from the car (on the development streets one frame placed a perpendicular van's
    points 7 m from the rest, and the merged cloud made the van 6.5 m long across its true
    axis). A cloud of which fewer than ``share`` of the points lie within ``distance`` metres
    (horizontally) of another frame's points is left out, unless fewer than three frames are
    given (no majority) or no kept cloud would have ``min_points``.
    """
    if len(clouds) < 3 or share <= 0:
        return clouds
    moved = {o: to_target_time(c, o, motion)[:, [0, 2]] for o, c in clouds.items()}
    keep = {}
    for o, xz in moved.items():
        others = np.concatenate([v for k, v in moved.items() if k != o])
        d, _ = cKDTree(others).query(xz, distance_upper_bound=distance)
        if np.mean(np.isfinite(d)) >= share:
            keep[o] = clouds[o]
    return keep if keep and max(len(c) for c in keep.values()) >= min_points else clouds


def merged_cloud(clouds: dict[int, np.ndarray], cameras: dict[int, np.ndarray], motion: np.ndarray,
                 centre_offset: int, max_offset: int,
                 max_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Clouds of the frames within ``max_offset`` of ``centre_offset``, moved to the target time.

    Returns (points (N, 3), the centre of the camera that saw each point (N, 3), moved the same
    way, i.e. relative to the instance at the target time), subsampled to ``max_points``.
    """
    offs = [o for o in sorted(clouds) if abs(o - centre_offset) <= max_offset]
    pts = np.concatenate([to_target_time(clouds[o], o, motion) for o in offs])
    cams = np.concatenate([np.repeat(to_target_time(cameras[o], o, motion)[None], len(clouds[o]), 0)
                           for o in offs])
    if len(pts) > max_points:
        keep = np.sort(np.random.default_rng(0).choice(len(pts), max_points, replace=False))
        pts, cams = pts[keep], cams[keep]
    return pts, cams


# --------------------------------------------------------------------------------------------
# Orientation
# --------------------------------------------------------------------------------------------

def _axes(yaw: float) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal (x, z) components of the length axis and the width axis of a box with ``yaw``
    (the columns of :func:`vsrd_mi.geometry.boxes.yaw_matrix` for local z and x)."""
    rotation = yaw_matrix(yaw)
    return rotation[[0, 2], 2], rotation[[0, 2], 0]


def _edge_extents(xz: np.ndarray, psi: float, percentile: float) -> list[tuple[float, float]]:
    """Robust ``(lo, hi)`` of the x-z points along the length and width axes of yaw ``psi``."""
    return [tuple(np.percentile(xz @ ax, [percentile, 100.0 - percentile])) for ax in _axes(psi)]


def _refine_rectangle_angle(xz: np.ndarray, psi: float, cfg: OrientationConfig) -> float:
    """Least-squares refinement of a rectangle orientation ``psi``.

    Each point within ``cfg.refine_distance`` of an edge of the current rectangle is assigned to
    its nearest edge; the orientation minimising the squared distances of the points to their
    (mean-centred) edge lines is the eigenvector of the smallest eigenvalue of
    ``C_long + J^T C_lat J`` (scatter of the points on the faces across the length axis and on
    the faces along it; J rotates by 90 degrees). Repeated ``cfg.refine_iterations`` times.
    """
    J = np.array([[0.0, 1.0], [-1.0, 0.0]])           # length axis -> width axis
    for _ in range(cfg.refine_iterations):
        dists = []
        for k, ax in enumerate(_axes(psi)):
            proj = xz @ ax
            lo, hi = np.percentile(proj, [cfg.edge_percentile, 100.0 - cfg.edge_percentile])
            dists += [np.abs(proj - lo), np.abs(proj - hi)]
        dists = np.stack(dists)                          # (4, N): A-lo, A-hi, B-lo, B-hi
        nearest = dists.argmin(0)
        near = dists.min(0) <= cfg.refine_distance
        scatter = [np.zeros((2, 2)), np.zeros((2, 2))]
        for e in range(4):
            pts = xz[near & (nearest == e)]
            if len(pts) >= 2:
                c = pts - pts.mean(0)
                scatter[e // 2] += c.T @ c
        m = scatter[0] + J.T @ scatter[1] @ J
        if not np.any(m):
            break
        a = np.linalg.eigh(m)[1][:, 0]                   # new length axis (x, z)
        new = np.arctan2(a[0], a[1])
        psi = float(psi + wrap_angle(2 * (new - psi)) / 2)   # same axis, modulo pi
    return psi


def extents_show_length(extents: list[float], cfg: OrientationConfig) -> bool:
    """Whether a cloud's footprint extents along two rectangle axes tell which is the length (the
    larger one): one exceeds ``cfg.length_evidence`` (no car is that wide), or they differ by more
    than ``cfg.extent_margin`` and the cloud is no single face (both exceed ``cfg.face_depth``)."""
    longest, shortest = max(extents), min(extents)
    return longest > cfg.length_evidence or (longest - shortest > cfg.extent_margin and shortest > cfg.face_depth)


def length_axis_seen(points: np.ndarray, yaw: float, cfg: OrientationConfig) -> bool:
    """Whether the cloud itself shows that the length axis of ``yaw`` is the car's length
    (:func:`extents_show_length`, the larger extent along it; else :func:`dominant_yaw` fell back
    on the road prior)."""
    xz = points[:, [0, 2]] - points[:, [0, 2]].mean(axis=0)
    extents = [hi - lo for lo, hi in _edge_extents(xz, yaw, cfg.edge_percentile)]
    return extents_show_length(extents, cfg) and extents[0] >= extents[1]


def dominant_yaw(points: np.ndarray, cfg: OrientationConfig) -> float:
    """Yaw of a parked car from the dominant horizontal directions of its cloud.

    A rectangle orientation in [0, 90) is found by maximising the closeness criterion of
    Zhang et al. (2017, "Efficient L-shape fitting for vehicle detection using laser scanners")
    on the x-z points and refined by least squares (:func:`_refine_rectangle_angle`); which of the
    two rectangle axes is the car's length is decided by the cloud's extent along them
    (:func:`extents_show_length`), else by the road prior (the axis closer to the optimisation
    frame's forward direction).
    The result is in [-pi/2, pi/2) (a box is symmetric under yaw + pi).
    """
    xz = points[:, [0, 2]] - points[:, [0, 2]].mean(axis=0)
    psi = np.deg2rad(np.arange(0.0, 90.0, cfg.search_step_deg))
    best_score, best = -np.inf, 0.0
    for k in range(len(psi)):
        d = np.inf
        for ax, (lo, hi) in zip(_axes(psi[k]), _edge_extents(xz, psi[k], cfg.edge_percentile)):
            proj = xz @ ax
            d = np.minimum(d, np.minimum(np.abs(proj - lo), np.abs(hi - proj)))
        score = float(np.sum(1.0 / np.maximum(d, cfg.closeness_floor)))
        if score > best_score:
            best_score, best = score, float(psi[k])
    best = _refine_rectangle_angle(xz, best, cfg)
    extents = [hi - lo for lo, hi in _edge_extents(xz, best, cfg.edge_percentile)]
    if extents_show_length(extents, cfg):
        yaw = best if extents[0] >= extents[1] else best + np.pi / 2
    else:
        yaw = best if abs(np.cos(best)) >= abs(np.sin(best)) else best + np.pi / 2
    return float((yaw + np.pi / 2) % np.pi - np.pi / 2)


def yaw_from_velocity(velocity: np.ndarray) -> float:
    """Yaw whose length axis points along the horizontal velocity (moving cars drive forwards)."""
    return yaw_from_direction(np.asarray(velocity, float))


# --------------------------------------------------------------------------------------------
# Centre correction
# --------------------------------------------------------------------------------------------

def ray_residuals(local: np.ndarray, cam_local: np.ndarray, half: np.ndarray,
                  reference_range: float) -> np.ndarray:
    """Residuals of stereo points ``local`` (N, 2; box-local x, z) seen from ``cam_local``
    (N, 2) against the footprint rectangle ``|x| <= half``, along their viewing rays
    (:func:`vsrd_mi.geometry.surface.footprint_ray_residuals`)."""
    return footprint_ray_residuals(local[:, 0], local[:, 1], cam_local[:, 0], cam_local[:, 1],
                                   float(half[0]), float(half[1]), reference_range)


def fit_footprint(points: np.ndarray, yaw: float, cameras: np.ndarray,
                  cfg: FootprintConfig, quantile: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Centre and size of a box of (at least) typical car size behind the visible surface.

    Size: along each box axis the cloud spans ``[lo, hi]`` (robust percentiles); the box extent is
    ``clip(hi - lo, typical, max)``.

    Initial horizontal centre, per box axis: a camera further than ``cfg.visibility_margin``
    below ``lo`` sees the low face, so the box starts at ``lo`` (centre ``lo + L/2``); likewise
    ``hi - L/2`` for cameras beyond ``hi``; these are averaged over the points' cameras, and when
    no camera sees either face (the axis is seen edge-on) the centre is the middle of
    ``[lo, hi]``.

    Refinement: the edge percentiles are pulled towards the cameras by the stereo noise (which
    grows with the square of the depth), so the horizontal centre is then refined by robust least
    squares (``scipy.optimize.least_squares`` on
    :func:`vsrd_mi.geometry.surface.quantile_soft_l1` of scale ``cfg.fit_loss_scale`` and
    ``quantile``) of :func:`ray_residuals`: every point is compared with where its viewing ray
    enters the box, so noise averages out instead of biasing an edge, and rays missing the box
    pull it back under the observed silhouette. Vertically the box is centred on the cloud's
    extent (roof and underside are rarely seen face-on from a car-mounted camera).

    Args:
        points: (N, 3) cloud at the target time, optimisation frame.
        yaw: box yaw.
        cameras: (N, 3) centre of the camera that saw each point, relative to the instance at
            the target time.
        quantile: the refinement's quantile (default ``cfg.fit_quantile``).
    Returns (centre (3,), size (3,) = (w, h, l)).
    """
    length_ax, width_ax = _axes(yaw)
    basis = np.stack([width_ax, length_ax])              # rows: local x (width), local z (length)
    typical, largest = np.asarray(cfg.typical_size, float), np.asarray(cfg.max_size, float)
    p_lo, p_hi = cfg.edge_percentile, 100.0 - cfg.edge_percentile
    xz, cam_xz = points[:, [0, 2]], cameras[:, [0, 2]]
    local, cam_local = xz @ basis.T, cam_xz @ basis.T
    centre_local, half = np.zeros(2), np.zeros(2)
    for k, size_k in ((0, 0), (1, 2)):
        lo, hi = np.percentile(local[:, k], [p_lo, p_hi])
        dim = float(np.clip(hi - lo, typical[size_k], largest[size_k]))
        w_lo = float(np.sum(cam_local[:, k] < lo - cfg.visibility_margin))
        w_hi = float(np.sum(cam_local[:, k] > hi + cfg.visibility_margin))
        if w_lo + w_hi > 0:
            centre_local[k] = (w_lo * (lo + 0.5 * dim) + w_hi * (hi - 0.5 * dim)) / (w_lo + w_hi)
        else:
            centre_local[k] = 0.5 * (lo + hi)
        half[k] = 0.5 * dim
    if cfg.refine:
        quantile = cfg.fit_quantile if quantile is None else quantile
        if cfg.quantile_by_range:  # the faces' quantile of each point's depth at its range
            quantile = range_quantile(np.linalg.norm(local - cam_local, axis=1), quantile, cfg.reference_range,
                                      floor=cfg.min_quantile)

        def residuals(c: np.ndarray) -> np.ndarray:
            # sum f^2 = 2 scale sum quantile_soft_l1(r): least squares on the signed root
            r = ray_residuals(local - c, cam_local - c, half, cfg.reference_range)
            rho = quantile_soft_l1(r, cfg.fit_loss_scale, quantile)
            return np.sign(r) * np.sqrt(2.0 * cfg.fit_loss_scale * rho)
        fit = least_squares(residuals, centre_local, x_scale=1.0, diff_step=1e-3)
        if fit.success and np.linalg.norm(fit.x - centre_local) <= cfg.max_refine_shift:
            centre_local = fit.x
    centre = np.zeros(3)
    centre[[0, 2]] = centre_local @ basis
    y_lo, y_hi = np.percentile(points[:, _UP_AXIS], [p_lo, p_hi])
    centre[_UP_AXIS] = 0.5 * (y_lo + y_hi)
    size = np.array([2 * half[0], float(np.clip(y_hi - y_lo, typical[1], largest[1])), 2 * half[1]])
    return centre, size


# --------------------------------------------------------------------------------------------
# Driver
# --------------------------------------------------------------------------------------------

def initialise_instance(instance_id: int, clouds: dict[int, np.ndarray],
                        cameras: dict[int, np.ndarray], cfg: InitConfig,
                        truncated: set[int] | frozenset[int] = frozenset()) -> InstanceInit | None:
    """Attributes of one instance from its clouds per frame offset (None if too few points).

    ``truncated`` lists the offsets where the instance's mask is cut by the image border: their
    clouds show a part of the car that moves with the camera, so they take no part in the
    velocity estimate (no velocity, hence static, when no other frames remain).
    """
    if not clouds or max(len(c) for c in clouds.values()) < cfg.min_points_any:
        return None
    est = estimate_velocity({o: c for o, c in clouds.items() if o not in truncated}, cfg.velocity)
    velocity, n_pairs = est.velocity, est.n_pairs
    dynamic = is_dynamic(velocity, cfg.velocity, est.standard_error, est.effective_pairs)
    motion = velocity if dynamic else np.zeros(3)
    located = consistent_views(clouds, motion, cfg.min_points_any, cfg.agreement_share,
                               cfg.agreement_distance)
    ref = reference_offset(located, cfg.min_points_location)
    cloud_mean = to_target_time(located[ref], ref, motion).mean(axis=0)
    fp = cfg.footprint
    max_off = fp.aggregate_dynamic_offset if dynamic else fp.aggregate_static_offset
    pts, cams = merged_cloud(located, cameras, motion, ref, max_off, fp.max_fit_points)
    yaw = yaw_from_velocity(velocity) if dynamic else dominant_yaw(pts, cfg.orientation)
    axis_seen = dynamic or length_axis_seen(pts, yaw, cfg.orientation)
    if fp.enabled:
        centre, size = fit_footprint(pts, yaw, cams, fp, fp.fit_quantile_for(dynamic))
    else:
        centre, size = cloud_mean.copy(), None
    return InstanceInit(instance_id=instance_id, centre=centre, yaw=yaw, velocity=velocity,
                        dynamic=dynamic, size=size, n_points=len(clouds[ref]), clouds=clouds,
                        reference_offset=ref, cloud_mean=cloud_mean, n_velocity_pairs=n_pairs,
                        velocity_standard_error=est.standard_error,
                        velocity_effective_pairs=est.effective_pairs,
                        truncated=tuple(sorted(truncated)), axis_seen=axis_seen,
                        fit_points=pts, fit_cameras=cams)


def touches_border(mask: np.ndarray, margin: int) -> bool:
    """Whether a mask has a pixel within ``margin`` px of the image border (truncated object)."""
    m = max(int(margin), 1)
    return bool(mask[:m].any() or mask[-m:].any() or mask[:, :m].any() or mask[:, -m:].any())


def collect_clouds(frames: list[StereoFrame], cfg: InitConfig
                   ) -> tuple[dict[int, dict[int, np.ndarray]], dict[int, np.ndarray],
                              dict[int, set[int]]]:
    """Clouds per instance id and frame offset, camera centres per frame offset, and per
    instance the offsets where its mask is cut by the image border (:func:`touches_border`)."""
    offsets = [f.frame_offset for f in frames]
    if len(set(offsets)) != len(offsets):
        raise ValueError(f"frame offsets must be unique, got {sorted(offsets)}")
    clouds: dict[int, dict[int, np.ndarray]] = {}
    truncated: dict[int, set[int]] = {}
    cameras = {}
    for frame in frames:
        cameras[frame.frame_offset] = frame.camera_centre
        if not frame.masks:
            continue
        for iid, cloud in frame_clouds(frame, frame_depth(frame, cfg), cfg).items():
            clouds.setdefault(iid, {})[frame.frame_offset] = cloud
            if touches_border(frame.masks[iid], cfg.velocity.border_margin_px):
                truncated.setdefault(iid, set()).add(frame.frame_offset)
    return clouds, cameras, truncated


def initialise(frames: list[StereoFrame], cfg: InitConfig | None = None) -> dict[int, InstanceInit]:
    """Initial 3D attributes of every instance seen in ``frames`` (VSRD++ §III-D).

    Args:
        frames: posed stereo frames with instance masks (the target frame has offset 0).
        cfg: settings; ``depth_mode == "none"`` returns ``{}`` (callers use their default box).
    Returns instance id -> :class:`InstanceInit`, for instances with enough points.
    """
    cfg = cfg or InitConfig()
    if cfg.depth_mode == "none":
        return {}
    clouds, cameras, truncated = collect_clouds(frames, cfg)
    out = {}
    for iid in sorted(clouds):
        init = initialise_instance(iid, clouds[iid], cameras, cfg, truncated.get(iid, set()))
        if init is not None:
            out[iid] = init
    return out


#: Colours (RGB) cycled over instances in :func:`save_point_clouds_ply`.
_PALETTE = np.array([[230, 25, 75], [60, 180, 75], [255, 225, 25], [0, 130, 200], [245, 130, 48],
                     [145, 30, 180], [70, 240, 240], [240, 50, 230], [210, 245, 60], [0, 128, 128]],
                    dtype=np.uint8)


def save_point_clouds_ply(path: str | Path, inits: dict[int, InstanceInit],
                          at_target_time: bool = True) -> int:
    """Write every instance's clouds (all frames) as one coloured PLY point cloud (trimesh).

    Args:
        path: output ``.ply``.
        inits: result of :func:`initialise`.
        at_target_time: move dynamic instances' clouds by ``-v * dt`` to the target time.
    Returns the number of points written.
    """
    import trimesh

    pts, cols = [], []
    for k, (iid, init) in enumerate(sorted(inits.items())):
        motion = init.velocity if (init.dynamic and at_target_time) else np.zeros(3)
        for off, cloud in sorted(init.clouds.items()):
            pts.append(to_target_time(cloud, off, motion))
            cols.append(np.repeat(_PALETTE[k % len(_PALETTE)][None], len(cloud), 0))
    if not pts:
        raise ValueError("no points to write")
    points = np.concatenate(pts)
    colours = np.concatenate(cols)
    alpha = np.full((len(colours), 1), 255, np.uint8)
    trimesh.PointCloud(points, colors=np.hstack([colours, alpha])).export(str(path))
    return len(points)
