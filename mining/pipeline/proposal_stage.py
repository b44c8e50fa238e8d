"""The proposal stage: the proposer's model parts on actors of their own (GPUs where the cluster has them).

A job whose proposer runs a network (``onnx``, ``torch``, ``fastsam``, ``sam``) can hand that
part to ``run.proposal_actors`` actors, each holding one model and ``run.gpus_per_proposal_actor``
GPUs. The observe steps stay on the CPU workers (decode, geometry, the stereo and json parts,
the union and localisation) and send each window's left images to one proposal actor in
batches of ``run.proposal_batch`` frames, at most ``run.proposal_queue`` batches ahead of
the frame they are working on: that bounds what waits in Ray's object store to
``workers × queue × batch`` left images, however long the sequence (backpressure), and lets
the model's batch run while the CPU works on the batch before it.

Why explicit actors and not Ray Data's ``map_batches``, measured (``mine bench stages``: the same
frames and the same model fed both ways on logical GPUs, docs/RESULTS.md): the actors kept the
GPUs busier, had every GPU at work sooner and held a third to a quarter of the object store that
Ray Data's pools held, with the same proposals frame by frame. And by construction: the observe
step carries geometry state from frame to frame and owns retries, resume and the cache's
identity per window (``steps.py``); a window is a unit both sides already agree on, so the
proposal actors are plain services of it and the fault tests keep their meaning. Ray Data would
also need pandas in the core install and re-materialise frames at every non-fused stage boundary.

A frame's proposals are the same whichever side ran its model parts (``FrameProposer.finish``
joins them in the configured order; a batch gives each frame what it alone would get), so a
job with the stage writes the same tubes as one without it (tested).
"""

from __future__ import annotations

import os
import time
from collections import deque
from collections.abc import Iterator, Sequence
from itertools import islice
from typing import Any, Protocol

import numpy as np

from mining.errors import InputError, MiningError
from mining.proposals.config import ProposalConfig
from mining.proposals.make import FrameProposer
from mining.proposals.registry import MODELS, proposer_names
from mining.types import Proposals, StereoFrame


def has_models(cfg: ProposalConfig) -> bool:
    """Whether the configured proposer has a part a proposal stage could run."""
    return any(n in MODELS for n in proposer_names(cfg.proposer))


class ProposalWorker:
    """One model (per frame size) on one actor; ``propose`` runs a batch of left images."""

    def __init__(self, cfg: ProposalConfig):
        self.cfg = cfg
        self.models: dict[tuple[int, int], FrameProposer] = {}
        self.frames = 0  # frames proposed by this actor (a test reads where the work went)
        # Its busy time: the GPU busy share of a job is the sum over actors over actors × mining time
        # (``Summary``); first and last call in unix time, so the driver can say when work first reached it.
        self.busy_s = 0.0
        self.first_t: float | None = None
        self.last_t: float | None = None

    def propose(self, frame_size: tuple[int, int], frames: Sequence[int],
                images: Sequence[np.ndarray]) -> list[list[Proposals]] | tuple[str, str | None, int | None]:
        """Each frame's model parts; bad input comes back as (reason, path, frame), not as a
        Ray error, so the observe step reports it as it would its own."""
        size = (int(frame_size[0]), int(frame_size[1]))
        try:
            if size not in self.models:  # loading the model is not counted as busy: it is no batch's work
                self.models[size] = FrameProposer(self.cfg, size, frame_parts=False)
            t0, c0 = time.time(), time.perf_counter()
            try:
                out = self.models[size].propose_images(frames, images)
            finally:
                self.busy_s += time.perf_counter() - c0
                self.first_t = t0 if self.first_t is None else self.first_t
                self.last_t = time.time()
        except InputError as e:
            return (e.reason, e.path, e.frame)
        except MiningError as e:
            return (str(e), None, None)
        self.frames += len(frames)
        return out

    def where(self) -> dict[str, Any]:
        """The actor's process, the GPUs Ray gave it, the frames it proposed and its busy time."""
        import ray

        return {"pid": os.getpid(), "gpu_ids": [str(g) for g in ray.get_gpu_ids()], "frames": self.frames,
                "node": ray.get_runtime_context().get_node_id(), "busy_s": self.busy_s,
                "first_t": self.first_t, "last_t": self.last_t}


class ModelStage(Protocol):
    """Where a frame loop's model parts run: ``submit`` a batch, ``result`` of it later, in order."""

    def submit(self, frame_size: tuple[int, int], frames: list[int], images: list[np.ndarray]) -> Any: ...

    def result(self, handle: Any) -> list[list[Proposals]]: ...


class RemoteModels:
    """A ``ModelStage`` on one proposal actor (``ProposalWorker`` under Ray)."""

    def __init__(self, actor: Any):
        import ray

        self.ray, self.actor = ray, actor

    def submit(self, frame_size: tuple[int, int], frames: list[int], images: list[np.ndarray]) -> Any:
        return self.actor.propose.remote(frame_size, frames, images)

    def result(self, handle: Any) -> list[list[Proposals]]:
        out = self.ray.get(handle)
        if isinstance(out, tuple):
            reason, path, frame = out
            raise InputError(reason, path, frame)
        return out


def ahead(frames: Iterator[tuple[int, StereoFrame, bool]], stage: ModelStage, batch: int,
          queue: int) -> Iterator[tuple[int, StereoFrame, bool, list[Proposals]]]:
    """``frames`` (position, frame, after_gap) with each frame's model parts from ``stage``:
    batches of ``batch`` frames, at most ``queue`` submitted and not yet collected."""
    pending: deque = deque()

    def fill() -> None:
        while len(pending) < queue:
            chunk = list(islice(frames, batch))
            if not chunk:
                return
            size = (chunk[0][1].calib.height, chunk[0][1].calib.width)
            pending.append((chunk, stage.submit(size, [f.index for _, f, _ in chunk], [f.left for _, f, _ in chunk])))

    fill()
    while pending:
        chunk, handle = pending.popleft()
        results = stage.result(handle)
        fill()  # at most ``queue`` out: the ones after this run on the model while its frames are worked on here
        for (position, frame, after_gap), models in zip(chunk, results, strict=True):
            yield position, frame, after_gap, models


class LocalModels:
    """A ``ModelStage`` in this process: the model parts of a ``FrameProposer`` run at ``submit``
    (a benchmark timing the stage alone; the same batches a proposal actor would get)."""

    def __init__(self, cfg: ProposalConfig):
        self.worker = ProposalWorker(cfg)

    def submit(self, frame_size: tuple[int, int], frames: list[int], images: list[np.ndarray]) -> Any:
        return self.worker.propose(frame_size, frames, images)

    def result(self, handle: Any) -> list[list[Proposals]]:
        if isinstance(handle, tuple):
            reason, path, frame = handle
            raise InputError(reason, path, frame)
        return handle
