"""Configuration of the synthetic KITTI-360 generator (:mod:`vsrd_mi.synth`).

Every number the generator uses is a documented field here; defaults follow KITTI-360
(camera rig, frame rate) and typical urban streets (lane and parking widths, car sizes, speeds).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from .cars import ProceduralCarConfig

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
    #: Sun direction (world, z up; normalised at use) and the ambient / diffuse light shares.
    sun: tuple[float, float, float] = (0.35, 0.25, 0.9)
    ambient: float = 0.55
    diffuse: float = 0.45
    #: Sky colours at the horizon and towards the zenith.
    sky_horizon: tuple[int, int, int] = (205, 215, 228)
    sky_zenith: tuple[int, int, int] = (110, 150, 210)
    #: Elevation sine at which the sky reaches its zenith colour is ``1 / sky_gradient``.
    sky_gradient: float = 2.5


@dataclass(frozen=True)
class SynthConfig:
    """All settings of :func:`vsrd_mi.synth.generate_sequence`."""

    rig: RigConfig = field(default_factory=RigConfig)
    ego: EgoConfig = field(default_factory=EgoConfig)
    road: RoadConfig = field(default_factory=RoadConfig)
    traffic: TrafficConfig = field(default_factory=TrafficConfig)
    texture: TextureConfig = field(default_factory=TextureConfig)
    procedural: ProceduralCarConfig = field(default_factory=ProceduralCarConfig)
    #: Index of the first frame (KITTI-360 sequences rarely start at 0).
    first_frame: int = 0
    #: PNG compression level (0-9) of the written images.
    png_compression: int = 9
