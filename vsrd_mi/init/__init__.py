"""vsrd-mi init stage: 3D attribute initialisation from stereo depth (VSRD++ §III-D).

:func:`initialise` turns posed stereo frames with instance masks (:class:`StereoFrame`) into an
initial box per instance (:class:`InstanceInit`: centre, yaw, velocity, dynamic flag, size).
Depth comes from OpenCV semi-global matching, from a directory of depth maps, or not at all
(:mod:`.depth`); settings live in :mod:`.config`.
"""

from .attributes import InstanceInit, initialise, save_point_clouds_ply
from .config import (FootprintConfig, InitConfig, OrientationConfig, PointCloudConfig,
                     StereoConfig, VelocityConfig)
from .frames import StereoFrame

__all__ = ["InstanceInit", "initialise", "save_point_clouds_ply", "StereoFrame", "InitConfig",
           "StereoConfig", "PointCloudConfig", "VelocityConfig", "FootprintConfig",
           "OrientationConfig"]
