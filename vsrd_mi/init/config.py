"""Configuration of the 3D attribute initialisation (VSRD++ §III-D, docs/method.md §6).

Every threshold of the stage is a documented field here; the defaults are the paper's / the
reference code's values unless a field's documentation says why another value is used.
Units: metres, pixels, frame indices (velocity is in metres per frame index).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..config_io import dataclass_from_dict

#: Depth sources understood by :func:`vsrd_mi.init.depth.make_depth_source`.
DEPTH_MODES = ("sgbm", "dir", "none")


@dataclass
class StereoConfig:
    """OpenCV semi-global matching (``cv2.StereoSGBM``) on a rectified pair.

    The penalties follow OpenCV's documented recipe ``P1 = 8 * C * b^2``, ``P2 = 32 * C * b^2``
    (C channels, b block size). 128 disparities on KITTI-360 (f*B ~ 328 px*m) cover depths from
    2.6 m on; the speckle filter and the left-right check (``disp12_max_diff``) invalidate the
    typical mismatches on textureless car paint and at occlusion borders.
    """

    #: Smallest disparity searched (px).
    min_disparity: int = 0
    #: Number of disparities searched (px, a multiple of 16); the image must be wider than this.
    num_disparities: int = 128
    #: Matching block side (px, odd).
    block_size: int = 5
    #: ``P1 = p1_factor * channels * block_size^2`` (penalty for disparity changes of 1 px).
    p1_factor: int = 8
    #: ``P2 = p2_factor * channels * block_size^2`` (penalty for larger disparity changes).
    p2_factor: int = 32
    #: Maximum left-right disparity difference (px) before a pixel is invalidated.
    disp12_max_diff: int = 1
    #: Margin (%) by which the best cost must beat the second best.
    uniqueness_ratio: int = 10
    #: Regions smaller than this (px) with disparity variation > ``speckle_range`` are invalidated.
    speckle_window_size: int = 100
    #: Disparity variation (px) allowed inside a speckle region.
    speckle_range: int = 2
    #: Pre-filter cap of the x-derivative prefilter.
    pre_filter_cap: int = 63
    #: Run the 3-way SGBM (8 directions would be ``"hh"``; ``"sgbm"`` is 5 directions).
    mode: str = "sgbm_3way"
    #: Post-filter the disparity with ``cv2.ximgproc`` weighted least squares (fills holes; the
    #: photometric-warp selection then decides which pixels to trust). Off by default.
    wls: bool = False
    #: WLS smoothness strength.
    wls_lambda: float = 8000.0
    #: WLS colour sensitivity.
    wls_sigma_color: float = 1.5
    #: Pixels with depth beyond this (m) are marked invalid (disparity < f*B/max_depth): at
    #: 80 m on KITTI-360 one disparity step is already ~20 m of depth.
    max_depth: float = 80.0
    #: The initialisation matches only the part of a frame around its instance masks: the rows
    #: and columns of their union's bounding box, widened by this margin (px) and, to the left,
    #: by the disparity range (:func:`vsrd_mi.init.depth.matching_region`); None matches the whole
    #: image. SGBM's path costs then start at the region's edges instead of the image's, which
    #: changes the disparity of some mask pixels (docs/speed.md, "Stereo initialisation").
    region_margin: int | None = 32


@dataclass
class PointCloudConfig:
    """Depth -> pseudo point cloud of one instance in one frame (Algorithm 1, docs/method.md §6 1-4)."""

    #: Erosion kernel side = ``int(sqrt(mask area) * erosion_factor)`` px (square kernel).
    erosion_factor: float = 0.25
    #: Keep pixels whose left-right photometric warp error is at most this percentile of the
    #: (eroded) mask's errors.
    warp_percentile: float = 40.0
    #: Side (px) of the box filter applied to the per-pixel warp error (1 = no filter); a 3x3 mean
    #: makes the selection less sensitive to single-pixel interpolation noise.
    warp_window: int = 3
    #: Radius (m) of the neighbourhood counted by the density filter.
    density_radius: float = 0.5
    #: Fraction of points with the fewest neighbours dropped by the density filter.
    density_drop_fraction: float = 0.01
    #: Linkage distance (m) of the main-cluster selection (DBSCAN-like, ``min_samples = 1``).
    cluster_eps: float = 0.8
    #: Clouds larger than this are subsampled (deterministically) before filtering: the radius
    #: graph of the clustering grows with the square of the size (2000 points of one car give
    #: ~4e5 pairs, ~0.15 s); means, extents and ICP need far fewer points.
    max_points: int = 2000
    #: Minimum number of valid mask pixels needed to build a cloud at all.
    min_pixels: int = 10


@dataclass
class VelocityConfig:
    """Velocity by translation-only ICP (eq. 11-12, docs/method.md §6 step 5)."""

    #: Frames whose cloud has more than this many points take part in the velocity estimate.
    min_points: int = 100
    #: Frames where an instance's mask comes within this many pixels of the image border are
    #: truncated: the visible part of the car slides with the camera (a parked car beside the
    #: road looks as fast as the ego car), so they are left out of the velocity estimate.
    border_margin_px: int = 2
    #: Frame pairs further apart than this (frame indices) are skipped.
    max_gap: int = 15
    #: ICP iterations at most.
    icp_max_iterations: int = 30
    #: ICP stops when the translation update is below this (m); far below the stereo noise.
    icp_tolerance: float = 1e-3
    #: Source clouds are subsampled to at most this many points for ICP (speed; the target keeps
    #: all its points).
    icp_max_points: int = 400
    #: Each usable frame is registered with its next ``pair_neighbours`` usable frames in time
    #: (within ``max_gap``): 1 = consecutive frames only; a large value = every pair. With
    #: ``gap_weighted`` the longer pairs carry the estimate, so four neighbours give it a
    #: baseline of up to four frame steps per frame at a fraction of the cost of all pairs.
    pair_neighbours: int = 4
    #: Weight each pair's estimate by ``gap^2`` as well as by its point count. A pair's ICP
    #: translation error hardly depends on its gap (the two views see partly different
    #: surfaces, and each frame's stereo cloud is off by its own decimetres), so its velocity
    #: error falls as ``1 / gap`` and inverse-variance weighting favours the long pairs. With
    #: two neighbours and point-count weights only (and the outlier centre weighted, as it was),
    #: parked cars 26-58 m ahead came out at 1.9-5.0 m/s from their consecutive pairs and were
    #: labelled moving: 4 of the 177 target instances of the six 4 + 2 sequences and the bundled
    #: scene. Measured on them (unweighted outlier centre throughout): two
    #: neighbours 2 wrong (1 with the t test of ``significance``), four neighbours 0; the gap
    #: weights then lower the moving cars' speed error median from 0.41 to 0.35 m/s and the
    #: parked cars' apparent speed p90 from 0.64 to 0.28 m/s. docs/method.md §6 (and the authors'
    #: code) weighs by point count only: ``gap_weighted=False`` with ``pair_neighbours=2`` is
    #: that recipe (with this module's outlier rejection and significance test).
    gap_weighted: bool = True
    #: Fraction of nearest-neighbour correspondences kept per ICP iteration (trimmed ICP: the two
    #: clouds see partly different surfaces, the worst-matching points have no partner).
    icp_trim_fraction: float = 0.8
    #: Runs of :func:`vsrd_mi.init.icp.register_translation` whose trimmed RMS is within
    #: ``icp_rms_tolerance_abs + icp_rms_tolerance_rel * best`` (m) of the best run count as
    #: equally good; the smallest translation among them is taken. The absolute part is about
    #: the stereo noise of a car's surface at 10-20 m.
    icp_rms_tolerance_abs: float = 0.02
    icp_rms_tolerance_rel: float = 0.1
    #: Estimates further than ``outlier_mad_factor`` robust standard deviations (1.4826 * MAD of the
    #: distance to the weighted median) from the weighted median are dropped as extreme.
    outlier_mad_factor: float = 3.0
    #: ... but an estimate within this distance (m / frame) of the median is never dropped (keeps
    #: all of a consistent set whose MAD is ~0).
    outlier_floor: float = 0.05
    #: Cars move on the road: drop the vertical (gravity) component of the velocity in the
    #: gravity-aligned optimisation frame, which otherwise only carries stereo noise.
    horizontal_only: bool = True
    #: Frame rate (Hz) used to convert the m/s thresholds below into metres per frame index
    #: (KITTI-360 records at about 10 Hz).
    frame_rate_hz: float = 10.0
    #: Speed (m/s) above which an instance is dynamic. The paper quotes 0.03 m/s, but the ICP
    #: speed of a parked car is far from 0: between two views the visible surface changes (rear,
    #: then side) and stereo depth at 10-30 m is uncertain by decimetres, so parked cars show
    #: apparent speeds of a few tenths of m/s. 1.5 m/s (5.4 km/h, walking pace) sits above that
    #: noise and below the speed of cars in traffic (``vsrd-mi bench init-accuracy``).
    dynamic_speed_threshold: float = 1.5
    #: ... and the velocity must be significantly away from zero: this many standard errors
    #: (spread of the pair estimates, :func:`vsrd_mi.init.attributes.robust_weighted_mean`) when
    #: many pairs agree, more when few carry the mean (Student's t at the same one-sided level,
    #: with the kept pairs' effective count less one as degrees of freedom,
    #: :func:`vsrd_mi.init.attributes.critical_value`; one pair alone never suffices). At long
    #: range a parked car's pair estimates scatter by metres per second around zero (per-frame
    #: depth biases of stereo), a moving car's agree. Two is the usual ~97.7 % one-sided level.
    significance: float = 2.0


@dataclass
class FootprintConfig:
    """Centre correction: a typical-size box footprint fitted to the visible surface.

    A stereo cloud covers only the surfaces facing the camera, so its mean lies in front of the
    box centre. The fit places a box of (at least) typical car size so that its faces that are
    visible from the observing cameras coincide with the near edges of the cloud, and so that the
    cloud lies inside the box.
    """

    #: Typical car size (w, h, l) in metres (KITTI/KITTI-360 car medians: 1.6-1.8 x 1.5 x 4.0-4.4).
    typical_size: tuple[float, float, float] = (1.8, 1.5, 4.3)
    #: Upper bound of the size (w, h, l) used when the cloud is larger than typical (vans, pickups).
    max_size: tuple[float, float, float] = (2.4, 3.0, 6.5)
    #: Percentile (and 100 - it) taken as the near/far edge of the cloud along a box axis; robust to
    #: stereo outliers.
    edge_percentile: float = 5.0
    #: A face counts as seen by a camera when the camera lies at least this far (m) in front of the
    #: plane of the cloud's edge along that axis; otherwise the axis is seen edge-on and the box
    #: is centred on the cloud's extent.
    visibility_margin: float = 0.3
    #: Correct the centre at all (False: the centre is the plain cloud mean, as in the paper).
    enabled: bool = True
    #: Frames within this many frame indices of the reference frame contribute their (motion
    #: compensated) clouds to the footprint and orientation fit of a static car: a parked car seen
    #: from several viewpoints shows more of its faces.
    aggregate_static_offset: int = 25
    #: The same for a dynamic car, whose clouds are moved by ``-v * dt``: velocity errors grow
    #: with ``dt``, so fewer frames are merged.
    aggregate_dynamic_offset: int = 5
    #: The merged cloud is subsampled to at most this many points (speed).
    max_fit_points: int = 4000
    #: Refine the horizontal centre by least squares on the visible faces (see
    #: :func:`vsrd_mi.init.attributes.fit_footprint`).
    refine: bool = True
    #: Scale (m, at ``reference_range``) of the soft-L1 loss of the refinement: residuals beyond
    #: it (outliers, points of mirrors and wheels off the box faces) count linearly.
    fit_loss_scale: float = 0.2
    #: Range (m) at which the depth residuals of the refinement are expressed (they are scaled by
    #: ``(reference_range / range)^2``, the growth of stereo depth noise with range).
    reference_range: float = 10.0
    #: Share of the points the refined footprint leaves in front of its faces (the residuals
    #: weigh ``1 - fit_quantile`` in front, ``fit_quantile`` behind;
    #: :func:`vsrd_mi.geometry.surface.quantile_soft_l1`). The same as the optimisation's
    #: visible-surface term (``SurfaceConfig.quantile``, chosen on the development seeds): a car's
    #: stereo points lie behind its tight box's faces (docs/accuracy.md), so fitting the faces to
    #: the points' median depth (0.5) started boxes too far, and the init anchor held them there.
    fit_quantile: float = 0.1
    #: ``fit_quantile`` of moving cars. Their merged cloud is moved to the target time by the
    #: estimated velocity, whose error smears it along the motion both ways; a low quantile puts
    #: the faces at the front of the smear. While the optimisation anchored a moving box's centre,
    #: 0.5 did better (0.1 doubled the development seeds' mean centre error, 0.24 -> 0.48 m: the
    #: centre lies half an assumed length behind the face); anchoring its faces
    #: (``LossWeights.init_anchor_dynamic``) without the length prior, 0.1 / 0.5 gave
    #: development-traffic's moving cars 0.832 / 0.764 mean 3D IoU and the development set's
    #: 0.784 / 0.785 (docs/accuracy.md).
    fit_quantile_dynamic: float = 0.1
    #: Take ``fit_quantile`` as the faces' quantile at ``reference_range`` and adapt it to each
    #: point's range (:func:`vsrd_mi.geometry.surface.range_quantile`: stereo noise grows with
    #: the square of the range and, far away, dwarfs how far the body lies behind the box's
    #: faces, so the faces move from a low quantile of the depths towards their median).
    quantile_by_range: bool = True
    #: No point's quantile falls below this nearer than ``reference_range``
    #: (:func:`vsrd_mi.geometry.surface.range_quantile`'s ``floor``): there the model's quantile
    #: drops towards 0 (0.03 at 5 m) and the faces went onto the clouds' stereo outliers, in front
    #: of the cars (docs/accuracy.md). The optimisation's ``SurfaceConfig.min_quantile`` is the same.
    min_quantile: float = 0.1
    #: A refinement moving the centre further than this (m, about a car length) from its initial
    #: value is rejected as diverged. Far cars need shifts of ~2 m: their edge percentiles sit
    #: well in front of the surface (depth noise ~0.8 m at 33 m on KITTI-360).
    max_refine_shift: float = 4.0

    def fit_quantile_for(self, dynamic: bool) -> float:
        """The refinement's quantile for a moving (``dynamic``) or a parked car."""
        return self.fit_quantile_dynamic if dynamic else self.fit_quantile

    def __post_init__(self) -> None:
        """Refuse values the fit cannot use, naming the field (``footprint.<field>``)."""
        sizes = (np.asarray(self.typical_size, dtype=float), np.asarray(self.max_size, dtype=float))
        if any(s.shape != (3,) or not np.all(s > 0) for s in sizes) or np.any(sizes[0] > sizes[1]):
            raise ValueError(f"footprint.typical_size and footprint.max_size must be three positive sizes "
                             f"(w, h, l), the typical ones at most the largest, got {self.typical_size}, "
                             f"{self.max_size}")
        checks = (("edge_percentile", 0.0 <= self.edge_percentile < 50.0, "in [0, 50)"),
                  ("visibility_margin", self.visibility_margin >= 0.0, ">= 0"),
                  ("aggregate_static_offset", self.aggregate_static_offset >= 0, ">= 0"),
                  ("aggregate_dynamic_offset", self.aggregate_dynamic_offset >= 0, ">= 0"),
                  ("max_fit_points", self.max_fit_points >= 1, ">= 1"),
                  ("fit_loss_scale", self.fit_loss_scale > 0.0, "> 0"),
                  ("reference_range", self.reference_range > 0.0, "> 0"),
                  ("fit_quantile", 0.0 < self.fit_quantile < 1.0, "in (0, 1)"),
                  ("fit_quantile_dynamic", 0.0 < self.fit_quantile_dynamic < 1.0, "in (0, 1)"),
                  ("min_quantile", 0.0 <= self.min_quantile < 0.5, "in [0, 0.5)"),
                  ("max_refine_shift", self.max_refine_shift > 0.0, "> 0"))
        for name, ok, bound in checks:
            if not ok:
                raise ValueError(f"footprint.{name} must be {bound}, got {getattr(self, name)}")


@dataclass
class OrientationConfig:
    """Yaw of parked cars from the dominant horizontal direction of their cloud (WeakM3D-style)."""

    #: Angular step (degrees) of the rectangle (L-shape) fit search over [0, 90).
    search_step_deg: float = 1.0
    #: Closeness criterion of the L-shape fit (Zhang et al. 2017): a point scores
    #: ``1 / max(d, closeness_floor)`` with d its distance to the nearest rectangle edge. The floor
    #: is about the stereo depth noise at 10-20 m, so that noise does not decide the fit.
    closeness_floor: float = 0.1
    #: Percentile (and 100 - it) taken as the rectangle edges in the L-shape fit (outlier robust).
    edge_percentile: float = 2.0
    #: Least-squares refinements of the searched angle (the floor above makes the search blind
    #: to a few degrees).
    refine_iterations: int = 3
    #: Points further than this (m) from every rectangle edge are left out of the refinement.
    refine_distance: float = 0.3
    #: When the cloud extends further than this (m) along one of the two rectangle axes, that axis
    #: is the car's length (no car is this wide); when neither the extents nor their difference
    #: (below) tell, the axis closer to the optimisation frame's forward (z) direction is chosen:
    #: parked cars mostly line the road being driven.
    length_evidence: float = 2.6
    #: Below that, the axis along which the cloud extends further by more than this (m) is the
    #: length (the stereo noise of a car's surface at 10-30 m is a few decimetres) ...
    extent_margin: float = 0.3
    #: ... unless the cloud is thinner than this (m) along the other axis: then it is one face of
    #: the car, whose extent is a width as often as a length. On the development set the road
    #: prior had put 21 of 44 such parked cars 70-90 degrees off (perpendicular bays, cars across
    #: tight rows); this rule turned 17 of them and no other.
    face_depth: float = 0.6


@dataclass
class InitConfig:
    """All settings of the initialisation stage."""

    #: Where depth comes from: ``"sgbm"`` (stereo matching), ``"dir"`` (precomputed depth maps in
    #: ``depth_dir``) or ``"none"`` (no initialisation; callers use their default box).
    depth_mode: str = "sgbm"
    #: Directory of ``%010d.png`` (uint16, metres * 256) or ``%010d.npy`` (float metres) depth maps.
    depth_dir: str | None = None
    #: Instances need at least this many points in a frame to be located from that frame alone
    #: (docs/method.md §6 step 6; the paper's text says 100, the code 120).
    min_points_location: int = 120
    #: Instances whose clouds hold fewer points than this in every frame get no initialisation.
    min_points_any: int = 20
    #: A frame's cloud takes part in locating its instance when at least ``agreement_share`` of
    #: its points lie within ``agreement_distance`` (m, horizontally) of the other frames' points
    #: (:func:`vsrd_mi.init.attributes.consistent_views`): a stereo mismatch can put a whole
    #: frame's cloud metres from the car, while a frame that shows another face of the car shares
    #: an edge with the frames before and after it. ``agreement_share = 0`` keeps every frame.
    agreement_share: float = 0.2
    agreement_distance: float = 1.0
    stereo: StereoConfig = field(default_factory=StereoConfig)
    cloud: PointCloudConfig = field(default_factory=PointCloudConfig)
    velocity: VelocityConfig = field(default_factory=VelocityConfig)
    footprint: FootprintConfig = field(default_factory=FootprintConfig)
    orientation: OrientationConfig = field(default_factory=OrientationConfig)

    @staticmethod
    def from_dict(d: dict) -> "InitConfig":
        """The configuration ``dataclasses.asdict`` (or its JSON) gave: nested groups rebuilt,
        lists back to tuples where the field holds a tuple; an unknown key raises TypeError."""
        return dataclass_from_dict(InitConfig, d)

    def __post_init__(self) -> None:
        if self.depth_mode not in DEPTH_MODES:
            raise ValueError(f"depth_mode must be one of {DEPTH_MODES}, got {self.depth_mode!r}")
        if self.depth_mode == "dir" and not self.depth_dir:
            raise ValueError("depth_mode 'dir' needs depth_dir")
        if not 0.0 <= self.agreement_share <= 1.0 or self.agreement_distance <= 0:
            raise ValueError(f"agreement_share must be in [0, 1] and agreement_distance > 0, got "
                             f"{self.agreement_share}, {self.agreement_distance}")
