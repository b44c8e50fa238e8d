"""infra/'s GPU worker groups against what the job asks Ray for (issue 42, item 4).

The manifests are parsed and their resources checked with the job's own rules: the job the
GPU RayJob's entrypoint configures (its ``--set`` lines through ``job_config``, the same as
``mine submit``) gets the proposal actors it asks for from the GPUs its pods announce when
it starts (``proposal_actor_count``), each actor fits one pod, Kubernetes is asked for the
GPUs Ray is told of, and the cluster is the one the README's projection sizes.
"""

from __future__ import annotations

import re

import pytest
from conftest import REPO
from test_infra import (INFRA, PYPROJECT, cluster, container_workdir, gpu_pod, gpus_asked, mine_commands, parse,
                        rayjob, repo_relative)

from mining.pipeline.arguments import job_config
from mining.pipeline.executors import proposal_actor_count

# The cluster the README's projection sizes for a learned proposer: 64 cores and 4 GPUs.
CLUSTER_GPUS_PROJECTED = (64.0, 4.0)


def _job(name: str):
    """The JobConfig the RayJob's entrypoint runs (its job config read from this checkout)."""
    args = parse(mine_commands(rayjob(name)["spec"]["entrypoint"])[0])
    args.config = str(REPO / repo_relative(args.config, [container_workdir()]))
    return job_config(args)


def _at_start(name: str) -> dict[str, float]:
    """The Ray resources the RayJob's worker pods announce when the job starts (``replicas`` each: the
    pods KubeRay creates with the cluster; the GPU groups never scale)."""
    total = {"CPU": 0.0, "GPU": 0.0}
    for g in rayjob(name)["spec"]["rayClusterSpec"]["workerGroupSpecs"]:
        c = g["template"]["spec"]["containers"][0]
        cpus = float(g["rayStartParams"].get("num-cpus", c["resources"]["limits"]["cpu"]))
        gpus = float(g["rayStartParams"].get("num-gpus", gpus_asked(c)))
        total["CPU"] += g["replicas"] * cpus
        total["GPU"] += g["replicas"] * gpus
    return total


def test_the_gpu_extra_is_onnxruntimes_cuda_build_at_the_cpu_builds_version():
    extras = PYPROJECT["project"]["optional-dependencies"]
    pins = {re.match(r"[\w-]+", d)[0]: d.split("==")[1] for d in extras["gpu"] + extras["onnx"]}
    assert pins["onnxruntime-gpu"] == pins["onnxruntime"], "one onnxruntime version, CPU or CUDA"
    assert not any(d.startswith("onnxruntime==") for d in extras["gpu"]), "both builds are the module onnxruntime"


def test_every_gpu_pod_asks_kubernetes_for_the_gpus_it_tells_ray():
    groups = rayjob("rayjob-gpu.yaml")["spec"]["rayClusterSpec"]["workerGroupSpecs"]
    assert any(gpu_pod(g) for g in groups) and not all(gpu_pod(g) for g in groups)
    for g in groups:
        c = g["template"]["spec"]["containers"][0]
        asked = gpus_asked(c)
        assert float(c["resources"]["requests"].get("nvidia.com/gpu", 0)) == asked, g["groupName"]
        assert float(g["rayStartParams"].get("num-gpus", asked)) == asked, f"{g['groupName']}: Ray told otherwise"
        if asked:  # tainted GPU nodes admit it; it is there when the job counts the GPUs
            assert any(t.get("key") == "nvidia.com/gpu" for t in g["template"]["spec"].get("tolerations", []))
            assert g["minReplicas"] == g["replicas"] == g["maxReplicas"], g["groupName"]


def test_the_gpu_job_gets_every_proposal_actor_it_asks_for_and_the_cpu_job_none():
    cfg = _job("rayjob-gpu.yaml")
    at_start = _at_start("rayjob-gpu.yaml")
    asked = cfg.run.proposal_actors
    assert asked > 0, "the GPU job names its actors: a cluster without its GPUs fails instead of using CPUs"
    assert proposal_actor_count(cfg, at_start) == asked  # no ConfigError: the GPUs are there
    for g in rayjob("rayjob-gpu.yaml")["spec"]["rayClusterSpec"]["workerGroupSpecs"]:
        per_pod = gpus_asked(g["template"]["spec"]["containers"][0])
        if per_pod:  # an actor's GPUs lie on one pod, and a pod's GPUs are used whole
            assert cfg.run.gpus_per_proposal_actor <= per_pod
            assert (per_pod / cfg.run.gpus_per_proposal_actor).is_integer()
    stereo = _job("rayjob.yaml")
    assert proposal_actor_count(stereo, _at_start("rayjob.yaml")) == 0 and _at_start("rayjob.yaml")["GPU"] == 0


def test_the_gpu_clusters_are_the_projections():
    """64 cores and 4 GPUs in the RayJob when it starts; the launcher's GPU nodes reach 4."""
    cores, gpus = CLUSTER_GPUS_PROJECTED
    assert _at_start("rayjob-gpu.yaml") == {"CPU": cores, "GPU": gpus}
    cfg = cluster()
    gpu_types = {k: t for k, t in cfg["available_node_types"].items() if t["resources"].get("GPU")}
    assert sum(t["max_workers"] * t["resources"]["GPU"] for t in gpu_types.values()) == gpus
    assert cfg["max_workers"] >= sum(t["max_workers"] for k, t in cfg["available_node_types"].items()
                                     if k != cfg["head_node_type"])
    readme = (REPO / "README.md").read_text()
    assert f"--cpus {cores:g} --gpus {gpus:g}" in readme, "the README's sizing command projects this cluster"
    assert (INFRA / "rayjob-gpu.yaml").name in (INFRA / "README.md").read_text()


@pytest.mark.parametrize("name", ["rayjob-gpu.yaml"])
def test_the_model_is_mounted_where_the_job_reads_it(name):
    cfg = _job(name)
    path = cfg.proposals.onnx.model_path
    assert path.startswith("/"), path
    pods = [rayjob(name)["spec"]["rayClusterSpec"]["headGroupSpec"]["template"]["spec"]] + \
        [g["template"]["spec"] for g in rayjob(name)["spec"]["rayClusterSpec"]["workerGroupSpecs"]]
    for pod in pods:
        mounts = [m["mountPath"] for c in pod["containers"] for m in c.get("volumeMounts", [])]
        assert any(path.startswith(m.rstrip("/") + "/") for m in mounts), f"{path} not mounted: {mounts}"
