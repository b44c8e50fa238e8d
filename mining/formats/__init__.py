"""File formats of other tools and datasets, one module each, read and written in one place.

* ``coco`` — the 80 COCO classes: contiguous order and the COCO category ids.
* ``kitti_calib`` — KITTI calibration files (both tracking dialects and the raw-data ones).
* ``kitti_tracking`` — KITTI tracking label / result rows (``label_02``, tracker output)
  and the one writer of tracking results from tubes.
* ``kitti_detections`` — KITTI detection files: PointRCNN's and the result format.
* ``disparity`` — KITTI 16-bit disparity PNG and Middlebury PFM.
* ``poses`` — KITTI odometry poses (one 3×4 camera-to-world matrix per line).
* ``oxford_labels`` — the 4D-GVT RobotCar ("oxford-unknown") label files.

A low floor: these modules import only ``mining.types``, ``mining.errors``, ``mining.masks``
and third-party libraries, so every stage, the catalogue, the pipeline and the evaluation
can use them.
"""
