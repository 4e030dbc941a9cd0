"""vsrd-mi export stage: labels out of the pipeline and into a detector's hands (the label files
themselves: :mod:`vsrd_mi.data.kitti_labels`).

* :mod:`.calib` - KITTI calib files of exported frames;
* :mod:`.level` - level cameras: the image warp and exact labels for a pitched camera;
* :mod:`.dataset` - ``vsrd-mi export-dataset``: runs -> the KITTI object-detection layout;
* :mod:`.report` / :mod:`.report_render` - ``vsrd-mi report``: a review page of a run;
* :mod:`.cli` - the two sub-commands (``docs/export.md``).
"""
