"""Fragments of one object become one tube before selection (issue 18, scope 2), on renderer
output: a gap in an object's proposals is bridged by the generator's join, and tubes that
continue each other with agreeing masks are linked into one candidate."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from conftest import MODEL
from mining.config import load_config
from mining.eval.synthetic import gt_frame
from mining.masks import mask_ioa, mask_iou
from mining.pipeline.frames import frame_records
from mining.pipeline.mine import tube_generator, with_links
from mining.sources import open_source
from mining.tubes.link import candidate_links, join_chain, link_fragments, one_to_one

pytestmark = pytest.mark.slow  # rendered frames with stereo and the ONNX proposer

N_FRAMES = 24
GAP = range(10, 13)  # the frames whose proposals of the target are removed


@pytest.fixture(scope="module")
def parked_pair():
    """Tracking frames and truth of the 'parkedpair' scenario (parked cars at 35–55 m)."""
    if not MODEL.exists():
        pytest.skip(f"no ONNX model at {MODEL}")
    cfg = load_config(None, ['proposals.proposer="onnx+stereo"', f'proposals.onnx.model_path="{MODEL}"',
                             'source.options={scenario="parkedpair"}'])
    src = open_source("synthetic", None, n_frames=N_FRAMES, scenario="parkedpair")
    plan = src.plan("0000")
    frames, truths = [], {}
    for rec in frame_records(src, plan, 0, N_FRAMES, cfg):
        frames.append(rec.tracking)
        truths[rec.frame.index] = gt_frame(rec.frame.truth)
    return cfg, frames, truths


def _matches(frame, truth, track: int) -> np.ndarray:
    """Observations of ``frame`` whose masks are ``track``'s ground truth (IoU ≥ 0.5)."""
    g = int(np.flatnonzero(truth.track_ids == track)[0])
    rles = frame.observations.proposals.rles
    if not rles:
        return np.zeros(0, np.int64)
    return np.flatnonzero(mask_iou([truth.rles[g]], rles)[0] >= 0.5)


def _on_car(frame, truth, track: int) -> np.ndarray:
    """Observations of ``frame`` on ``track``: its matches, and masks lying mostly inside it
    (IoA ≥ 0.5 over their own area: the stereo proposer's colour-refined parts of a far car)."""
    g = int(np.flatnonzero(truth.track_ids == track)[0])
    rles = frame.observations.proposals.rles
    if not rles:
        return np.zeros(0, np.int64)
    inside = mask_ioa(rles, [truth.rles[g]])[:, 0] >= 0.5
    return np.union1d(_matches(frame, truth, track), np.flatnonzero(inside))


def _target(frames, truths) -> int:
    """A ground-truth car proposed in every frame (the one with the most matching proposals)."""
    tracks = set.intersection(*(set(map(int, truths[f.index].track_ids)) for f in frames))
    seen = {t: [len(_matches(f, truths[f.index], t)) for f in frames] for t in tracks}
    ok = [t for t, n in seen.items() if min(n) > 0]
    assert ok, "no object proposed in every frame of the scenario"
    return max(ok, key=lambda t: sum(seen[t]))


def _with_gap(frames, truths, track: int):
    """The frames with every observation of ``track`` removed in the GAP frames."""
    out = []
    for f in frames:
        if f.index in GAP:
            keep = np.setdiff1d(np.arange(len(f.observations)), _on_car(f, truths[f.index], track))
            f = dataclasses.replace(f, observations=f.observations.take(keep))
        out.append(f)
    return out


def _spanning(tubes, frames, truths, track: int) -> list:
    """Tubes observing ``track`` both before and after the gap."""
    out = []
    by_index = {f.index: f for f in frames}
    for t in tubes:
        on = {tf.frame for tf in t.frames if tf.observed
              and tf.obs_index in _matches(by_index[tf.frame], truths[tf.frame], track)}
        if any(k < GAP.start for k in on) and any(k >= GAP.stop for k in on):
            out.append(t)
    return out


def _mine(cfg, frames):
    gen = tube_generator(cfg)
    for f in frames:
        gen.step(f)
    return gen.finish()


def test_a_tube_continues_across_a_gap_in_its_proposals(parked_pair):
    cfg, frames, truths = parked_pair
    track = _target(frames, truths)
    gapped = _with_gap(frames, truths, track)
    off = dataclasses.replace(cfg, tubes=dataclasses.replace(cfg.tubes, join_max_gap_s=0.0))
    # Without joining, no tube bridges three frames without a proposal of the car.
    assert not _spanning(_mine(off, gapped), gapped, truths, track)
    joined = _spanning(_mine(cfg, gapped), gapped, truths, track)
    assert joined
    t = joined[0]
    # The gap is filled with predicted frames: every frame between first and last, once.
    assert [f.frame for f in t.frames] == list(range(t.first_frame, t.last_frame + 1))
    assert not any(f.observed for f in t.frames if f.frame in GAP)
    # The predicted masks over the gap still lie on the car.
    gap_ious = [mask_iou([f.rle], [truths[f.frame].rles[int(np.flatnonzero(truths[f.frame].track_ids == track)[0])]])[0, 0]
                for f in t.frames if f.frame in GAP]
    assert min(gap_ious) > 0.3


def test_a_join_needs_the_continuation_to_be_the_same_object(parked_pair):
    """Over the same gap, the car's tube never continues into a tube on something else: the
    object's later proposals are removed too, so nothing after the gap is the car."""
    cfg, frames, truths = parked_pair
    track = _target(frames, truths)
    gone = []
    for f in frames:
        if f.index >= GAP.start:
            keep = np.setdiff1d(np.arange(len(f.observations)), _on_car(f, truths[f.index], track))
            f = dataclasses.replace(f, observations=f.observations.take(keep))
        gone.append(f)
    tubes = _mine(cfg, gone)
    by_index = {f.index: f for f in frames}
    for t in tubes:
        before = [tf for tf in t.frames if tf.observed and tf.frame < GAP.start
                  and tf.obs_index in _matches(by_index[tf.frame], truths[tf.frame], track)]
        if before:  # the car's tube ends with the car's proposals
            assert all(tf.frame < GAP.start for tf in t.frames if tf.observed)


def test_linked_fragments_agree_and_hand_over_once(parked_pair):
    cfg, frames, truths = parked_pair
    tubes = _mine(cfg, frames)
    links = one_to_one(candidate_links(tubes, cfg.tubes))
    assert links, "no fragments to link in the scenario"
    assert len({k.a for k in links}) == len(links) and len({k.b for k in links}) == len(links)
    for k in links:
        a, b = tubes[k.a], tubes[k.b]
        assert b.first_frame > a.first_frame and b.last_frame > a.last_frame
        oa = {f.frame: f.rle for f in a.frames if f.observed}
        ob = {f.frame: f.rle for f in b.frames if f.observed}
        common = sorted(set(oa) & set(ob))
        ious = mask_iou([oa[f] for f in common], [ob[f] for f in common]).diagonal()
        assert len(common) == k.common and np.mean(ious > cfg.tubes.link_mask_iou) >= cfg.tubes.link_agree_share
        assert k.handover == common[-1]
        joined = join_chain(tubes, [k])
        frames_of = [f.frame for f in joined.frames]
        assert frames_of == sorted(set(frames_of))  # each frame once, in order
        # up to the handover it is a's frames, after it b's
        assert all(f is a.frame_map()[f.frame] for f in joined.frames if f.frame <= k.handover)
        assert all(f is b.frame_map()[f.frame] for f in joined.frames if f.frame > k.handover)


def test_links_are_added_beside_their_fragments(parked_pair):
    cfg, frames, truths = parked_pair
    tubes = _mine(cfg, frames)
    top = max(t.tube_id for t in tubes)
    joined = link_fragments(tubes, cfg.tubes, first_id=top + 1)
    assert joined
    both = with_links(tubes, cfg)
    # the fragments stay candidates; the joined tubes follow with fresh ids
    assert both[: len(tubes)] == tubes and len(both) == len(tubes) + len(joined)
    assert [t.tube_id for t in both[len(tubes):]] == list(range(top + 1, top + 1 + len(joined)))
    for tube, parts in joined:
        assert tube.first_frame == tubes[parts[0]].first_frame and tube.last_frame == tubes[parts[-1]].last_frame
    off = dataclasses.replace(cfg, tubes=dataclasses.replace(cfg.tubes, link_fragments=False))
    assert with_links(tubes, off) == tubes
