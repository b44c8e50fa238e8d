"""COCO's 80 classes in the terms of LVIS and TAO: the WordNet synset each is known by, and
TAO's category (id and name) where TAO has one.

LVIS names its categories by WordNet synsets, and TAO and BURST take LVIS v0.5's category list
(ids 1..1230), so a synset is how a COCO class is found there. The facts:

* synsets — REFERENCE: LVIS's COCO-to-synset mapping (lvis-api, ``data/coco_to_synset.json``);
  some are not the obvious word (cow → ``beef.n.01``, handbag → ``bag.n.04``, potted plant →
  ``pot.n.04``, hot dog → ``frank.n.02``).
* TAO ids and names — REFERENCE: TAO's category list (LVIS v0.5), as TrackEval's BURST readers
  ship it (``burst_helpers/tao_categories.json``). 78 classes have one; hot dog and oven have
  none (TrackEval's BURST-OW says the same: its 78 "known" ids are these).
  ``tests/test_export_trackeval.py`` checks this table against that file.
"""

from __future__ import annotations

from mining.formats.coco import COCO_CLASSES

TAO_MAX_ID = 1230  # REFERENCE: TAO's categories are LVIS v0.5's, ids 1..1230

# COCO class → (WordNet synset, TAO category id or None, TAO category name or None).
COCO_IN_LVIS: dict[str, tuple[str, int | None, str | None]] = {
    "person": ("person.n.01", 805, "baby"),  # TAO's name is the first of LVIS v0.5's synonyms
    "bicycle": ("bicycle.n.01", 95, "bicycle"),
    "car": ("car.n.01", 211, "car_(automobile)"),
    "motorcycle": ("motorcycle.n.01", 714, "motorcycle"),
    "airplane": ("airplane.n.01", 4, "airplane"),
    "bus": ("bus.n.01", 174, "bus_(vehicle)"),
    "train": ("train.n.01", 1135, "train_(railroad_vehicle)"),
    "truck": ("truck.n.01", 1144, "truck"),
    "boat": ("boat.n.01", 118, "boat"),
    "traffic light": ("traffic_light.n.01", 1132, "traffic_light"),
    "fire hydrant": ("fireplug.n.01", 452, "fireplug"),
    "stop sign": ("stop_sign.n.01", 1038, "stop_sign"),
    "parking meter": ("parking_meter.n.01", 779, "parking_meter"),
    "bench": ("bench.n.01", 91, "bench"),
    "bird": ("bird.n.01", 99, "bird"),
    "cat": ("cat.n.01", 229, "cat"),
    "dog": ("dog.n.01", 382, "dog"),
    "horse": ("horse.n.01", 579, "horse"),
    "sheep": ("sheep.n.01", 961, "sheep"),
    "cow": ("beef.n.01", 81, "cow"),
    "elephant": ("elephant.n.01", 429, "elephant"),
    "bear": ("bear.n.01", 78, "bear"),
    "zebra": ("zebra.n.01", 1229, "zebra"),
    "giraffe": ("giraffe.n.01", 502, "giraffe"),
    "backpack": ("backpack.n.01", 34, "backpack"),
    "umbrella": ("umbrella.n.01", 1155, "umbrella"),
    "handbag": ("bag.n.04", 35, "handbag"),
    "tie": ("necktie.n.01", 729, "necktie"),
    "suitcase": ("bag.n.06", 36, "suitcase"),
    "frisbee": ("frisbee.n.01", 480, "frisbee"),
    "skis": ("ski.n.01", 982, "ski"),
    "snowboard": ("snowboard.n.01", 993, "snowboard"),
    "sports ball": ("ball.n.06", 41, "ball"),
    "kite": ("kite.n.03", 621, "kite"),
    "baseball bat": ("baseball_bat.n.01", 58, "baseball_bat"),
    "baseball glove": ("baseball_glove.n.01", 60, "baseball_glove"),
    "skateboard": ("skateboard.n.01", 980, "skateboard"),
    "surfboard": ("surfboard.n.01", 1057, "surfboard"),
    "tennis racket": ("tennis_racket.n.01", 1099, "tennis_racket"),
    "bottle": ("bottle.n.01", 133, "bottle"),
    "wine glass": ("wineglass.n.01", 1215, "wineglass"),
    "cup": ("cup.n.01", 347, "cup"),
    "fork": ("fork.n.01", 475, "fork"),
    "knife": ("knife.n.01", 625, "knife"),
    "spoon": ("spoon.n.01", 1018, "spoon"),
    "bowl": ("bowl.n.03", 139, "bowl"),
    "banana": ("banana.n.02", 45, "banana"),
    "apple": ("apple.n.01", 13, "apple"),
    "sandwich": ("sandwich.n.01", 926, "sandwich"),
    "orange": ("orange.n.01", 747, "orange_(fruit)"),
    "broccoli": ("broccoli.n.01", 154, "broccoli"),
    "carrot": ("carrot.n.01", 221, "carrot"),
    "hot dog": ("frank.n.02", None, None),  # not among TAO's categories
    "pizza": ("pizza.n.01", 829, "pizza"),
    "donut": ("doughnut.n.02", 392, "doughnut"),
    "cake": ("cake.n.03", 185, "cake"),
    "chair": ("chair.n.01", 237, "chair"),
    "couch": ("sofa.n.01", 1001, "sofa"),
    "potted plant": ("pot.n.04", 852, "flowerpot"),
    "bed": ("bed.n.01", 79, "bed"),
    "dining table": ("dining_table.n.01", 371, "dining_table"),
    "toilet": ("toilet.n.02", 1117, "toilet"),
    "tv": ("television_receiver.n.01", 1097, "television_set"),
    "laptop": ("laptop.n.01", 642, "laptop_computer"),
    "mouse": ("mouse.n.04", 717, "mouse_(computer_equipment)"),
    "remote": ("remote_control.n.01", 896, "remote_control"),
    "keyboard": ("computer_keyboard.n.01", 299, "computer_keyboard"),
    "cell phone": ("cellular_telephone.n.01", 235, "cellular_telephone"),
    "microwave": ("microwave.n.02", 699, "microwave_oven"),
    "oven": ("oven.n.01", None, None),  # not among TAO's categories
    "toaster": ("toaster.n.02", 1115, "toaster"),
    "sink": ("sink.n.01", 979, "sink"),
    "refrigerator": ("electric_refrigerator.n.01", 428, "refrigerator"),
    "book": ("book.n.01", 126, "book"),
    "clock": ("clock.n.01", 276, "clock"),
    "vase": ("vase.n.01", 1162, "vase"),
    "scissors": ("scissors.n.01", 937, "scissors"),
    "teddy bear": ("teddy.n.01", 1091, "teddy_bear"),
    "hair drier": ("hand_blower.n.01", 544, "hair_dryer"),
    "toothbrush": ("toothbrush.n.01", 1122, "toothbrush"),
}

assert tuple(COCO_IN_LVIS) == COCO_CLASSES


def synset(coco_class: str) -> str:
    """The WordNet synset LVIS gives a COCO class."""
    return COCO_IN_LVIS[coco_class][0]


def tao_category(coco_class: str) -> tuple[int, str] | None:
    """TAO's (id, name) of a COCO class; None for the two TAO lacks (hot dog, oven)."""
    _, cid, name = COCO_IN_LVIS[coco_class]
    return None if cid is None else (cid, name)
