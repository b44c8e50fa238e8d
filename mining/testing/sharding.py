"""Do two catalogues hold the same tubes? (Sharding invariance, issue 4; a test helper.)

Two tubes are compared by their mean mask IoU over the union of their frames (a frame
only one of them covers counts as IoU 0). Tubes are matched one-to-one (Hungarian on
that mean), and a tube *agrees* when its match reaches the threshold.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass

import numpy as np
from pycocotools import mask as mask_utils
from scipy.optimize import linear_sum_assignment

from mining.catalog.views import connect

AGREE_IOU = 0.9  # issue 4: tubes agree at a mean mask IoU of at least 0.9


@dataclass
class TubeAgreement:
    n_reference: int
    n_other: int
    agree: int  # reference tubes whose match reaches the threshold
    best_iou: np.ndarray  # (n_reference,) mean IoU of each reference tube's match (0 unmatched)

    @property
    def fraction(self) -> float:
        return self.agree / max(self.n_reference, 1)


def selected_tube_masks(out: str, sequence: str | None = None) -> dict[str, dict[int, dict]]:
    """tube_id → frame → RLE, for the selected tubes of a catalogue."""
    con = connect(out)
    where = "t.selected" + (f" AND t.sequence = '{sequence}'" if sequence else "")
    rows = con.execute(f"SELECT f.tube_id, f.frame, f.rle_counts, f.rle_h, f.rle_w FROM tube_frames f "
                       f"JOIN tubes t USING (tube_id) WHERE {where}").fetchall()
    out_: dict[str, dict[int, dict]] = defaultdict(dict)
    for tid, frame, counts, h, w in rows:
        out_[tid][frame] = {"size": [h, w], "counts": counts.encode("ascii")}
    return dict(out_)


def tube_agreement(reference: dict[str, dict[int, dict]], other: dict[str, dict[int, dict]],
                   threshold: float = AGREE_IOU) -> TubeAgreement:
    ref_ids, oth_ids = sorted(reference), sorted(other)
    iou_sum = np.zeros((len(ref_ids), len(oth_ids)))
    shared = np.zeros_like(iou_sum)  # frames both tubes cover
    by_frame_ref: dict[int, list[int]] = defaultdict(list)
    by_frame_oth: dict[int, list[int]] = defaultdict(list)
    for i, t in enumerate(ref_ids):
        for f in reference[t]:
            by_frame_ref[f].append(i)
    for j, t in enumerate(oth_ids):
        for f in other[t]:
            by_frame_oth[f].append(j)
    for f, ri in by_frame_ref.items():
        oj = by_frame_oth.get(f)
        if not oj:
            continue
        a = [reference[ref_ids[i]][f] for i in ri]
        b = [other[oth_ids[j]][f] for j in oj]
        iou_sum[np.ix_(ri, oj)] += np.asarray(mask_utils.iou(a, b, [0] * len(b))).reshape(len(a), len(b))
        shared[np.ix_(ri, oj)] += 1
    n_ref = np.array([len(reference[t]) for t in ref_ids], float)
    n_oth = np.array([len(other[t]) for t in oth_ids], float)
    # |union of frames| = |A| + |B| − |A ∩ B|
    mean = iou_sum / np.maximum(n_ref[:, None] + n_oth[None, :] - shared, 1)
    best = np.zeros(len(ref_ids))
    if len(ref_ids) and len(oth_ids):
        r, c = linear_sum_assignment(-mean)
        best[r] = mean[r, c]
    return TubeAgreement(len(ref_ids), len(oth_ids), int((best >= threshold).sum()), best)
