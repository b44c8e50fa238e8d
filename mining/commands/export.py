"""``mine export``: the tubes matching a SQL predicate, written in a format other tools read
(``export/run.py`` selects and writes; ``export/registry.py`` names the formats)."""

from __future__ import annotations

import argparse

from mining.checks import count, output_folder, path_text, real
from mining.export.registry import FORMATS as EXPORT_FORMATS

# A copy of a constant whose module loads pyarrow (slow for `mine export --help`); tests/test_labels.py
# checks it equal to its source.
MOTS_MAX_CLASS = 1000  # export/kitti.MOTS_MAX_CLASS


def add_arguments(exp: argparse.ArgumentParser) -> None:
    exp.add_argument("dest", type=output_folder, help="output folder")
    exp.add_argument("--where", default="selected", help="SQL predicate over the tubes table (default: selected)")
    exp.add_argument("--format", choices=list(EXPORT_FORMATS), required=True)
    exp.add_argument("--out", type=path_text, default="out/catalog", help="catalogue folder or URI")
    exp.add_argument("--overwrite", action="store_true",
                     help="DEST holds an earlier export: remove what that export recorded (DEST/.mine-export.json) "
                          "and write this one; other files in DEST are kept")
    exp.add_argument("--margin", type=real(0.0, 10.0), default=None,
                     help="crops: context on each side, as a fraction of the box (default 0.15, at least 8 px)")
    exp.add_argument("--images", action="store_true",
                     help="youtube-vis, tao, burst: also write the video frames (rectified left images, JPEG) the JSON names; "
                          "fiftyone: the videos the manifest names; rerun: the frames, stereo depth and pinhole")
    exp.add_argument("--unknown-class", type=count(1, MOTS_MAX_CLASS - 1), default=None,
                     help="kitti-mots: class id for unknown tubes (default 10, the format's ignore, which MOTS tools drop)")
    exp.add_argument("--category-from", choices=["category", "tag"], default="category",
                     help="tag: a tagged tube's category is its tag (mine label / mine view), as a known class; "
                          "default: the mined category. Every export writes tube_labels.json beside its files")


def run(args: argparse.Namespace) -> int:
    from mining.export.run import run_export

    return run_export(args.out, args.where, args.format, args.dest, args.margin, args.images, args.overwrite,
                      args.unknown_class, args.category_from)
