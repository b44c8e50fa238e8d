"""infra/: the cluster launcher YAML, the KubeRay RayJob and the Containerfile.

Every ``mine ...`` command line written in them is parsed by the real CLI parser, and
what they install and run is checked against pyproject.toml, jobs/ and Ray's own
cluster-config validator.
"""

from __future__ import annotations

import json
import re
import shlex
import tomllib
from pathlib import PurePosixPath

import pytest
import yaml

from conftest import REPO
from mining.cli import build_parser

INFRA = REPO / "infra"
PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())
EXTRAS = set(PYPROJECT["project"]["optional-dependencies"])
GiB = 1024**3

# RayJobSpec's fields (KubeRay ray-operator/apis/ray/v1/rayjob_types.go): a misspelt key
# is silently dropped by a lenient apiserver, so name them here.
RAYJOB_SPEC_FIELDS = {
    "activeDeadlineSeconds", "backoffLimit", "rayClusterSpec", "submitterPodTemplate",
    "metadata", "clusterSelector", "submitterConfig", "managedBy", "deletionStrategy",
    "entrypoint", "runtimeEnvYAML", "jobId", "submissionMode", "entrypointResources",
    "entrypointNumCpus", "entrypointNumGpus", "ttlSecondsAfterFinished",
    "shutdownAfterJobFinishes", "suspend", "schedule",
}

_MINE_AT = re.compile(r"(?:^|&&|;|\|)\s*mine\s+\S")


def mine_commands(text: str) -> list[list[str]]:
    """Every ``mine ...`` command line in shell text, YAML comments included, as argv."""
    text = re.sub(r"\\\n", " ", text)  # shell line continuations
    found = []
    for line in text.splitlines():
        line = line.strip().lstrip("#").strip().removeprefix("$ ").strip()
        if not _MINE_AT.search(line):
            continue
        lex = shlex.shlex(line, posix=True, punctuation_chars=True)
        lex.whitespace_split = True
        lex.commenters = ""
        segment: list[str] = []
        for tok in [*lex, ";"]:
            if tok and set(tok) <= set(";&|()<>"):
                if segment and segment[0] == "mine":
                    found.append(segment)
                segment = []
            else:
                segment.append(tok)
                if " " in tok and _MINE_AT.search(tok):  # a quoted script, e.g. `ray exec ... "cd x && mine ..."`
                    found += mine_commands(tok)
    return found


def parse(argv: list[str]):
    """The real parser; argparse's SystemExit on a bad line fails the test."""
    assert argv[0] == "mine", argv
    try:
        return build_parser().parse_args(argv[1:])
    except SystemExit as e:
        # only `mine --help` may exit, and only with success
        assert e.code == 0 and "--help" in argv, f"`{shlex.join(argv)}` does not parse (exit {e.code})"
        return None


def containerfile() -> str:
    return (INFRA / "Containerfile").read_text()


def build_args(text: str) -> dict[str, str]:
    """The Containerfile's ``ARG NAME=default`` values."""
    return dict(re.findall(r"^ARG\s+(\w+)=(\S+)", text, flags=re.M))


def expand_args(text: str, args: dict[str, str]) -> str:
    """``${NAME}`` and ``$NAME`` replaced by the build arguments' values."""
    return re.sub(r"\$\{?(\w+)\}?", lambda m: args.get(m[1], m[0]), text)


def container_workdir() -> str:
    workdirs = re.findall(r"^WORKDIR\s+(\S+)", containerfile(), flags=re.M)
    assert workdirs, "Containerfile sets no WORKDIR"
    return workdirs[-1]


def cluster() -> dict:
    return yaml.safe_load((INFRA / "ray-cluster.yaml").read_text())


RAYJOBS = ("rayjob.yaml", "rayjob-gpu.yaml")  # stereo only; a learned proposer with a GPU worker group


def rayjob(name: str = "rayjob.yaml") -> dict:
    return yaml.safe_load((INFRA / name).read_text())


def repo_relative(path: str, roots: list[str]) -> PurePosixPath:
    """A path as written in infra/ → relative to the repository root (a known checkout
    location in the image or on the cluster nodes, or already relative)."""
    p = PurePosixPath(path)
    if not (p.is_absolute() or path.startswith("~")):
        return p
    for root in roots:
        if p.is_relative_to(root):
            return p.relative_to(root)
    raise AssertionError(f"{path} is not inside the repository checkout ({', '.join(roots)})")


def check_job_paths(argv: list[str], roots: list[str]) -> None:
    args = parse(argv)
    config = getattr(args, "config", None)
    if config:
        rel = repo_relative(config, roots)
        assert rel.parts[0] == "jobs", f"{config}: job configs live in jobs/"
        assert (REPO / rel).is_file(), f"{config}: no such job config in the repository"


def min_python() -> str:
    m = re.fullmatch(r">=\s*(\d+)\.(\d+)", PYPROJECT["project"]["requires-python"].strip())
    assert m, "requires-python is not of the form >=X.Y"
    return f"{m[1]}.{m[2]}"


def pinned(name: str) -> str:
    for dep in PYPROJECT["project"]["dependencies"]:
        m = re.fullmatch(rf"{name}(?:\[[^]]*\])?==(\S+)", dep)
        if m:
            return m[1]
    raise AssertionError(f"{name} is not pinned in pyproject.toml")


def installed_extras(command: str) -> set[str]:
    """The extras of an editable or plain `pip install '.[a,b]'` of this repository."""
    m = re.search(r"pip install\b[^'\"]*['\"]?\.\[([\w,\s-]+)\]", command)
    assert m, f"no `pip install '.[extras]'` of the repository in: {command}"
    return {e.strip() for e in m[1].split(",")}


# ---------------------------------------------------------------- mine command lines

def test_extractor_finds_commands_and_rejects_a_bad_one():
    text = ("# mine status --out s3://b/c\nrun: cd ~/x && mine submit --dataset synthetic \\\n  --no-progress\n"
            "# the mine command line\n"
            "#   ray exec c.yaml \"cd ~/x && mine query 'SELECT 1' --format csv\"\n")
    cmds = mine_commands(text)
    assert cmds == [["mine", "status", "--out", "s3://b/c"], ["mine", "submit", "--dataset", "synthetic", "--no-progress"],
                    ["mine", "query", "SELECT 1", "--format", "csv"]]
    with pytest.raises(AssertionError):
        parse(["mine", "submit", "--no-such-option"])


@pytest.mark.parametrize("name", RAYJOBS)
def test_rayjob_entrypoint_is_a_mine_submit_the_cli_accepts(name):
    entrypoint = rayjob(name)["spec"]["entrypoint"]
    cmds = mine_commands(entrypoint)
    assert [c[1] for c in cmds] == ["submit"], entrypoint
    args = parse(cmds[0])
    assert args.dataset and args.root and args.config
    # The job runs inside the cluster: no Ray Jobs re-submission, no local-only options.
    assert args.address is None, "the entrypoint already runs on the cluster"
    assert args.workers is None, "--workers is for a local Ray only"
    assert args.no_progress, "a progress bar in pod logs is noise"
    # the cluster is deleted when the job ends: the catalogue must outlive the pods
    assert "://" in args.out, f"--out {args.out} would vanish with the cluster"
    check_job_paths(cmds[0], [container_workdir()])


def test_cluster_yaml_commands_parse_and_name_real_job_configs():
    text = (INFRA / "ray-cluster.yaml").read_text()
    cmds = mine_commands(text)
    assert "submit" in [c[1] for c in cmds]
    roots = list(cluster()["file_mounts"])  # the checkout's place on the nodes
    for argv in cmds:
        check_job_paths(argv, roots)
    submits = [parse(c) for c in cmds if c[1] == "submit"]
    assert any(a.address and a.address.startswith(("http://", "ray://")) for a in submits), \
        "one submit goes to the cluster through --address"


def test_readme_commands_parse():
    cmds = mine_commands((INFRA / "README.md").read_text())
    assert {"submit", "status", "query"} <= {c[1] for c in cmds}
    for argv in cmds:
        check_job_paths(argv, [container_workdir(), *cluster()["file_mounts"]])


def test_containerfile_cmd_is_mine_help():
    m = re.search(r"^CMD\s+(\[.*\])\s*$", containerfile(), flags=re.M)
    assert m, "Containerfile has no exec-form CMD"
    argv = json.loads(m[1])
    assert argv[:1] == ["mine"]
    parse(argv)


# ---------------------------------------------------------------- Containerfile

def test_containerfile_python_matches_requires_python():
    bases = re.findall(r"^FROM\s+(\S+)", containerfile(), flags=re.M)
    assert len(bases) == 1
    m = re.fullmatch(r"(?:docker\.io/(?:library/)?)?python:(\d+\.\d+)[.\w-]*", bases[0])
    assert m, f"base image {bases[0]} is not an official python image"
    assert m[1] == min_python()


def test_containerfile_installs_the_package_with_existing_extras():
    text = containerfile()
    text = re.sub(r"\\\n", " ", text)  # one instruction per line
    raw_runs = " ; ".join(re.findall(r"^RUN\s+(.*)$", text, flags=re.M))
    runs = expand_args(raw_runs, build_args(text))
    extras = installed_extras(runs)
    assert extras <= EXTRAS, f"extras {extras - EXTRAS} are not in pyproject.toml"
    assert {"cluster", "onnx"} <= extras  # the default build: the CPU image
    # the GPU image's build line (EXTRAS=…) names extras that exist, gpu in place of onnx
    gpu_builds = re.findall(r"--build-arg\s+EXTRAS=(\S+)", text)
    assert gpu_builds, "the Containerfile says how its GPU image is built"
    for b in gpu_builds:
        gpu = installed_extras(expand_args(raw_runs, {"EXTRAS": b}))
        assert {"cluster", "gpu"} <= gpu <= EXTRAS and "onnx" not in gpu, b
    assert "--no-cache-dir" in runs
    # the package reads schemas/ and jobs/ from the repository root: editable install
    # from the WORKDIR, with both folders copied there
    assert re.search(r"pip install\b.*\s-e\s", runs), "install editable so schemas/ and jobs/ stay beside mining/"
    copied = set()
    for line in re.findall(r"^COPY\s+(.*)$", text, flags=re.M):
        sources = [w for w in line.split() if not w.startswith("--")][:-1]  # the last is the destination
        copied |= {PurePosixPath(s).parts[0] if s not in (".", "./") else "." for s in sources}
    assert {"mining", "schemas", "jobs", "pyproject.toml"} <= copied or "." in copied, copied
    readme = PYPROJECT["project"].get("readme")
    assert readme is None or readme in copied or "." in copied, "pyproject's readme must be in the image"
    assert re.search(r"^ENV\b.*RAY_USAGE_STATS_ENABLED=0", text, flags=re.M | re.S)
    # KubeRay's exec probes run wget in the Ray container; slim images lack it
    assert re.search(r"apt-get install\b.*\bwget\b", runs)


# ---------------------------------------------------------------- ray-cluster.yaml

def test_cluster_yaml_passes_rays_own_validator():
    from ray.autoscaler._private.util import prepare_config, validate_config

    validate_config(prepare_config(cluster()))


def test_cluster_yaml_structure_and_setup():
    cfg = cluster()
    assert cfg["cluster_name"]
    assert cfg["provider"]["type"]
    types = cfg["available_node_types"]
    assert cfg["head_node_type"] in types
    workers = {k: v for k, v in types.items() if k != cfg["head_node_type"]}
    assert workers and all(v["max_workers"] > 0 for v in workers.values())
    remote, local = next(iter(cfg["file_mounts"].items()))
    assert local == "."
    # every node installs the package from where file_mounts puts the repository: the head and
    # the CPU workers with onnxruntime's CPU build, a GPU node type with its CUDA build instead
    node_setups = {cfg["head_node_type"]: cfg["setup_commands"] + cfg["head_setup_commands"]}
    for name, t in workers.items():
        node_setups[name] = cfg["setup_commands"] + t.get("worker_setup_commands", cfg["worker_setup_commands"])
    for name, commands in node_setups.items():
        setup = " ; ".join(commands)
        extras = installed_extras(setup)
        wanted = "gpu" if types[name].get("resources", {}).get("GPU") else "onnx"
        assert {"cluster", wanted} <= extras <= EXTRAS, (name, extras)
        assert not {"onnx", "gpu"} <= extras, f"{name}: two builds of onnxruntime"
        assert f"cd {remote}" in setup, name


def test_cluster_image_matches_the_pins():
    image = cluster()["docker"]["image"]
    m = re.fullmatch(r"rayproject/ray:(\d+\.\d+\.\d+)-py(\d)(\d+)-cpu", image)
    assert m, image
    assert m[1] == pinned("ray")
    assert f"{m[2]}.{m[3]}" == min_python()
    for name, t in cluster()["available_node_types"].items():
        own = t.get("docker", {}).get("worker_image")
        if t.get("resources", {}).get("GPU"):  # Ray's CUDA image, same Ray and Python
            assert own == image.removesuffix("-cpu") + "-gpu", name
        else:
            assert own is None, f"{name}: a CPU node runs the cluster's image"


def test_cluster_workers_have_2gb_per_cpu():
    cfg = cluster()
    for name, t in cfg["available_node_types"].items():
        if name == cfg["head_node_type"]:
            assert t["resources"]["CPU"] == 0, "the head runs the driver, not windows"
            continue
        res = t["resources"]
        assert res["CPU"] >= 1
        assert res["memory"] / res["CPU"] >= 2e9, f"{name}: under 2 GB per window task"


# ---------------------------------------------------------------- rayjob.yaml

def _pods(job: dict) -> list[dict]:
    spec = job["spec"]["rayClusterSpec"]
    return [spec["headGroupSpec"]["template"]["spec"]] + [g["template"]["spec"] for g in spec["workerGroupSpecs"]]


@pytest.mark.parametrize("name", RAYJOBS)
def test_rayjob_structure(name):
    job = rayjob(name)
    assert job["apiVersion"] == "ray.io/v1"
    assert job["kind"] == "RayJob"
    spec = job["spec"]
    assert set(spec) <= RAYJOB_SPEC_FIELDS, set(spec) - RAYJOB_SPEC_FIELDS
    assert spec["shutdownAfterJobFinishes"] is True
    rc = spec["rayClusterSpec"]
    assert rc["rayVersion"] == pinned("ray")
    groups = [rc["headGroupSpec"], *rc["workerGroupSpecs"]]
    for g in groups:
        # KubeRay turns rayStartParams into `ray start` flags: values must be strings
        assert all(isinstance(v, str) for v in g["rayStartParams"].values()), g["rayStartParams"]
    assert rc["headGroupSpec"]["rayStartParams"].get("num-cpus") == "0"
    for g in rc["workerGroupSpecs"]:
        assert g["groupName"]
        assert g["minReplicas"] <= g["replicas"] <= g["maxReplicas"]


def gpus_asked(container: dict) -> float:
    """The GPUs a container asks Kubernetes for (its limit: Kubernetes takes extended resources there)."""
    return float(container["resources"].get("limits", {}).get("nvidia.com/gpu", 0))


def gpu_pod(group: dict) -> bool:
    return any(gpus_asked(c) for c in group["template"]["spec"]["containers"])


def _gib(q: str) -> float:
    m = re.fullmatch(r"(\d+(?:\.\d+)?)(Gi|Mi|G|M)?", str(q))
    assert m, q
    scale = {"Gi": GiB, "Mi": 1024**2, "G": 1e9, "M": 1e6, None: 1}[m[2]]
    return float(m[1]) * scale


@pytest.mark.parametrize("name", RAYJOBS)
def test_rayjob_pods_use_the_image_and_size_workers_for_2gb_per_cpu(name):
    job = rayjob(name)
    images = set()
    for pod in _pods(job):
        for c in pod["containers"]:
            images |= set() if gpus_asked(c) else {c["image"]}
            r = c["resources"]
            assert r["requests"] and r["limits"], c["name"]
            assert _gib(r["requests"]["memory"]) == _gib(r["limits"]["memory"]), "memory request = limit (no OOM surprises)"
    submitter = job["spec"].get("submitterPodTemplate")
    if submitter:
        images |= {c["image"] for c in submitter["spec"]["containers"]}
    assert len(images) == 1, f"one image (infra/Containerfile) for all pods without a GPU: {images}"
    for g in job["spec"]["rayClusterSpec"]["workerGroupSpecs"]:
        c = g["template"]["spec"]["containers"][0]
        # the GPU pods run the same Containerfile built with EXTRAS=cluster,gpu, tagged -gpu
        assert c["image"] == (f"{next(iter(images))}-gpu" if gpu_pod(g) else next(iter(images))), g["groupName"]
        cpus = float(c["resources"]["limits"]["cpu"])
        store = float(g["rayStartParams"].get("object-store-memory", 0.3 * _gib(c["resources"]["limits"]["memory"])))
        assert (_gib(c["resources"]["limits"]["memory"]) - store) / cpus >= 2e9


@pytest.mark.parametrize("name", RAYJOBS)
def test_rayjob_root_is_mounted_on_head_and_workers(name):
    job = rayjob(name)
    args = parse(mine_commands(job["spec"]["entrypoint"])[0])
    for pod in _pods(job):
        mounts = [m["mountPath"] for c in pod["containers"] for m in c.get("volumeMounts", [])]
        assert any(PurePosixPath(args.root).is_relative_to(m) for m in mounts), \
            f"--root {args.root} is not mounted in every pod ({mounts})"


def test_version_is_one_number_and_mine_prints_it():
    import subprocess
    import sys
    import tomllib

    import mining
    from mining.catalog.schema import SCHEMA_VERSION

    root = REPO
    assert tomllib.loads((root / "pyproject.toml").read_text())["project"]["version"] == mining.__version__
    r = subprocess.run([sys.executable, "-m", "mining.cli", "--version"], capture_output=True, text=True, cwd=root)
    assert r.returncode == 0 and r.stdout.strip() == f"mine (tube-miner) {mining.__version__}, catalogue schema v{SCHEMA_VERSION}"
