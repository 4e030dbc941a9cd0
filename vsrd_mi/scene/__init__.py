"""vsrd-mi scene stage: Mitsuba sensors, default initial boxes and the per-target scene.

* :mod:`vsrd_mi.scene.sensors` -- ``pixel_rays`` and the matching ``perspective`` sensor.
* :mod:`vsrd_mi.scene.initial` -- ``default_initial_boxes`` (no stereo initialisation available).
* :mod:`vsrd_mi.scene.builder` -- ``scene_dict``, ``load_scene``, ``save_scene_xml``.
"""

from .builder import load_scene, save_scene_xml, scene_dict, scene_xml, sensor_id
from .initial import DefaultInitConfig, default_initial_boxes
from .sensors import perspective_sensor, pixel_rays

__all__ = ["load_scene", "save_scene_xml", "scene_dict", "scene_xml", "sensor_id", "DefaultInitConfig",
           "default_initial_boxes", "perspective_sensor", "pixel_rays"]
