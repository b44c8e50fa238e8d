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
        if opt in _PATH_OPTIONS:
            value = value if eq else next(it, "")
            fwd += [opt, _absolute(value)]
            continue
        fwd.append(a)
    if "--out" not in fwd:
        fwd += ["--out", _absolute(out)]
    return fwd


def submit_ray_job(address: str, argv: list[str], out: str, poll_s: float = 1.0) -> int:
    """Hand the command line to a cluster through Ray Jobs, print its logs as they come, and
    return its driver's exit status (1 when the job failed without one, e.g. it was stopped).

    The entrypoint is ``mine ... --address auto``: ``mine`` must be on the PATH the cluster's
    Ray was started with, and the driver joins that cluster (Ray Jobs sets RAY_ADDRESS).
    """
    try:
        from ray.job_submission import JobStatus, JobSubmissionClient
    except ImportError as e:
        raise ConfigError(f"--address {address} needs Ray Jobs: pip install '.[cluster]' ({e})") from None
    try:
        client = JobSubmissionClient(address)
    except ConnectionError as e:
        raise ConfigError(f"no Ray Jobs server at --address {address}: {e}") from None
    entry = shlex.join(["mine", *_forwarded_argv(argv, out), "--address", "auto", "--no-progress"])
    job_id = client.submit_job(entrypoint=entry)
    print(f"submitted Ray job {job_id}: {entry}", file=sys.stderr)
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
