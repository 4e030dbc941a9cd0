"""vsrd-mi data stage: KITTI-360 readers (:mod:`.kitti360`), instance masks (:mod:`.masks`),
PNG reading (:mod:`.png`), the frames of a target (:mod:`.selection`), everything one target's
optimisation reads (:mod:`.observations`), semantic label ids (:mod:`.labels`) and KITTI label
files, read and written (:mod:`.kitti_labels`)."""
