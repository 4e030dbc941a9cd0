"""Configuration of the synthetic KITTI-360 generator (:mod:`vsrd_mi.synth`).

Every number the generator uses is a documented field here; defaults follow KITTI-360
(camera rig, frame rate) and typical urban streets (lane and parking widths, car sizes, speeds).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from .cars import ProceduralCarConfig
from .vehicles import VehicleConfig

Range = tuple[float, float]

#: KITTI-360 ``R_rect_00`` (row-major 3x3), as in ``calibration/perspective.txt`` of the release.
KITTI360_R_RECT_00 = (9.999740e-01, -7.141000e-03, -8.900000e-05,
                      7.141000e-03, 9.999690e-01, -3.247000e-03,
                      1.120000e-04, 3.247000e-03, 9.999950e-01)

#: KITTI-360 ``calib_cam_to_pose.txt`` entry ``image_00`` (row-major 3x4): unrectified left camera
#: -> IMU/GPS pose frame (x forward, y right, z down). The camera looks about 5.6 deg downwards.
KITTI360_CAM0_TO_POSE = (0.0371783278, -0.0986182135, 0.9944306009, 1.5752681039,
                         0.9992675562, -0.0053553387, -0.0378902567, 0.0043914093,
                         0.0090621821, 0.9951109327, 0.0983468786, -0.6500000000)


@dataclass(frozen=True)
class RigConfig:
    """The stereo camera rig (KITTI-360 perspective cameras 00 and 01, rectified)."""

    #: Rectified image size ``(width, height)``.
    image_size: tuple[int, int] = (1408, 376)
    fx: float = 552.554261
    fy: float = 552.554261
    cx: float = 682.049453
    cy: float = 238.769549
    #: Stereo baseline in metres; ``P_rect_01[0, 3] = -fx * baseline``.
    baseline: float = 0.594
    #: Rectifying rotation of camera 00 (row-major 3x3).
    r_rect_00: tuple[float, ...] = KITTI360_R_RECT_00
    #: Unrectified cam0 -> pose transform (row-major 3x4).
    cam0_to_pose: tuple[float, ...] = KITTI360_CAM0_TO_POSE
    #: Height of the (rectified) left camera centre above the road, metres.
    camera_height: float = 1.55
    #: Frames per second (velocities per frame = speed / frame_rate).
    frame_rate: float = 10.0
    #: Per-sequence pitch and roll of the rectified left camera relative to the road, degrees
    #: (:func:`~vsrd_mi.synth.world.camera_pitch_roll`: pitch = optical axis below the horizon,
    #: roll = image-right axis above it), each drawn uniformly from its range; the vehicle's
    #: attitude is set so that its camera, mounted as in ``cam0_to_pose``, has them (the ego
    #: noise of :class:`EgoConfig` comes on top). None: the vehicle stands level, which gives
    #: this calibration's own pitch of about 5.7 deg and roll of about -0.1 deg. KITTI-360's
    #: sequence 0000 reads pitch 5.8-6.1 deg, roll -0.7 to -1.0 deg.
    camera_pitch_deg: Range | None = None
    camera_roll_deg: Range | None = None


@dataclass(frozen=True)
class EgoConfig:
    """Ego-vehicle motion: along the centre of the right-hand lane with smooth noise."""

    #: Mean distance driven per frame, metres (KITTI-360: about 0.85 m at 10 Hz).
    step: float = 0.85
    #: Amplitude of the smooth variation of the per-frame step, metres.
    step_jitter: float = 0.04
    #: Amplitude of the smooth lateral offset from the lane centre, metres.
    lateral_jitter: float = 0.15
    #: Amplitudes of the smooth heading / pitch / roll noise, degrees.
    yaw_noise_deg: float = 0.8
    pitch_noise_deg: float = 0.5
    roll_noise_deg: float = 0.3
    #: Range of the periods (frames) of the sinusoids that make up the smooth noise.
    noise_period: tuple[float, float] = (8.0, 60.0)
    #: Number of sinusoids summed per noise channel.
    noise_terms: int = 3


@dataclass(frozen=True)
class RoadConfig:
    """Street layout across the road (lateral offsets from the centre line, metres)."""

    #: One driving lane per direction, this wide (right-hand traffic: the ego drives at -w/2).
    lane_width: float = 3.5
    #: Parking strip outside each lane.
    parking_width: float = 2.4
    kerb_height: float = 0.15
    sidewalk_width: float = 3.0
    #: Largest curvature of the centre line (1/m); curvature varies sinusoidally along the road.
    max_curvature: float = 0.0008
    #: Range of the wavelength of the curvature variation, metres.
    curvature_wavelength: tuple[float, float] = (150.0, 400.0)
    #: Spacing of the road mesh samples along the centre line, metres.
    mesh_step: float = 1.0
    #: Road modelled behind the first and ahead of the last ego position, metres.
    behind: float = 15.0
    ahead: float = 130.0
    #: Building blocks along each side: setback behind the sidewalk, length, height, depth.
    building_setback: tuple[float, float] = (0.0, 4.0)
    building_length: tuple[float, float] = (8.0, 30.0)
    building_height: tuple[float, float] = (6.0, 20.0)
    building_depth: float = 12.0
    #: Facade colours: a grey level in this range plus a per-channel tint of up to +-tint.
    building_grey: tuple[float, float] = (120.0, 215.0)
    building_tint: float = 25.0
    #: Probability of an open gap after a building, and the gap's length range.
    building_gap_prob: float = 0.35
    building_gap: tuple[float, float] = (3.0, 10.0)
    #: Lateral offset of the back wall seen through gaps between buildings; flat terrain lies
    #: between the sidewalks and the back walls.
    back_wall_offset: float = 38.0


@dataclass(frozen=True)
class TrafficConfig:
    """Where the cars go and how they move."""

    #: Parked cars are placed along the parking strips between these offsets (metres along the
    #: road) from the ego's first and last positions.
    parked_range: tuple[float, float] = (3.0, 45.0)
    #: Random lateral offset of parked cars inside their strip.
    parked_lateral_jitter: float = 0.2
    #: Standard deviation of the parked cars' yaw around the road direction, degrees.
    parked_yaw_jitter_deg: float = 4.0
    #: Probability that a parked car faces against the traffic direction of its side.
    parked_reverse_prob: float = 0.3
    #: Probability of an angled parked car, and the range of its angle to the road, degrees.
    angled_prob: float = 0.2
    angled_yaw_deg: tuple[float, float] = (20.0, 40.0)
    #: Parked cars stay this far from the road edge (the kerb) and from the driving lane.
    kerb_clearance: float = 0.1
    lane_intrusion: float = 0.3
    #: Minimum free distance between any two car footprints, metres.
    min_gap: float = 0.6
    #: Speed range of moving cars, m/s.
    speed: tuple[float, float] = (2.0, 12.0)
    #: Probability that a moving car drives in the ego's direction (in the ego lane, ahead).
    same_direction_prob: float = 0.5
    #: Distance kept between the ego camera and a car ahead in its lane at every frame, metres.
    follow_gap: float = 9.0
    #: Extra random distance (range) added to the initial gap of a car ahead, metres.
    follow_extra: tuple[float, float] = (0.0, 25.0)
    #: Range of the frame (as a fraction of the sequence) at which an oncoming car passes the ego.
    oncoming_pass: tuple[float, float] = (0.4, 1.3)
    #: Fraction of cars built procedurally (the rest use the mesh files).
    procedural_fraction: float = 0.5
    #: Mesh-file cars are scaled by ``1 + U(-j, j)``.
    mesh_scale_jitter: float = 0.04
    #: Attempts to place one car before giving up.
    max_tries: int = 300
    #: How parked cars are placed: "scatter" (at random spots of both parallel parking strips,
    #: the fields above) or "rows" (rows along the kerbs in parallel, angled or perpendicular
    #: bays: :class:`ParkingConfig`).
    parking: str = "scatter"
    #: Which vehicles to build, as (entry, weight) pairs drawn in turn from a shuffled deck that
    #: holds each entry ``weight`` times (so every entry comes up once per deck): a procedural
    #: class of :class:`~vsrd_mi.synth.vehicles.VehicleConfig`, a mesh file's stem, or "meshes"
    #: for every mesh file. Mesh cars drawn this way carry lamps and plates. Empty: the
    #: ``procedural_fraction`` draw between the basic procedural cars and the mesh files.
    vehicle_mix: tuple[tuple[str, int], ...] = ()


#: Parking layouts of :class:`ParkingConfig`.
PARKING_LAYOUTS = ("parallel", "angled", "perpendicular")


@dataclass(frozen=True)
class ParkingConfig:
    """Parked cars in rows along both kerbs (``TrafficConfig.parking == "rows"``), metres.

    Each side of the street is cut into segments, each with one layout: parallel (along the
    kerb, facing either way), angled bays (the length axis ``angle_deg`` off the road, leaning
    forwards or backwards along it, nose or tail to the kerb) or perpendicular bays. The parking
    strip of a side is as deep as its deepest segment needs.
    """

    #: Layout probabilities per segment.
    layouts: tuple[tuple[str, float], ...] = (("parallel", 0.5), ("angled", 0.3),
                                              ("perpendicular", 0.2))
    #: Length of a segment along the road (range).
    segment_length: Range = (25.0, 70.0)
    #: Where rows may stand along the road, relative to the ego's first and last positions.
    extent: Range = (0.0, 60.0)
    #: Depth of a parallel strip; a bay is ``bay_length`` deep and ``bay_width`` wide, so an
    #: angled strip is ``bay_length * sin(a) + bay_width * cos(a)`` deep.
    parallel_depth: float = 2.3
    bay_length: float = 5.0
    bay_width: float = 2.5
    #: Angle of angled bays to the road, degrees (one per segment, leaning either way).
    angle_deg: Range = (15.0, 60.0)
    #: Standard deviation of each car's yaw about its bay's direction, degrees.
    yaw_jitter_deg: float = 2.5
    #: Probability that a parallel-parked car faces against its side's traffic direction.
    parallel_reverse_prob: float = 0.4
    #: Probability that a car in an angled or perpendicular bay stands tail to the kerb.
    bay_reverse_prob: float = 0.35
    #: Free distance between neighbouring cars of a row (range; footprint to footprint).
    gap: Range = (0.5, 1.6)
    #: Probability that a slot stays empty, and the length of the hole.
    hole_prob: float = 0.15
    hole_length: Range = (2.0, 8.0)
    #: Distance of a car's kerb-side end from the kerb (range).
    kerb_gap: Range = (0.1, 0.4)
    #: A parked car may reach this far into the driving lane (longer cars are not put in bays).
    lane_intrusion: float = 0.6
    #: Least free distance between any two car footprints (below the smallest ``gap``: a row's
    #: spacing is set by ``gap``, this guards the yaw jitter and the other row).
    min_clearance: float = 0.3
    #: Step by which a car is moved along the row when it is too close to its neighbour.
    retry_step: float = 0.25
    #: Moves per car, and vehicles drawn per slot, before the slot is given up.
    max_moves: int = 40
    max_models: int = 12


#: Prop kinds of :class:`PropConfig`.
PROP_KINDS = ("pole", "sign", "tree", "pedestrian", "bin")


@dataclass(frozen=True)
class PropConfig:
    """Things that are not cars, on the sidewalks and between parked cars (metres, RGB).

    Each kind has its own semantic id in the instance maps (pole 17, traffic sign 20,
    vegetation 21, person 24, trash bin 39), never a car's.
    """

    #: Expected number of each kind per 100 m of street and side (Poisson); none by default.
    density: tuple[tuple[str, float], ...] = ()
    #: Where props may stand along the road, relative to the ego's first and last positions.
    extent: Range = (0.0, 60.0)
    #: Distance behind the kerb of props on the sidewalk (range).
    sidewalk_offset: Range = (0.3, 1.2)
    #: Share of pedestrians and bins standing in the parking strip (between parked cars), and
    #: their least distance from the driving lane.
    in_row_share: float = 0.5
    lane_margin: float = 0.4
    #: Least free distance between a prop and a car footprint or another prop.
    clearance: float = 0.15
    #: Attempts to place one prop.
    max_tries: int = 20
    pole_radius: Range = (0.06, 0.11)
    pole_height: Range = (4.0, 8.0)
    sign_post_radius: Range = (0.03, 0.045)
    sign_height: Range = (2.0, 2.7)
    sign_size: Range = (0.55, 0.8)
    trunk_radius: Range = (0.10, 0.22)
    trunk_height: Range = (2.4, 3.4)
    crown_radius: Range = (1.2, 2.6)
    person_height: Range = (1.50, 1.95)
    person_width: Range = (0.40, 0.52)
    person_depth: Range = (0.22, 0.30)
    bin_size: tuple[Range, Range, Range] = ((0.55, 0.75), (0.55, 0.75), (0.90, 1.10))
    #: Facets around a pole or trunk.
    sections: int = 10
    pole_palette: tuple[tuple[int, int, int], ...] = ((110, 112, 115), (62, 64, 66), (150, 150, 145))
    sign_palette: tuple[tuple[int, int, int], ...] = ((30, 80, 170), (200, 30, 30),
                                                      (230, 230, 230), (240, 200, 30))
    bark_rgb: tuple[int, int, int] = (85, 65, 45)
    foliage_palette: tuple[tuple[int, int, int], ...] = ((60, 95, 40), (45, 80, 35), (85, 115, 50))
    clothes_palette: tuple[tuple[int, int, int], ...] = (
        (40, 40, 45), (30, 45, 90), (120, 30, 35), (200, 200, 195), (90, 90, 95), (160, 120, 60),
        (50, 90, 60), (180, 90, 40))
    skin_palette: tuple[tuple[int, int, int], ...] = ((225, 190, 160), (190, 140, 105),
                                                      (120, 85, 60))
    bin_palette: tuple[tuple[int, int, int], ...] = ((40, 90, 50), (60, 60, 65), (30, 60, 120),
                                                     (150, 150, 150))


@dataclass(frozen=True)
class VisibilityConfig:
    """How the attributes file measures each car's occlusion and truncation (left camera)."""

    #: The car is ray cast alone through every pixel of its projected box inside the image, and
    #: up to this many image sizes beyond each border at a coarser stride (truncation).
    margin: float = 1.0
    #: Pixel stride of those rays outside the image (each hit counts stride^2 pixels).
    margin_stride: int = 4
    #: Largest number of rays per car inside the image: a larger silhouette rectangle is sampled
    #: every k-th pixel in each direction (k as small as keeps the count below this).
    max_rays_per_car: int = 20000
    #: Decimals of the occlusion and truncation written to the file.
    decimals: int = 4


@dataclass(frozen=True)
class TextureConfig:
    """Procedural, piecewise-constant textures (functions of the 3D point) and simple shading.

    Cell sizes are chosen so that stereo matching finds texture at 5-40 m while large flat
    patches keep the PNGs small.
    """

    #: Road asphalt cells (along, across), metres, and the grey range.
    road_cell: tuple[float, float] = (0.6, 0.4)
    road_grey: tuple[int, int] = (62, 118)
    #: Number of grey levels of the piecewise constant textures (fewer -> smaller PNGs).
    levels: int = 6
    #: Lane markings: width, dash length and dash period, metres; paint grey value.
    marking_width: float = 0.15
    dash_length: float = 3.0
    dash_period: float = 9.0
    marking_grey: int = 215
    #: Kerb stones along the road (cell, metres) and their grey range.
    kerb_cell: float = 0.5
    kerb_grey: tuple[int, int] = (150, 205)
    #: Sidewalk tiles and terrain patches: cell (metres), base colour, brightness factor range.
    sidewalk_cell: float = 0.4
    sidewalk_rgb: tuple[int, int, int] = (175, 160, 150)
    sidewalk_modulation: tuple[float, float] = (0.7, 1.2)
    terrain_cell: float = 0.6
    terrain_rgb: tuple[int, int, int] = (95, 120, 60)
    terrain_modulation: tuple[float, float] = (0.6, 1.3)
    #: Facade: brick cells (along, up) and their brightness factor range, window grid (along,
    #: up), window size (metres) and the brightness factor range of the window glass. Windows
    #: start on the first floor.
    facade_cell: tuple[float, float] = (0.9, 0.6)
    facade_modulation: tuple[float, float] = (0.78, 1.18)
    window_grid: tuple[float, float] = (3.2, 3.0)
    window_size: tuple[float, float] = (1.3, 1.5)
    window_modulation: tuple[float, float] = (0.6, 1.5)
    #: Car paint cells (3D, car frame), metres, and the modulation of the paint brightness.
    car_cell: float = 0.16
    car_modulation: float = 0.35
    #: Additive paint modulation (grey levels) so that dark cars keep some texture.
    car_additive: float = 40.0
    #: Car paints (RGB) drawn at random per car.
    car_palette: tuple[tuple[int, int, int], ...] = (
        (225, 225, 222), (180, 182, 186), (120, 122, 126), (60, 62, 66), (165, 30, 30),
        (30, 60, 140), (40, 95, 60), (210, 170, 40), (110, 70, 40), (150, 170, 200))
    glass_rgb: tuple[int, int, int] = (55, 70, 85)
    tyre_rgb: tuple[int, int, int] = (38, 38, 40)
    #: Relative brightness modulation of car glass and tyres (their cells are the paint cells).
    detail_modulation: float = 0.8
    #: Wheel hub discs, headlamps (white), indicators (amber), rear lamps (red), number plates.
    rim_rgb: tuple[int, int, int] = (165, 168, 172)
    headlamp_rgb: tuple[int, int, int] = (235, 236, 230)
    indicator_rgb: tuple[int, int, int] = (235, 150, 35)
    taillamp_rgb: tuple[int, int, int] = (175, 22, 28)
    plate_rgb: tuple[int, int, int] = (228, 228, 218)
    #: Lamps and plates are painted on body faces whose car-frame normal has an x component
    #: beyond this (facing forwards) or below its negative (facing backwards).
    lamp_facing: float = 0.35
    #: Sun direction (world, z up; normalised at use) and the ambient / diffuse light shares.
    sun: tuple[float, float, float] = (0.35, 0.25, 0.9)
    ambient: float = 0.55
    diffuse: float = 0.45
    #: Sky colours at the horizon and towards the zenith.
    sky_horizon: tuple[int, int, int] = (205, 215, 228)
    sky_zenith: tuple[int, int, int] = (110, 150, 210)
    #: Elevation sine at which the sky reaches its zenith colour is ``1 / sky_gradient``.
    sky_gradient: float = 2.5
    #: Props: 3D cell size (metres) and brightness factor range of their colour.
    prop_cell: float = 0.12
    prop_modulation: tuple[float, float] = (0.75, 1.2)


@dataclass(frozen=True)
class SynthConfig:
    """All settings of :func:`vsrd_mi.synth.generate_sequence`."""

    rig: RigConfig = field(default_factory=RigConfig)
    ego: EgoConfig = field(default_factory=EgoConfig)
    road: RoadConfig = field(default_factory=RoadConfig)
    traffic: TrafficConfig = field(default_factory=TrafficConfig)
    texture: TextureConfig = field(default_factory=TextureConfig)
    procedural: ProceduralCarConfig = field(default_factory=ProceduralCarConfig)
    vehicles: VehicleConfig = field(default_factory=VehicleConfig)
    parking: ParkingConfig = field(default_factory=ParkingConfig)
    props: PropConfig = field(default_factory=PropConfig)
    visibility: VisibilityConfig = field(default_factory=VisibilityConfig)
    #: Index of the first frame (KITTI-360 sequences rarely start at 0).
    first_frame: int = 0
    #: PNG compression level (0-9) of the written images.
    png_compression: int = 9
