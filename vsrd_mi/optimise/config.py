"""Configuration of the VSRD++ box optimisation (paper Method §III-B..E, docs/method.md §3-4, §7).

Two presets: :func:`paper_config` reproduces the paper's schedule (3000 steps, 1000 box-only
warm-up steps, 1000 rays, dense sampling); :func:`default_config` is the fast default (adaptive
sampling, fewer steps with the same cosine schedules compressed, a learning rate that decays
less over them, early stopping), chosen by the run-time-versus-error benchmark.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field

from ..config_io import dataclass_from_dict
from ..init.config import InitConfig


#: Forms of the projection loss (see :func:`vsrd_mi.optimise.losses.projection_loss`).
PROJECTION_MODES = ("symmetric", "containment")
#: What the init regulariser holds of a box (``LossWeights.init_anchor``, ``init_anchor_dynamic``).
INIT_ANCHORS = ("centre", "seen_faces")
#: Largest share of a box's extent a car-profile part leaves out at each end (the wheel part's
#: ``CarProfile.overhang`` of the length, the body's bottom raised by ``clearance``): the part
#: keeps at least 0.4 of its box (:func:`vsrd_mi.optimise.losses.box_corners`).
MAX_PART_FRACTION = 0.3


@dataclass(frozen=True)
class LossWeights:
    """Loss weights (paper §IV-B: alpha = 1, beta = 0.1, lambda_slh = 1, lambda_eik = 0.01, lambda_init = 0.1).

    The init regulariser's weights differ from the paper's (``init``, ``init_dynamic``, measured
    below); ``--set weights.init=0.1 --set weights.init_dynamic=0.1`` restores the paper's. The
    default leaves the silhouette term out (``silhouette``, below); the ``paper`` preset has it.
    """

    projection_huber: float = 1.0
    projection_diou: float = 0.1
    #: Weight of the rendered-silhouette BCE (the paper: 1). 0 by default: at the paper's weight
    #: the term is ~1/200 of the pixel-scale projection loss; on the development set parked /
    #: moving cars came out at 0.731 / 0.809 mean 3D IoU with it and 0.731 / 0.808 without, at
    #: 66 against 4 s of optimisation per target (docs/autolabel.md, "No rendered-silhouette
    #: term by default"). With 0 nothing is rendered and the step runs frozen
    #: (``AutolabelConfig.frozen_step``); the residual field acts only through this term and
    #: needs it > 0.
    silhouette: float = 0.0
    eikonal: float = 0.01
    #: Init regulariser weight of parked cars (the paper: 0.1; the authors' code: 1.0). For a parked
    #: car near the direction of travel the ego motion's parallax is too small to resist the
    #: projection loss along the line of sight; 2 held such cars where 0.1 let a van drift 2.3 m
    #: and 20 kept the stereo start's own range error (docs/autolabel.md).
    init: float = 2.0
    #: What the init anchor holds of a parked box: ``"centre"`` (the paper) or ``"seen_faces"``.
    #: The initial centre lies half an *assumed* size behind the faces the stereo cloud measured
    #: (the 4.3 m length floor where the far end is unseen), so a centre anchor makes a box that
    #: the masks lengthen grow towards the camera as much as away from it. ``seen_faces`` holds,
    #: horizontally, the middle of the side and end faces the target camera sees
    #: (:func:`vsrd_mi.optimise.losses.seen_face_normals`), the side face taken
    #: ``CarProfile.mirror`` inside the box: a cloud shows the body's side, and the tight box's
    #: side lies the mirrors' span beyond it (moving cars: ``init_anchor_dynamic``). Development parked
    #: cars (4 targets per street): centre 0.777, seen faces without the inset 0.779, with it
    #: 0.784; development-traffic 0.745 / 0.756 / 0.758; validation 0.735 -> 0.747
    #: (docs/accuracy.md).
    init_anchor: str = "seen_faces"
    #: ``init_anchor`` of moving cars. Their initial centre, too, lies half the assumed length behind
    #: the faces their cloud measured, and most moving cars are seen end-on, so the centre anchor
    #: set their length to the assumed one (city cars +15 % long); with ``seen_faces`` the length
    #: is the masks' where a view measures it and the length prior's where none does
    #: (``length_prior``). Without that prior the masks shrank end-on vans and pickups (development
    #: moving vans -6 -> -15 %, pickups -13 -> -26 %).
    init_anchor_dynamic: str = "seen_faces"
    #: Init regulariser weight of moving cars. A car moving at constant velocity seen from a camera
    #: moving at constant velocity has no depth in its images (its offset, relative velocity and
    #: size scale together), so stereo must outweigh the pixel-scale losses: 0.1 (the paper) left
    #: moving cars at 0.23 mean 3D IoU, 20 at 0.68 (docs/autolabel.md). Since the visible-surface
    #: term holds moving boxes' faces too (``surface_dynamic``), the anchor on the initial centre,
    #: which carries the initialisation's assumed size, need not: weights 20 / 5 / 2 gave the
    #: moving cars of the development seeds 0.816 / 0.833 / 0.828 mean 3D IoU, and 5 raised the
    #: validation seeds' from 0.672 to 0.716 (docs/accuracy.md).
    init_dynamic: float = 5.0
    #: Size prior (not in the paper; on in the ``paper`` preset, off in the default): L1 distance
    #: (m) of each box's size from its initial size. The projection loss hardly sees some
    #: directions of a box (the length of a car seen end-on, the yaw / length trade-off of a car
    #: ahead), so over the paper's 3000 steps boxes drift along them; the prior holds them. The
    #: 600-step default with early stopping does not drift that far, and there the prior cost
    #: accuracy (it pulls cars towards a typical length): off (docs/autolabel.md). 0 switches a term off.
    init_size: float = 0.0
    #: Yaw prior (not in the paper): ``sin^2`` of each parked box's yaw change from its initial yaw
    #: (period pi: a box initialised backwards costs nothing). The initial axis comes from the
    #: stereo cloud's footprint and the axis hypotheses (:mod:`vsrd_mi.optimise.axis`), 2 degrees
    #: off on the development streets (median); the mask boxes alone turned boxes away from it
    #: (the yaw trades against the width, length and range in a 2D box), to 3-13 degrees median
    #: on the parked, angled and perpendicular development streets: weights 0 / 20 / 50 / 200 gave
    #: them 0.675 / 0.697 / 0.705 / 0.709 mean 3D IoU of parked cars (one target each). On the
    #: real Golf, whose initial axis is 4.5 degrees off, the masks do correct it, and the same
    #: weights left its length +2 / +5 / +9 / +16 % long: 20 keeps most of the synthetic gain
    #: without holding a real car's start. See also ``init_size``.
    init_yaw: float = 20.0
    #: ``init_size`` of moving cars (that one applies to parked ones; the ``paper`` preset sets
    #: both to 2). Moving cars are already held by ``init_dynamic``.
    init_size_dynamic: float = 0.0
    #: ``init_yaw`` of moving cars, whose initial axis is their stereo velocity's direction: the
    #: mask boxes turned them too (up to 7 degrees); 0 / 200 gave the moving cars of two
    #: development streets 0.78 / 0.80 mean 3D IoU (8 boxes). The same weight as parked cars'.
    init_yaw_dynamic: float = 20.0
    #: Width prior (not in the paper): L1 distance (m) of each box's width from the width real
    #: vehicles of its length and height have, mirrors included
    #: (:func:`vsrd_mi.geometry.vehicle_sizes.tight_width`, a plane through 23 catalogue vehicles,
    #: residuals 4 cm on average). The mask boxes leave a parked car's width free to trade against
    #: its yaw, length and range: without the prior boxes kept their initial width (1.8 m for
    #: every car whose stereo cloud shows no width) and vans came out 17 % narrow
    #: (docs/accuracy.md, "Widths"). Weights 0 / 2 / 10 / 30 gave the development street
    #: ``parked_mixed`` 0.652 / 0.675 / 0.697 / 0.706 mean 3D IoU of parked cars (two targets; the
    #: two other development streets tried rose likewise): a catalogue this close to real widths
    #: can outweigh the masks. 0 switches it off.
    width_prior: float = 30.0
    #: Length prior (not in the paper) for the moving cars whose length no view measures: L1
    #: distance (m) of the box's length from the length real vehicles of its body width and height
    #: have (:func:`vsrd_mi.geometry.vehicle_sizes.typical_length`, a plane through 43 catalogue
    #: vehicles' body widths, residuals 0.26 m; the box's width less twice ``CarProfile.mirror``),
    #: in place of the width prior (the two planes together would move width and length round
    #: each other). A car driving ahead of the camera or towards it is seen
    #: end-on: its stereo cloud spans 0.5-2 m along its axis and no view's mask box moves by a
    #: pixel when its far end does, while its width and height are what those views show best. Such
    #: a box's length was the initialisation's assumed 4.3 m, held there by the centre anchor: on
    #: development-traffic moving city cars came out +15 % long, vans -10 %. With the faces anchored
    #: (``init_anchor_dynamic``) and this prior at 10, development / development-traffic moving cars
    #: (four targets per street) 0.819 / 0.787 -> 0.819 / 0.858 mean 3D IoU, the traffic set's
    #: moving city cars +15 -> +8 %, hatchbacks +9 -> +2 % (docs/accuracy.md, "Lengths of moving
    #: cars seen end-on"); the plane on body widths, with the catalogue's small cars: 0.833 /
    #: 0.861, worst class length bias 5.7 / 10.5 -> 4.8 / 6.5 % ("The length plane on the body
    #: width"). 0 switches it off.
    length_prior: float = 10.0
    #: A moving box's length counts as measured when, in some view of its target or sources, its
    #: initial box's 2D box moves by at least this many pixels as its far end moves out by
    #: :data:`~vsrd_mi.geometry.camera.LENGTH_PROBE_M` (:func:`vsrd_mi.data.observations.length_view_px`);
    #: below it the length prior holds the length. 1 and 2 px gave the same development figures.
    length_prior_px: float = 1.0
    #: Visible-surface term (not in the paper; :class:`vsrd_mi.optimise.losses.VisibleSurface`):
    #: parked boxes held where their stereo points show the car's faces (``surface``, in metres
    #: at ``SurfaceConfig.reference_range``). The mask boxes alone let a parked box trade its
    #: range against its size. Weights 0 / 10 / 30 / 100 gave the parked cars of the development
    #: seeds 0.678 / 0.692 / 0.704 / 0.710 mean 3D IoU (118 cars, 12 targets); 30 is the largest
    #: that raised every development sequence and kept cars within 10 m (at 100 their boxes sat
    #: ~5 cm too far and lost 0.02 IoU). 0 switches it off.
    surface: float = 30.0
    #: ``surface`` of moving boxes, against their merged cloud as the initialisation moved it to
    #: the target time (its estimated velocity times each frame's offset, within
    #: ``FootprintConfig.aggregate_dynamic_offset`` frames): where the faces lie once the
    #: optimisation has changed the size, beside the init anchor (``init_dynamic``).
    #: 0 / 30 gave the moving cars 0.808 / 0.816 mean 3D IoU on the development seeds (every
    #: street up or level) and 0.661 / 0.672 on the validation seeds; with the median of the
    #: depths instead of ``SurfaceConfig.quantile`` for them (their cloud is smeared along the
    #: motion) 0.790 on the development seeds. 0 switches it off.
    surface_dynamic: float = 30.0
    #: Huber (smooth L1) transition, pixels.
    huber_beta: float = 1.0
    #: Projection loss form: "symmetric" (the paper) or "containment" (only mask-box parts outside
    #: the projected box count; see :func:`vsrd_mi.optimise.losses.projection_loss`).
    projection_mode: str = "symmetric"
    #: ``containment`` mode only: weight of the projected box's parts outside the mask box (the
    #: mask box's parts outside the projected box weigh 1; 1 here is the symmetric loss, 0 pure
    #: containment, which does not shrink a too-large start; docs/autolabel.md).
    projection_excess: float = 0.0
    #: Rendered labels are clamped to [eps, 1 - eps] inside the BCE.
    bce_eps: float = 1e-6

    def __post_init__(self) -> None:
        for name in ("init_anchor", "init_anchor_dynamic"):
            if getattr(self, name) not in INIT_ANCHORS:
                raise ValueError(f"weights.{name} must be one of {INIT_ANCHORS}, got {getattr(self, name)!r}")
        for name in ("length_prior", "width_prior"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"weights.{name} must be >= 0, got {getattr(self, name)}")
        if not self.length_prior_px > 0:
            raise ValueError(f"weights.length_prior_px must be > 0 px, got {self.length_prior_px}")
        if self.projection_mode not in PROJECTION_MODES:
            raise ValueError(f"projection_mode must be one of {PROJECTION_MODES}, got {self.projection_mode!r}")


@dataclass(frozen=True)
class CarProfile:
    """What the projection loss projects: the car a box bounds, not the box's 8 corners.

    A car meets the ground only at its wheels, which sit ``overhang`` of its length in from each
    end of its box (axle to bumper: a share of the length, because wheelbases scale with it), and
    the body over the overhangs starts
    ``clearance`` metres above the ground (the bumpers' underside): the box's bottom corners at the
    ends enclose empty space, so a car's mask ends above its box's projected bottom (8.5 px median
    within 10 m), a gap the symmetric projection loss closed by pushing boxes away or shortening
    them. Seen from above most cars' corners are rounded (bumpers wrap around), so in oblique views
    their mask's sides lie inside their box's projected vertical edges, which the loss closed by
    shortening the box. The loss therefore projects parts of each box
    (:func:`vsrd_mi.optimise.losses.projected_boxes`): the body above ``clearance`` as an octagonal
    prism (each plan corner cut along both sides: by ``corner`` metres, or with ``fit_corner`` by a
    cut fitted per car that starts there) and the full height over the length less ``overhang`` at
    each end, and takes the 2D box of their union. The values are those of passenger cars, chosen
    before any run (docs/autolabel.md).
    A box holds the whole vehicle, mirrors included, but the mirrors are thin and sit a third of
    the way back: they widen a car's mask box only in views along its axis, while its body sets the
    mask's sides in every other view. So the projected body is ``mirror`` metres narrower on each
    side than the box: manufacturers' widths with and without mirrors differ by 0.21-0.25 m on
    passenger cars (VW Golf VII 2.027 / 1.799 m, Passat B8 2.083 / 1.832 m, BMW X5 G05 2.218 /
    2.004 m, Tesla Model 3 2.089 / 1.849 m), 0.12 m a side; vans and pickups have larger mirrors.
    A car reaches its box's top only over its roof: bonnet, boot deck or pickup bed end lower.
    Seen from a camera below the roof, the box's top corners at the far end project above the
    roof, and for a vehicle taller than the camera (SUVs, vans, pickups over KITTI-360's 1.55 m)
    the near end's do: matching them to the mask's top edge lowers the box. So the projected body
    ends at ``waist`` of the height outside a roof that spans ``roof`` of the length, centred
    (the front is not known while boxes are fitted). Both are proportions of common body styles,
    not fitted to any run (docs/accuracy.md): flat roofs span about 0.4 of a saloon's or
    hatchback's length (VW Golf VII ~1.8 of 4.26 m, Passat B8 ~1.9 of 4.77 m), 0.5 of an SUV's,
    0.3 of a double-cab pickup's and 0.65 of a van's; bonnets, boot decks and pickup beds end at
    0.6-0.7 of the height. ``roof = 1`` puts the whole top at the box's top.
    ``overhang = clearance = corner = mirror = 0`` and ``roof = 1`` project the box corners (the
    paper).
    """

    clearance: float = 0.25
    #: Axle-to-bumper distance at each end as a share of the box's length: (length - wheelbase)
    #: / 2 / length is 0.18-0.21 on common cars (published lengths / wheelbases: Fiat 500
    #: 3.55 / 2.30 m, VW Golf VII 4.26 / 2.64, Tesla Model 3 4.69 / 2.88, VW Passat B8 4.77 / 2.79,
    #: BMW X5 G05 4.92 / 2.98, VW Transporter T6 4.90 / 3.00, Toyota Hilux 5.33 / 3.09). A fixed
    #: distance (0.9 m) made the wheels of short cars sit too far in and of long ones too far out,
    #: so lengths came out long for city cars and short for pickups (docs/accuracy.md).
    overhang: float = 0.2
    #: Plan-corner cut (metres) of the projected body; with ``fit_corner`` where each box's fit starts.
    corner: float = 0.3
    #: Fit each car's cut with its box, within ``[0, corner_max]``: how far bumpers wrap around
    #: varies from car to car (a box-shaped van hardly cuts its corners, a rounded hatchback more),
    #: and a fixed cut wider than a car's own puts its mask's sides in oblique views outside the
    #: projected body, which the loss closed by lengthening the box (narrower: by shortening it).
    #: The views of a passing camera see the car at different angles, each weighing length, width
    #: and cut differently, so they fix the cut too (docs/accuracy.md, "Each car's plan corners").
    #: Nothing is fitted where ``corner`` is 0 (the box corners' recipe).
    fit_corner: bool = True
    #: Upper bound of the fitted cut (metres; twice the default ``corner``, so that the default's
    #: fit starts at the centre of its range). The projection also caps a cut at
    #: ``MAX_PART_FRACTION`` of the box's smaller extent less ``mirror`` (0.42 m for a 1.8 m wide
    #: box, :func:`~vsrd_mi.optimise.losses.projected_boxes`).
    corner_max: float = 0.6
    mirror: float = 0.12
    #: Share of the box's length over which the car reaches the box's top (centred).
    roof: float = 0.45
    #: Height of the body outside the roof, as a share of the box's height.
    waist: float = 0.65

    @property
    def enabled(self) -> bool:
        return (self.clearance > 0 or self.overhang > 0 or self.corner > 0 or self.mirror > 0
                or self.roof < 1.0)

    def __post_init__(self) -> None:
        if self.clearance < 0 or self.overhang < 0 or self.corner < 0 or self.mirror < 0:
            raise ValueError("CarProfile: clearance, overhang, corner and mirror must be >= 0, got "
                             f"{self.clearance}, {self.overhang}, {self.corner}, {self.mirror}")
        if self.fit_corner and self.corner > 0 and not self.corner < self.corner_max:
            raise ValueError(f"CarProfile: corner_max must exceed corner to fit the cut, got corner="
                             f"{self.corner}, corner_max={self.corner_max}")
        if self.overhang > MAX_PART_FRACTION:
            raise ValueError(f"CarProfile: overhang is a share of the length at each end, at most "
                             f"{MAX_PART_FRACTION}, got {self.overhang}")
        if not 0.0 < self.roof <= 1.0:
            raise ValueError(f"CarProfile: roof must be in (0, 1] (a share of the length), got {self.roof}")
        if not 0.5 <= self.waist <= 1.0:
            raise ValueError("CarProfile: waist must be in [0.5, 1] (a share of the height above the "
                             f"bumpers' underside), got {self.waist}")


@dataclass(frozen=True)
class LearningRates:
    """Adam learning rates per parameter group (docs/method.md §4), decayed exponentially to
    ``decay`` times their start over the whole run."""

    box: float = 1e-2
    velocity: float = 5e-3
    embedding: float = 1e-3
    hypernetwork: float = 1e-4
    #: The paper decays by 0.01 over 3000 steps (:data:`PAPER_LR_DECAY`, the ``paper`` preset).
    #: Over the default's 600 steps the same factor left boxes short of where their masks put
    #: them: Adam moves a latent about its learning rate per step, so the whole run could move a
    #: length by ~1.5 m and its second half by ~0.15 m, while a pickup or van seen from afar
    #: starts at the initialisation's 4.3 m floor and far cars' gradients agree in sign only
    #: slowly. 0.1 (ending at 1e-3, the paper's rate at its step 1500): development-traffic
    #: parked 0.758 -> 0.768 (pickups' length bias -7.4 -> -2.5 %), the development set's worst
    #: class height bias 7.9 -> 4.1 %, at the same time per target; 1200 steps did the same
    #: (docs/accuracy.md).
    decay: float = 0.1


@dataclass(frozen=True)
class Schedule:
    """Sharpness and softmin-temperature annealing (docs/method.md §3): cosine in ``1/s`` from
    ``1/s_start`` to ``1/s_end`` and in ``tau`` from ``tau_start`` to ``tau_end`` over the run."""

    inv_sharpness_start: float = 1.0
    inv_sharpness_end: float = 0.1
    tau_start: float = 1.0
    tau_end: float = 0.1


@dataclass(frozen=True)
class EarlyStop:
    """Stop when, over the last ``window`` steps after ``min_fraction`` of the run, the smoothed
    loss fell by less than ``rel_loss`` (relative) and no box moved more than ``box_tol`` (m,
    centre and size) -- see :class:`vsrd_mi.optimise.optimiser.Convergence`."""

    enabled: bool = True
    min_fraction: float = 0.6
    window: int = 40
    rel_loss: float = 0.01
    box_tol: float = 0.02


@dataclass(frozen=True)
class ConsensusConfig:
    """Sequence-level consensus of parked cars after every target is done (not in the paper;
    :mod:`vsrd_mi.autolabel.consensus`): each parked car's boxes from the targets that see it are
    fused (median centre and size, mean axis of the boxes that agree on it) and the fused box
    replaces them in the labels."""

    enabled: bool = True
    #: Boxes whose centre is farther than this (m) from the median centre are left out (a car
    #: parked at two places, a wrong box). The per-target centres of one parked car agreed to
    #: 0.6 m on seven synthetic sequences; a car that moves is labelled moving and never fused.
    gate: float = 2.0
    #: Fuse a car only when at least this many targets' boxes are inliers (at least 2).
    min_targets: int = 2
    #: A target's box of a car counts ``1 / max(range, near_range)^2`` (its range in metres from
    #: that target's camera): closer views pin a car down better (stereo depth error and the pixel
    #: footprint both scale with range squared); within ``near_range`` all count alike.
    near_range: float = 10.0
    #: Boxes whose axis is farther than this (degrees, modulo 180) from the axis most of the
    #: weight agrees with are left out: a box standing across the car is a wrong box, not an
    #: estimate to average (the weighted mean of two crossed axes is a diagonal that no target
    #: found). One car's boxes from different targets differ by up to ~15 degrees where both are
    #: right, by 45-90 where a target took the wrong axis. 90 switches the gate off.
    axis_gate_deg: float = 30.0

    def __post_init__(self) -> None:
        if self.gate <= 0 or self.min_targets < 2 or self.near_range <= 0:
            raise ValueError(f"ConsensusConfig: gate and near_range must be > 0 and min_targets >= 2, got "
                             f"{self.gate}, {self.near_range}, {self.min_targets}")
        if not 0.0 < self.axis_gate_deg <= 90.0:
            raise ValueError(f"ConsensusConfig: axis_gate_deg must be in (0, 90] degrees, got {self.axis_gate_deg}")


@dataclass(frozen=True)
class SurfaceConfig:
    """Settings of the visible-surface term (weight ``LossWeights.surface``); the same residual
    the initialisation fits footprints with (:class:`vsrd_mi.init.config.FootprintConfig`'s
    ``fit_loss_scale`` and ``reference_range`` have the same meaning and values)."""

    #: Scale (m, at ``reference_range``) of the soft-L1 loss: residuals beyond it (outliers,
    #: mirrors and wheels off the box faces) count linearly.
    scale: float = 0.2
    #: Range (m) at which residuals are expressed (scaled by ``(reference_range / range)^2``, the
    #: growth of stereo depth noise with range).
    reference_range: float = 10.0
    #: Points per box (a fixed random subset of the merged cloud).
    max_points: int = 256
    #: About the share of a box's points left in front of its faces: the residuals are weighted
    #: ``1 - quantile`` in front and ``quantile`` behind
    #: (:func:`vsrd_mi.geometry.surface.quantile_soft_l1`). A car's
    #: stereo points lie behind its tight box's faces (the body curves in from the mirrors,
    #: bumpers and wheel arches; windows and bonnet slope back), so the median (0.5) would put the
    #: faces on the body's middle depth.
    quantile: float = 0.1
    #: ``quantile`` holds at ``reference_range``; each point's own follows its range
    #: (:func:`vsrd_mi.geometry.surface.range_quantile`), as the initialisation's footprint fit's.
    quantile_by_range: bool = True
    #: No point's quantile falls below this (the initialisation's ``FootprintConfig.min_quantile``).
    min_quantile: float = 0.1

    def __post_init__(self) -> None:
        if self.scale <= 0 or self.reference_range <= 0 or self.max_points < 1 or not 0 < self.quantile < 1:
            raise ValueError(f"surface.scale and surface.reference_range must be > 0, surface.max_points >= 1 "
                             f"and surface.quantile in (0, 1), got {self.scale}, {self.reference_range}, "
                             f"{self.max_points}, {self.quantile}")
        if not 0.0 <= self.min_quantile < 0.5:  # a floor at or above the median is no floor
            raise ValueError(f"surface.min_quantile must be in [0, 0.5), got {self.min_quantile}")


@dataclass(frozen=True)
class AxisConfig:
    """Length axis of parked cars from yaw hypotheses before the optimisation (not in the paper;
    :mod:`vsrd_mi.optimise.axis`)."""

    #: Try the hypotheses at all (off: the initialisation's yaw).
    enabled: bool = True
    #: A hypothesis replaces the initial yaw when its fitted cost is below this fraction of the
    #: initial yaw's: the swap must be clearly better, since the initial yaw comes from the cloud.
    switch_ratio: float = 0.7
    #: Cars seen in fewer frames keep the initial yaw (too few views to compare widths).
    min_views: int = 3
    #: ... and the switch must also raise the mean silhouette IoU of a car body in the box with the
    #: masks by this much (a turned box's outline differs from a car's in a few hundredths of IoU).
    min_silhouette_gain: float = 0.02
    #: The road's direction and its normal are hypotheses only for cars further than this (m) from
    #: the target camera. Nearer, the stereo cloud's rectangle gives the car's two axes and only
    #: which is the length is in doubt; the road axes there let the mask boxes straighten angled
    #: cars (development streets: 3 cars at 10-17 m turned 43-47 degrees off). Further, stereo
    #: depth noise (0.7 m at 30 m on KITTI-360's rig, 0.25 px disparity noise) reaches a car's
    #: half width and the rectangle itself is unreliable.
    road_hypotheses_beyond: float = 30.0

    def __post_init__(self) -> None:
        if self.road_hypotheses_beyond < 0:
            raise ValueError(f"axis.road_hypotheses_beyond must be >= 0, got {self.road_hypotheses_beyond}")
        if not 0.0 < self.switch_ratio <= 1.0 or self.min_views < 1:
            raise ValueError(f"axis.switch_ratio must be in (0, 1] and axis.min_views >= 1, got "
                             f"{self.switch_ratio}, {self.min_views}")


#: Accepted values of :attr:`HeadingConfig.prior`.
HEADING_PRIORS = ("none", "right-hand", "left-hand")


@dataclass(frozen=True)
class HeadingConfig:
    """Front / back decision of parked cars (not in the paper; :mod:`vsrd_mi.optimise.heading`)."""

    #: Decide headings at all (off: boxes keep the optimiser's yaw).
    enabled: bool = True
    #: Smallest mean-IoU difference between the two ends that turns a box. Silhouette IoUs of
    #: the two ends of a well-fitted box differ by a few hundredths when the views show the car's
    #: side; 0.01 is below that and above the rasteriser's own noise (a pixel's share of a small
    #: car's silhouette).
    min_evidence: float = 0.01
    #: Frames whose mask has fewer pixels than this take no part (too small to show a shape).
    min_mask_pixels: int = 200
    #: Look at the lamps' colour too (red at the rear; :func:`vsrd_mi.optimise.heading.lamp_evidence`).
    lamps: bool = True
    #: Where no end looks lamped, of two ends both seen the one whose pixels are clearly more often
    #: lamp red over the frames is the rear ("red balance", :func:`vsrd_mi.optimise.heading.red_balance`):
    #: a rear lamp seen from the side or from afar covers less than a lamp's share of the end but
    #: is still red.
    red_balance: bool = True
    #: Where neither the lamps nor the silhouettes decide, an end seen head-on without red is a
    #: front ("bare ends", :func:`vsrd_mi.optimise.heading.bare_end_evidence`).
    bare_ends: bool = True
    #: The lamps (or bare ends) decide when at least this many frames showed a lamped (bare) end ...
    min_lamp_views: int = 2
    #: ... and the lamped rears outnumber the lamped fronts (or the reverse) by this share of them.
    min_lamp_evidence: float = 0.5
    #: Which way parked cars are assumed to face when the silhouettes cannot tell: ``"none"`` keeps
    #: the optimiser's yaw; ``"right-hand"`` (traffic drives on the right, the ego along +z of the
    #: optimisation frame) faces a car on the right (x > 0) along +z and one on the left along -z;
    #: ``"left-hand"`` the mirror image.
    prior: str = "none"

    def __post_init__(self) -> None:
        if self.prior not in HEADING_PRIORS:
            raise ValueError(f"heading.prior must be one of {HEADING_PRIORS}, got {self.prior!r}")
        if self.min_evidence < 0 or self.min_mask_pixels < 0:
            raise ValueError("heading.min_evidence and heading.min_mask_pixels must be >= 0")


@dataclass(frozen=True)
class HiddenLengthConfig:
    """Lengths the masks hold from inside only (not in the paper;
    :mod:`vsrd_mi.optimise.hidden_length`): after each target's optimisation, a box whose end is
    hidden in every view and held only where the visible part ends, or (with ``unmeasured``,
    off by default) whose end no view measures, takes the mean length of vehicles at least as long as the masks allow and as tall
    (the catalogue's lengths given heights).
    It reads the open sides of the symmetric projection loss, so it runs only with
    ``weights.projection_mode = "symmetric"`` and ``occlusion_aware`` on (the containment loss
    lets every end move out freely). The costs below are the projection loss's (``weights``'
    Huber and DIoU terms) summed over a box's views."""

    enabled: bool = True
    #: How far (m) each end is moved out and in to see what holds it: a few pixels at 20-60 m.
    probe: float = 0.2
    #: An end is held from inside only when moving it out raises the box's projection loss,
    #: summed over its lanes, by less than this (no view's closed side measures the end; moving
    #: it also moves the roof and wheel parts of the car profile a little, which closed tops and
    #: bottoms feel) ...
    free_cost: float = 0.25
    #: ... and moving it in raises the box's projection loss, summed over its lanes, by at least
    #: this much (the loss's units: a closed side 1.5 px off costs 1 with the default Huber
    #: transition of 1 px).
    min_cost: float = 0.5
    #: ... and in at most this share of the views that see the box does moving it in cost at
    #: least ``free_cost`` (an occluder's edge sweeps along a hidden end as the camera passes;
    #: a seen end that meets an occluder's edge in the image holds in most views).
    max_held_share: float = 0.5
    #: Only a bound at most this many of the prior's standard deviations below its mean length for
    #: the box's height is lengthened: from a bound far below, the truncated mean is the prior's
    #: mean, which made a city car held at 3.1 m 4.4 m long (development set; city cars' length
    #: bias +1.9 -> +7.2 %). One standard deviation (0.45 m) below the mean keeps the long
    #: vehicles whose hidden ends the step is for.
    min_score: float = -1.0
    #: Lengths no view measures (off by default): a box with an end that moving out costs less
    #: than ``free_cost`` and in less than ``min_cost`` takes the same mean length above the
    #: shortest length the masks allow (its free ends moved in by ``probe`` steps until they
    #: cost ``min_cost``). Development set, one target per street: such boxes, 23 of 123, were
    #: 10.4 % off on average at the length the optimisation left them (the initialisation's
    #: 4.3 m, vans among them); the prior's mean for their heights alone, 6.3 %. Four targets per
    #: street: parked / moving 0.837 / 0.819 -> 0.841 / 0.840, worst class length bias 5.8 ->
    #: 4.9 %, but city cars +1.9 -> +4.9 %; development-traffic parked 0.799 unchanged, moving
    #: 0.787 -> 0.781. The validation set's three rounds (reported, then this default set) had
    #: parked 0.796 either way, moving 0.725 -> 0.714 and city cars +9.7 -> +13.0 % with it: the
    #: catalogue's mean length for a car's height cannot tell a city car from a saloon, and a
    #: car seen end-on in every frame (moving ones) took it (docs/accuracy.md).
    unmeasured: bool = False
    #: The shortest length (m) a free end is moved in to: the shortest cars on the road (a Smart
    #: ForTwo is 2.7 m).
    min_length: float = 2.7

    def __post_init__(self) -> None:
        if (self.probe <= 0 or self.min_cost <= 0 or not 0.0 < self.free_cost < self.min_cost
                or not 0.0 < self.max_held_share <= 1.0 or not math.isfinite(self.min_score)
                or not self.min_length > 0):
            raise ValueError(f"hidden_length: probe, min_cost and min_length must be > 0, free_cost in "
                             f"(0, min_cost), max_held_share in (0, 1] and min_score finite, got {self.probe}, "
                             f"{self.min_cost}, {self.min_length}, {self.free_cost}, {self.max_held_share}, "
                             f"{self.min_score}")


@dataclass(frozen=True)
class AutolabelConfig:
    """Everything the per-target optimisation needs; defaults are the fast default preset."""

    name: str = "default"
    steps: int = 600
    #: Box-only steps before the residual field joins (the paper's 1000 of 3000).
    warmup_steps: int = 200
    rays_per_step: int = 1000
    sampling: str = "adaptive"
    band_samples: int = 16
    #: Adaptive sampling: rays whose enlarged boxes are disjoint along them get one band sample per
    #: box instead of ``band_samples`` (exact for the box SDF; see the ``vsrd_silhouette`` plugin).
    isolated_rays: bool = True
    #: Optimise the residual distance field after the warm-up (paper §III-C). Off by default:
    #: at the paper's loss weights the silhouette term is ~1/200 of the pixel-scale projection
    #: term, so boxes came out the same to 0.001 mean 3D IoU with and without the field, at 4-6x
    #: the time (docs/autolabel.md). The field acts only through the silhouette term: the
    #: ``paper`` preset, or ``--set residual=true --set weights.silhouette=1``, turns it on.
    residual: bool = False
    #: How the residual MLP's gradients are computed (the ``vsrd_silhouette`` plugin's
    #: ``residual_gradients``): ``fused`` (hand-written derivatives around one cooperative-vector
    #: kernel) or ``tensor`` (Dr.Jit AD through tensor-mode matmuls, the reference;
    #: docs/integrators.md compares them).
    residual_gradients: str = "fused"
    #: Where nothing is rendered (``weights.silhouette = 0``), run each step as one recorded
    #: ``dr.freeze`` function (:func:`vsrd_mi.optimise.optimiser.box_step`): traced once, then
    #: its kernels replayed (docs/speed.md, "The frozen box step"). Off: traced every step.
    frozen_step: bool = True
    velocity: bool = True
    #: Occlusion-aware projection loss (not in the paper): a side of a mask box that an occluder
    #: or the image edge may cut short (:func:`vsrd_mi.data.masks.open_sides`) only bounds the
    #: projected box from inside. Off: every mask box side is the car's (the paper).
    occlusion_aware: bool = True
    #: Use the stereo attribute initialisation (else the documented default box, see
    #: :func:`vsrd_mi.scene.default_initial_boxes`).
    init: bool = True
    #: Rays are drawn with probability ``sigmoid(signed distance / soft_mask_scale)`` (px).
    soft_mask_scale: float = 10.0
    #: Points per instance for the eikonal term and their finite-difference step (m).
    eikonal_points: int = 128
    eikonal_step: float = 0.02
    seed: int = 0
    weights: LossWeights = field(default_factory=LossWeights)
    car_profile: CarProfile = field(default_factory=CarProfile)
    lr: LearningRates = field(default_factory=LearningRates)
    schedule: Schedule = field(default_factory=Schedule)
    early_stop: EarlyStop = field(default_factory=EarlyStop)
    consensus: ConsensusConfig = field(default_factory=ConsensusConfig)
    heading: HeadingConfig = field(default_factory=HeadingConfig)
    axis: AxisConfig = field(default_factory=AxisConfig)
    surface: SurfaceConfig = field(default_factory=SurfaceConfig)
    hidden_length: HiddenLengthConfig = field(default_factory=HiddenLengthConfig)
    #: The stereo initialisation's settings (used when ``init`` is on; docs/method.md §6), e.g.
    #: ``--set stereo_init.footprint.fit_quantile=0.5``.
    stereo_init: InitConfig = field(default_factory=InitConfig)

    def __post_init__(self) -> None:
        if self.residual and self.weights.silhouette <= 0:
            raise ValueError("residual=true needs weights.silhouette > 0: the residual field shapes the rendered "
                             "silhouettes only (e.g. --set residual=true --set weights.silhouette=1, the paper's)")

    def replace(self, **kw) -> "AutolabelConfig":
        return dataclasses.replace(self, **kw)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def with_overrides(self, assignments: list[str]) -> "AutolabelConfig":
        """This configuration with ``KEY=VALUE`` assignments applied (the CLI's ``--set``).

        ``KEY`` is a dotted field path (``weights.init_dynamic``, ``lr.box``, ``steps``); ``VALUE``
        is read as JSON (numbers, ``true``/``false``) and otherwise kept as a string. An unknown
        key or a value of the wrong type raises :class:`ValueError` naming the key.
        """
        d = self.to_dict()
        for item in assignments:
            key, sep, text = item.partition("=")
            if not sep or not key:
                raise ValueError(f"--set {item!r}: expected KEY=VALUE")
            *parents, leaf = key.split(".")
            node = d
            for part in parents:
                if not isinstance(node.get(part), dict):
                    raise ValueError(f"--set {key}: {part!r} is not a configuration group "
                                     f"(groups: {sorted(k for k, v in node.items() if isinstance(v, dict))})")
                node = node[part]
            if leaf not in node or isinstance(node[leaf], dict):
                raise ValueError(f"--set {key}: unknown field {leaf!r} (fields: "
                                 f"{sorted(k for k, v in node.items() if not isinstance(v, dict))})")
            try:
                value = json.loads(text)
            except json.JSONDecodeError:
                value = text
            old = node[leaf]
            if isinstance(old, tuple) and isinstance(value, list):  # JSON has no tuples
                if len(value) != len(old) or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                     for v in value):
                    raise ValueError(f"--set {key}: {text!r} is not a list of {len(old)} numbers")
                value = tuple(float(v) for v in value)
            # a float field takes any number; other fields exactly their own type (bool is no int)
            accepted = (int, float) if isinstance(old, float) else type(old)
            if isinstance(value, bool) != isinstance(old, bool) or not isinstance(value, accepted):
                raise ValueError(f"--set {key}: {text!r} is not a valid {type(old).__name__} value")
            node[leaf] = float(value) if isinstance(old, float) else value
        return AutolabelConfig.from_dict(d)

    @staticmethod
    def from_dict(d: dict) -> "AutolabelConfig":
        """The configuration :meth:`to_dict` (or its JSON) gave; missing fields keep their
        defaults (:func:`vsrd_mi.config_io.dataclass_from_dict`)."""
        return dataclass_from_dict(AutolabelConfig, d)


#: Weight of the size / yaw prior in long schedules (see ``LossWeights.init_size``).
LONG_SCHEDULE_SHAPE_PRIOR = 2.0
#: The paper's silhouette weight lambda_slh (§IV-B).
PAPER_SILHOUETTE_WEIGHT = 1.0
#: The paper's learning-rate decay over its 3000 steps (§IV-B: 1e-2 -> 1e-4 for the boxes).
PAPER_LR_DECAY = 0.01


def paper_config() -> AutolabelConfig:
    """The paper's settings: 3000 steps, RDF on from step 1000, 1000 rays, dense sampling, no early stop.

    The loss weights are the default's (:class:`LossWeights`, including ``init_dynamic`` and the
    yaw priors) plus the paper's silhouette term (``LossWeights.silhouette``, which the residual
    field acts through) and the size prior, which 3000 steps need (``LossWeights.init_size``), and the
    projection loss projects the default's :class:`CarProfile` (the paper projects the box's corners:
    ``--set car_profile.clearance=0 --set car_profile.overhang=0 --set car_profile.corner=0
    --set car_profile.mirror=0 --set car_profile.roof=1``).
    A moving box seen end-on takes the length prior (``LossWeights.length_prior``, weight 10) as in
    the default, which outweighs the size prior's hold on its initial length.
    The sequence-level consensus of parked cars (:class:`ConsensusConfig`, not in the paper)
    runs after the targets in both presets (``--set consensus.enabled=false``); both presets also
    lengthen, at the end of each target's optimisation, the lengths the masks hold from inside
    only (:class:`HiddenLengthConfig`, ``--set hidden_length.enabled=false``).
    """
    # the yaw priors stay the default's (stronger than the long schedule's size prior)
    weights = dataclasses.replace(LossWeights(), silhouette=PAPER_SILHOUETTE_WEIGHT,
                                  init_size=LONG_SCHEDULE_SHAPE_PRIOR,
                                  init_size_dynamic=LONG_SCHEDULE_SHAPE_PRIOR)
    return AutolabelConfig(name="paper", steps=3000, warmup_steps=1000, rays_per_step=1000,
                           sampling="dense", residual=True, weights=weights,
                           lr=LearningRates(decay=PAPER_LR_DECAY), early_stop=EarlyStop(enabled=False))


def default_config() -> AutolabelConfig:
    """The fast default (docs/autolabel.md says why it differs from the paper's)."""
    return AutolabelConfig()


PRESETS = {"default": default_config, "paper": paper_config}
