"""``mine render``: a sequence with its selected tubes drawn (mask, id, category), as a video
(``export/render.py`` draws and writes it)."""

from __future__ import annotations

import argparse

from mining.checks import output_file, path_text, positive_float
from mining.pipeline.arguments import frame_range


def add_arguments(rnd: argparse.ArgumentParser) -> None:
    rnd.add_argument("dest", type=output_file, help="DEST.mp4 (H.264 with PyAV, the `video` extra; without it MPEG-4 Part 2, which "
                                  "browsers do not play) or DEST.webm (VP8); H.264 and VP8 play in browsers")
    rnd.add_argument("--out", type=path_text, default="out/catalog", help="catalogue folder")
    rnd.add_argument("--sequence", required=True)
    rnd.add_argument("--where", help="SQL predicate over the tubes table: draw only the selected tubes it matches")
    rnd.add_argument("--depth", action="store_true", help="add a stereo depth panel beside each frame")
    rnd.add_argument("--fps", type=positive_float(1000.0),  # render.MAX_FPS (not imported here: OpenCV is slow to load)
                     help="frame rate, > 0 and ≤ 1000 (default: the sequence's, from its timestamps)")
    rnd.add_argument("--frames", type=frame_range, default=None, metavar="A:B",
                     help="plan positions [A, B) (default: the frames the catalogue mined)")
    rnd.add_argument("--all-candidates", action="store_true",
                     help="also draw the candidates co-selection left out, dimmed (outline and label, no fill)")
    rnd.add_argument("--overwrite", action="store_true",
                     help="DEST exists: replace it (a plain file only; without this flag an existing DEST is refused)")


def run(args: argparse.Namespace) -> int:
    from mining.export.render import run_render

    return run_render(args.out, args.sequence, args.dest, args.where, args.depth, args.fps, args.frames,
                      overwrite=args.overwrite, all_candidates=args.all_candidates)
