"""The 80 COCO classes: names in the contiguous order models and posteriors use, and the
map from the original COCO annotation category ids (1..90 with ten gaps) to that order.

Two numberings meet in proposal files:

* contiguous, 0..79 (what YOLO-family models output; our posterior columns 0..79, with
  ``UNKNOWN_CLASS`` = 80 after them). The 4D-GVT proposal JSON's ``second_category_id``
  and the keys 1..80 of ``second_posterior`` are this order, 1-based (key 0 is background):
  see shared/data/proposals_4dgvt_format/kitti_tracking_0005/README.md.
* COCO category ids, 1..90 with gaps (12, 26, 29, 30, 45, 66, 68, 69, 71, 83 unused): what
  COCO-format detection results carry in ``category_id``.
"""

from __future__ import annotations

COCO_CLASSES: tuple[str, ...] = (
    "person", "bicycle", "car", "motorcycle", "airplane", "bus", "train", "truck", "boat",
    "traffic light", "fire hydrant", "stop sign", "parking meter", "bench", "bird", "cat", "dog",
    "horse", "sheep", "cow", "elephant", "bear", "zebra", "giraffe", "backpack", "umbrella",
    "handbag", "tie", "suitcase", "frisbee", "skis", "snowboard", "sports ball", "kite",
    "baseball bat", "baseball glove", "skateboard", "surfboard", "tennis racket", "bottle",
    "wine glass", "cup", "fork", "knife", "spoon", "bowl", "banana", "apple", "sandwich", "orange",
    "broccoli", "carrot", "hot dog", "pizza", "donut", "cake", "chair", "couch", "potted plant",
    "bed", "dining table", "toilet", "tv", "laptop", "mouse", "remote", "keyboard", "cell phone",
    "microwave", "oven", "toaster", "sink", "refrigerator", "book", "clock", "vase", "scissors",
    "teddy bear", "hair drier", "toothbrush",
)

# COCO 2017 annotation category id of each contiguous class, in COCO_CLASSES order.
COCO_CATEGORY_IDS: tuple[int, ...] = (
    1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 13, 14, 15, 16, 17, 18, 19, 20, 21, 22, 23, 24, 25, 27, 28,
    31, 32, 33, 34, 35, 36, 37, 38, 39, 40, 41, 42, 43, 44, 46, 47, 48, 49, 50, 51, 52, 53, 54, 55,
    56, 57, 58, 59, 60, 61, 62, 63, 64, 65, 67, 70, 72, 73, 74, 75, 76, 77, 78, 79, 80, 81, 82, 84,
    85, 86, 87, 88, 89, 90,
)

CATEGORY_ID_TO_INDEX: dict[int, int] = {cid: i for i, cid in enumerate(COCO_CATEGORY_IDS)}
CLASS_INDEX: dict[str, int] = {name: i for i, name in enumerate(COCO_CLASSES)}

assert len(COCO_CLASSES) == len(COCO_CATEGORY_IDS) == 80
