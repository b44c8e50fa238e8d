"""Where steps run: in this process, or on a pool of Ray actors (local Ray or a cluster).

Both executors are made the same way — ``LocalExecutor(job)``, ``RayExecutor(job)`` — and
take the same calls (``Executor``): ``submit(step, *args)`` while ``free()`` and
``wait()`` for the next result, so the loop in ``submit.py`` does not know which one it
drives. On Ray each worker is an actor holding the steps: a proposer that holds
a model (ONNX) loads once per worker, not once per window. Where the cluster has GPUs (or
``run.proposal_actors`` asks), the proposer's model parts run on proposal actors of their
own instead, one model per GPU, fed batches by the workers' observe steps
(``proposal_stage.py``). System failures (a killed
worker process, a lost node) restart the actor and retry the call; bad input is not a
system failure and comes back as a failed ``StepResult``.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections import deque
from typing import Any, Protocol

from mining.config import JobConfig
from mining.errors import ConfigError
from mining.pipeline.proposal_stage import ProposalWorker, RemoteModels, has_models
from mining.pipeline.schedule import Step
from mining.pipeline.steps import Finalize, Job, Observe, StepResult, Track
from mining.proposals.registry import MODELS


PLACEMENT_TIMEOUT_S = 10.0  # ours: how long the end-of-job placement report waits on an actor


class Executor(Protocol):
    """Where the steps of one job run; ``submit`` only while ``free()``."""

    def free(self) -> bool: ...

    def submit(self, step: str, *args: Any) -> Any:
        """Start ``step`` on ``args``; returns the reference ``wait`` hands back with its result."""

    def pending(self) -> int:
        """How many submitted steps ``wait`` has not returned yet."""

    def wait(self, timeout: float | None = None) -> tuple[Any, StepResult | None, BaseException | None] | None:
        """(reference, result, None) of a finished step, or (reference, None, error) when it
        could not run; None when none finished within ``timeout`` seconds (None: wait on)."""

    def placement(self) -> dict[str, list[dict[str, Any]]]:
        """Where the steps ran: "workers" and "proposal_actors", each {pid, gpu_ids, ...} (``Summary``)."""

    def shutdown(self) -> None: ...


class Worker:
    """The steps of one job, held by one process; ``proposal_actor``: where its observe steps
    send the proposer's model parts (``proposal_stage.ProposalWorker``), None to run them here."""

    def __init__(self, job: Job, proposal_actor: Any = None):
        models = None if proposal_actor is None else RemoteModels(proposal_actor)
        self.steps = {Step.OBSERVE: Observe(job, models), Step.TRACK: Track(job), Step.FINALIZE: Finalize(job)}

    def run(self, step: str, *args: Any) -> StepResult:
        return self.steps[step].run(*args)

    def pid(self) -> int:
        return os.getpid()

    def where(self) -> dict[str, Any]:
        """This process and the GPUs Ray gave it (none: the workers hold CPUs only)."""
        import ray

        gpu_ids = [str(g) for g in ray.get_gpu_ids()] if ray.is_initialized() else []
        return {"pid": os.getpid(), "gpu_ids": gpu_ids}


class LocalExecutor:
    """Runs each step in this process when it is submitted (debugging, profiling)."""

    def __init__(self, job: Job):
        self.worker = Worker(job)
        self.done: deque = deque()
        self.n = 0

    def free(self) -> bool:
        return True

    def submit(self, step: str, *args: Any) -> int:
        self.n += 1
        try:
            self.done.append((self.n, self.worker.run(step, *args), None))
        except Exception as e:  # noqa: BLE001 - reported as the step's failure, like Ray would
            self.done.append((self.n, None, e))
        return self.n

    def pending(self) -> int:
        return len(self.done)

    def wait(self, timeout: float | None = None) -> tuple[int, StepResult | None, BaseException | None]:
        return self.done.popleft()  # steps run in submit: one is always finished

    def placement(self) -> dict[str, list[dict[str, Any]]]:
        return {"workers": [{"pid": os.getpid(), "gpu_ids": []}], "proposal_actors": []}

    def shutdown(self) -> None:
        pass


class RayExecutor:
    """A pool of Ray actors, one per CPU the job may use; one call in flight per actor.

    Runs on the Ray this process has initialised: ``n_workers`` actors (default one per
    CPU of the cluster), each call retried ``max_retries`` times (default the job's
    ``run.max_retries``) after system failures.
    """

    def __init__(self, job: Job, n_workers: int | None = None, max_retries: int | None = None):
        import ray

        self.ray = ray
        n_workers = n_workers or max(1, int(ray.available_resources().get("CPU", 1)))
        max_retries = job.cfg.run.max_retries if max_retries is None else max_retries
        # No num_cpus: an actor needs a CPU to be placed but holds none after, so one that
        # lost its node restarts on a surviving node even when that node's CPUs are all
        # held by the pool (with num_cpus=1 it would wait for a free CPU forever, and so
        # would its call). The pool is sized to the CPUs, so nothing is oversubscribed
        # until a node is lost; SPREAD places the pool across the nodes.
        # The proposal stage: actors holding the model parts and their GPUs; the CPU workers
        # share them round robin. Each holds GPUs for life (nothing else may take them) and
        # a CPU only to be placed (the CPU pool below keeps the cores).
        n_models = proposal_actor_count(job.cfg, cluster_with_gpus(job.cfg, ray))
        gpus = job.cfg.run.gpus_per_proposal_actor
        model_actor = ray.remote(max_restarts=-1, max_task_retries=max_retries, num_gpus=gpus)(ProposalWorker)
        self.proposal_actors = [model_actor.remote(job.cfg.proposals) for _ in range(n_models)]
        actor = ray.remote(max_restarts=-1, max_task_retries=max_retries, scheduling_strategy="SPREAD")(Worker)
        self.actors = [actor.remote(job, self.proposal_actors[i % n_models] if n_models else None)
                       for i in range(n_workers)]
        self.idle = deque(self.actors)
        self.busy: dict[Any, Any] = {}

    def free(self) -> bool:
        return bool(self.idle)

    def submit(self, step: str, *args: Any):
        a = self.idle.popleft()
        ref = a.run.remote(step, *args)
        self.busy[ref] = a
        return ref

    def pending(self) -> int:
        return len(self.busy)

    def wait(self, timeout: float | None = None):
        ready, _ = self.ray.wait(list(self.busy), num_returns=1, timeout=timeout)
        if not ready:
            return None
        ref = ready[0]
        self.idle.append(self.busy.pop(ref))
        try:
            return ref, self.ray.get(ref), None
        except Exception as e:  # noqa: BLE001 - retries are spent: a system failure of this step
            return ref, None, e

    def pids(self) -> list[int]:
        return self.ray.get([a.pid.remote() for a in self.actors])

    def placement(self, timeout: float = PLACEMENT_TIMEOUT_S) -> dict[str, list[dict[str, Any]]]:
        """Empty when an actor does not answer within ``timeout`` (a lost node): it is a report, not a result."""
        try:
            return {"workers": self.ray.get([a.where.remote() for a in self.actors], timeout=timeout),
                    "proposal_actors": self.ray.get([a.where.remote() for a in self.proposal_actors], timeout=timeout)}
        except Exception:  # noqa: BLE001 - the job's results are written; only the report is missing
            return {}

    def shutdown(self) -> None:
        # The calls still in flight (Ctrl-C, an error) are cancelled before their actors go:
        # a call killed with its retries left makes Ray print "… will be retried" lines on the
        # user's terminal after the one "interrupted" line.
        for ref in list(self.busy):
            with contextlib.suppress(Exception):
                self.ray.cancel(ref)
        for a in self.actors + self.proposal_actors:
            self.ray.kill(a)


def cluster_with_gpus(cfg: JobConfig, ray: Any, poll_s: float = 2.0) -> dict[str, float]:
    """The cluster's resources once it holds the GPUs ``run.proposal_actors`` = N asks for.

    A cluster that scales (the launcher's or KubeRay's autoscaler) starts its GPU nodes only
    on demand, so the job asks the autoscaler for the N actors' GPUs (``request_resources``)
    and waits up to ``run.gpu_wait_s`` for them; without N (-1 takes what is there, 0 none),
    or once they are there, the resources as they are. A shortfall after the wait is for
    ``proposal_actor_count`` to name.
    """
    resources = ray.cluster_resources()
    n, gpus = cfg.run.proposal_actors, cfg.run.gpus_per_proposal_actor

    def enough(r: dict[str, float]) -> bool:
        return n * gpus <= r.get("GPU", 0.0) + 1e-9

    if n <= 0 or gpus <= 0 or not has_models(cfg.proposals) or enough(resources):
        return resources
    from ray.autoscaler.sdk import request_resources

    request_resources(bundles=[{"GPU": gpus}] * n)
    deadline = time.monotonic() + cfg.run.gpu_wait_s
    while not enough(resources) and time.monotonic() < deadline:
        time.sleep(min(poll_s, max(0.0, deadline - time.monotonic())))
        resources = ray.cluster_resources()
    return resources


def proposal_actor_count(cfg: JobConfig, resources: dict[str, float]) -> int:
    """How many proposal actors a job starts on a cluster with ``resources`` (``run.proposal_actors``)."""
    n, gpus = cfg.run.proposal_actors, cfg.run.gpus_per_proposal_actor
    if not has_models(cfg.proposals):
        if n > 0:
            raise ConfigError(f"run.proposal_actors={n}, but proposer {cfg.proposals.proposer!r} runs no network "
                              f"(a proposal stage runs {', '.join(MODELS)})")
        return 0
    if n >= 0:
        if n * gpus > resources.get("GPU", 0.0) + 1e-9:
            raise ConfigError(f"run.proposal_actors={n} with run.gpus_per_proposal_actor={gpus}: the cluster has "
                              f"{resources.get('GPU', 0.0):g} GPUs (after waiting up to run.gpu_wait_s="
                              f"{cfg.run.gpu_wait_s:g} s for its autoscaler to bring more)")
        return n
    return int(resources.get("GPU", 0.0) // gpus) if gpus > 0 else 0
