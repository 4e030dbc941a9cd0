"""The Mitsuba scene of one target frame: a sensor per frame plus the ``vsrd_silhouette`` integrator.

The scene frame is the target's optimisation frame (:mod:`vsrd_mi.data.observations`); sensor ``i``
is frame ``obs.frames[i]`` (id ``frame_%010d``), carries the frame offset as its ray time, and the
integrator holds the boxes (:func:`vsrd_plugins.box_properties`). The same description is
loaded with ``mi.load_dict`` (:func:`load_scene`) or written as Mitsuba XML (:func:`save_scene_xml`).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any, Sequence as Seq

import numpy as np

import vsrd_mi  # noqa: F401  (selects the Mitsuba variant, registers the plugins)
import mitsuba as mi
from vsrd_plugins import box_properties

from ..data.kitti360 import Sequence
from ..data.observations import ObservationConfig, Observations, load_observations
from ..data.selection import SelectionConfig, spec_for_frame
from ..geometry.boxes import Box3D
from .initial import DefaultInitConfig, default_initial_boxes
from .sensors import perspective_sensor

#: Mitsuba XML scene format version written by :func:`save_scene_xml`.
XML_VERSION = "3.0.0"
#: Id of the integrator in the scene.
INTEGRATOR_ID = "vsrd"
#: XML element names of the plugin types used here (others fall back to their dictionary key).
PLUGIN_TAGS = {"perspective": "sensor", "hdrfilm": "film", "box": "rfilter", "independent": "sampler"}


def sensor_id(frame: int) -> str:
    """Id of the sensor of ``frame``."""
    return f"frame_{int(frame):010d}"


def integrator_dict(boxes: Seq[Box3D], integrator_type: str = "vsrd_silhouette") -> dict:
    """Integrator description holding ``boxes`` (centre, size, yaw, velocity, dynamic flag)."""
    if not boxes:
        raise ValueError("a scene needs at least one box")
    props = box_properties(np.stack([b.centre for b in boxes]), np.stack([b.size for b in boxes]),
                           np.array([b.yaw for b in boxes]), np.stack([b.velocity for b in boxes]),
                           np.array([1 if b.dynamic else 0 for b in boxes]))
    return {"type": integrator_type, "id": INTEGRATOR_ID, **props}


def scene_dict(obs: Observations, boxes: Seq[Box3D], integrator: dict | None = None) -> dict:
    """``mi.load_dict`` description: one sensor per frame of ``obs`` and the integrator.

    ``integrator`` defaults to :func:`integrator_dict` of ``boxes`` (``vsrd_silhouette``).
    """
    scene: dict[str, Any] = {"type": "scene"}
    for i, frame in enumerate(obs.frames):
        sid = sensor_id(frame)
        scene[sid] = perspective_sensor(obs.K[i], obs.cam_to_opt[i], obs.image_size, int(obs.dt[i]), sid)
    scene["integrator"] = integrator if integrator is not None else integrator_dict(boxes)
    return scene


def load_scene(root: str | Path, sequence: int | str, frame: int, boxes: Seq[Box3D] | None = None,
               selection: SelectionConfig | None = None, observation: ObservationConfig | None = None,
               init: DefaultInitConfig | None = None) -> tuple[mi.Scene, Observations]:
    """Load the scene of target ``frame`` of a KITTI-360 sequence.

    Sources and group come from :func:`~vsrd_mi.data.selection.spec_for_frame`; ``boxes`` (in the
    optimisation frame) default to :func:`~vsrd_mi.scene.initial.default_initial_boxes`.
    """
    selection = selection or (observation.selection if observation else SelectionConfig())
    observation = observation or ObservationConfig(selection=selection)
    seq = Sequence(root, sequence)
    obs = load_observations(seq, spec_for_frame(seq, frame, selection), observation)
    if boxes is None:
        boxes = default_initial_boxes(obs, init)
    return mi.load_dict(scene_dict(obs, boxes)), obs


# ----------------------------------------------------------------------------------------------
# XML
# ----------------------------------------------------------------------------------------------


def _format(x: float) -> str:
    return repr(float(x))


def _add_value(parent: ET.Element, name: str, value: Any) -> None:
    if isinstance(value, dict):
        _add_plugin(parent, name, value)
    elif isinstance(value, bool):
        ET.SubElement(parent, "boolean", name=name, value="true" if value else "false")
    elif isinstance(value, (int, np.integer)):
        ET.SubElement(parent, "integer", name=name, value=str(int(value)))
    elif isinstance(value, (float, np.floating)):
        ET.SubElement(parent, "float", name=name, value=_format(value))
    elif isinstance(value, str):
        ET.SubElement(parent, "string", name=name, value=value)
    elif isinstance(value, mi.ScalarTransform4f):
        matrix = np.array(value.matrix, dtype=np.float64).reshape(4, 4)
        t = ET.SubElement(parent, "transform", name=name)
        ET.SubElement(t, "matrix", value=" ".join(_format(x) for x in matrix.ravel()))
    else:
        raise TypeError(f"cannot write property {name!r} of type {type(value).__name__} to Mitsuba XML")


def _add_plugin(parent: ET.Element, key: str, desc: dict) -> None:
    tag = PLUGIN_TAGS.get(desc["type"], key)
    attrs = {"type": desc["type"]}
    if "id" in desc:
        attrs["id"] = desc["id"]
    elem = ET.SubElement(parent, tag, attrs)
    for name, value in desc.items():
        if name not in ("type", "id"):
            _add_value(elem, name, value)


def scene_xml(desc: dict) -> str:
    """Mitsuba XML text of a scene description made by :func:`scene_dict`."""
    root = ET.Element("scene", version=XML_VERSION)
    for key, value in desc.items():
        if key != "type":
            _add_plugin(root, key, value)
    ET.indent(root)
    return ET.tostring(root, encoding="unicode") + "\n"


def save_scene_xml(path: str | Path, obs: Observations, boxes: Seq[Box3D],
                   integrator: dict | None = None) -> Path:
    """Write the scene of :func:`scene_dict` as Mitsuba XML (``mi.load_file`` reads it back)."""
    path = Path(path)
    path.write_text(scene_xml(scene_dict(obs, boxes, integrator)))
    return path
