"""Geometry shared by every stage: 3D boxes, camera projection, 2D boxes.

Conventions (used everywhere in vsrd-mi):

* Camera / optimisation frame: OpenCV, x right, y down, z forward, metres.
* A 3D box has a centre, a full ``size = (w, h, l)`` along its local ``(x, y, z)`` axes and a yaw
  ``theta`` about +y with ``R_y = [[c, 0, s], [0, 1, 0], [-s, 0, c]]``; the length axis (local +z)
  points along ``(sin theta, 0, cos theta)``. KITTI's ``ry`` is ``theta - pi/2``
  (see :func:`vsrd_mi.geometry.boxes.kitti_ry_from_yaw`).
* Dynamic boxes move with a velocity in metres per frame index: ``centre(dt) = centre + v * dt``.
"""
