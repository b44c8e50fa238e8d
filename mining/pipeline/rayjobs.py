"""``mine submit --address http://HOST:8265``: the command line handed to a cluster through Ray Jobs.

The same command line runs there (``--address auto``: the driver joins that cluster);
relative --config, --root and --out are made absolute here and read on the cluster.
This side only submits, prints the job's logs as they come and returns its exit status.
"""

from __future__ import annotations

import os
import shlex
import sys
import time

from mining.errors import ConfigError


# Options of ``mine submit`` that name a local path. On the cluster the job runs in a
# working directory of Ray's, so relative paths are made absolute here before the command
# line travels; they are then read *on the cluster*, which is right when the head is this
# machine or mounts the same files at the same place (URIs such as s3://... pass as they are).
_PATH_OPTIONS = ("--config", "--root", "--out")


def _absolute(path: str) -> str:
    return path if "://" in path else os.path.abspath(path)


def _forwarded_argv(argv: list[str], out: str) -> list[str]:
    """The command line for the cluster: no ``--address``, paths absolute, ``--out`` explicit.

    ``argv`` is what followed ``mine`` (``submit`` first); ``out`` is the catalogue the
    command line means, named explicitly so that the default lands where it would here.
    """
    fwd: list[str] = []
    it = iter(argv)
    for a in it:
        opt, eq, value = a.partition("=")
        if opt == "--address":
            if not eq:
                next(it, None)
            continue
        if opt == "--no-wait":  # the submitting side's choice, not the driver's
            continue
        if opt in _PATH_OPTIONS:
            value = value if eq else next(it, "")
            fwd += [opt, _absolute(value)]
            continue
        fwd.append(a)
    if "--out" not in fwd:
        fwd += ["--out", _absolute(out)]
    return fwd


def _client(address: str):
    try:
        from ray.job_submission import JobSubmissionClient
    except ImportError as e:
        raise ConfigError(f"--address {address} needs Ray Jobs: pip install '.[cluster]' ({e})") from None
    try:
        return JobSubmissionClient(address)
    except ConnectionError as e:
        raise ConfigError(f"no Ray Jobs server at --address {address}: {e}") from None


def ray_jobs_status(address: str, job_id: str | None = None) -> int:
    """``mine status --address http://HEAD:8265``: the cluster's Tube Miner jobs (entrypoint
    ``mine …``), newest first, or one job's status and the last lines of its logs; exit 1
    when the one job asked for failed (or any listed job did), 0 otherwise."""
    client = _client(address)
    if job_id:
        info = client.get_job_info(job_id)
        print(f"{job_id}: {info.status.value}  {info.entrypoint}")
        tail = client.get_job_logs(job_id).rstrip().splitlines()[-15:]
        for line in tail:
            print(f"  {line}")
        return 1 if info.status.value in ("FAILED", "STOPPED") else 0
    jobs = [j for j in client.list_jobs() if (j.entrypoint or "").startswith("mine ")]
    jobs.sort(key=lambda j: j.start_time or 0, reverse=True)
    print(f"{address}: {len(jobs)} Tube Miner job(s)")
    for j in jobs:
        started = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(j.start_time / 1000)) if j.start_time else "-"
        print(f"  {j.submission_id or j.job_id}  {j.status.value:9s}  started {started} UTC  {j.entrypoint}")
    return 1 if any(j.status.value == "FAILED" for j in jobs) else 0


def submit_ray_job(address: str, argv: list[str], out: str, poll_s: float = 1.0, wait: bool = True) -> int:
    """Hand the command line to a cluster through Ray Jobs, print its logs as they come, and
    return its driver's exit status (1 when the job failed without one, e.g. it was stopped).
    With ``wait=False``: print the submission id and return at once (follow it with
    ``mine status --address ADDRESS --job ID``).

    The entrypoint is ``mine ... --address auto``: ``mine`` must be on the PATH the cluster's
    Ray was started with, and the driver joins that cluster (Ray Jobs sets RAY_ADDRESS).
    """
    from ray.job_submission import JobStatus

    client = _client(address)
    entry = shlex.join(["mine", *_forwarded_argv(argv, out), "--address", "auto", "--no-progress"])
    job_id = client.submit_job(entrypoint=entry)
    print(f"submitted Ray job {job_id}: {entry}", file=sys.stderr)
    if not wait:
        print(job_id)
        print(f"follow it with: mine status --address {address} --job {job_id}", file=sys.stderr)
        return 0
    shown = 0
    try:
        while True:
            status = client.get_job_status(job_id)  # before the logs: a finished job's logs are complete
            logs = client.get_job_logs(job_id)
            sys.stdout.write(logs[shown:])
            sys.stdout.flush()
            shown = len(logs)
            if status.is_terminal():
                break
            time.sleep(poll_s)
    except KeyboardInterrupt:
        print(f"\nstopped following; the job goes on (stop it with: ray job stop --address {address} {job_id})",
              file=sys.stderr)
        return 130
    if status == JobStatus.SUCCEEDED:
        return 0
    info = client.get_job_info(job_id)
    reason = (info.message or "").strip().splitlines()[:1]  # the rest repeats the logs shown above
    print(f"Ray job {job_id} {status.value}: {''.join(reason)}".rstrip(), file=sys.stderr)
    code = getattr(info, "driver_exit_code", None)
    return code if code else 1
