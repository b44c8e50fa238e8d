"""Job configuration: one dataclass per stage, loaded from ``jobs/*.toml``.

Every tunable lives here with its default (from the paper or the original implementation,
see ``../shared/docs/REFERENCE.md``) and a comment saying where it comes from. The whole
configuration is hashed into ``params_hash`` so that a catalogue records what made it.
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import hashlib
import json
import tomllib
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

from mining.checks import Count, OneOf, Range, coerce, split_hint
from mining.errors import ConfigError
from mining.files import read_text
from mining.geometry.config import GeometryConfig
from mining.localise.config import LocaliseConfig
from mining.proposals.config import ProposalConfig
from mining.score.config import ScoreConfig
from mining.select.config import SelectConfig
from mining.sources import DATASETS
from mining.tubes.config import TubeConfig


@dataclass
class SourceConfig:
    dataset: Annotated[str, OneOf(tuple(DATASETS))] = "synthetic"  # one of mining.sources.DATASETS
    root: str = ""  # dataset root folder; unused by the synthetic source
    sequences: list[str] = field(default_factory=list)  # empty: every sequence the source finds
    options: dict[str, Any] = field(default_factory=dict)  # source-specific keyword arguments

    def open(self):
        """The source adapter this section names (``mining.sources.open_source``): the one opener
        for the CLI, the pipeline's steps, exports, render and the viewer."""
        from mining.sources import open_source

        return open_source(self.dataset, self.root or None, **self.options)


@dataclass
class ExportConfig:
    observed_only: bool = True  # ours: tracking exports list observed frames only; False adds predicted boxes in gaps
    unclassified_as: str = "Misc"  # ours: KITTI type of tubes without class information (e.g. stereo proposals); "Car" scores them class-agnostically


@dataclass
class WindowConfig:
    core: Annotated[int, Range(1, why="a window holds at least one core frame")] = 100  # DESIGN.md: a window's core is 100 frames
    context_before: int = 30  # ours: frames tracked before the core so tube start-up and co-selection see the same data as an unsharded run
    context_after: int = 30  # ours: frames tracked after the core, likewise (tube ends, forward-backward starts)
    stitch_min_shared: Count = 3  # ours: inliers two windows' pieces must share to be one tube


@dataclass
class EmbedConfig:
    """Tube embeddings from an image encoder the user brings, run on each tube's best views
    (mining/discovery/embed.py): ``mine embed``'s options, or with ``model_path`` set a stage at the end
    of ``mine submit``. Not part of the job's identity or params_hash: embeddings never change the tubes."""

    model_path: str = ""  # the image encoder's ONNX file ("" = no embedding stage in mine submit; mine embed --model)
    where: str = "selected"  # ours: the tubes mine submit's stage embeds, a SQL predicate as mine export's
    preset: Annotated[str, OneOf(("clip", "dino", "imagenet"))] = "clip"  # ours: the normalisation (embed.PRESETS): CLIP's mean / std, or ImageNet's (DINO's)
    views: Count = 3  # ours: the observed frames a tube is embedded from (largest mask area × objectness)
    margin: Annotated[float, Range(0.0, 2.0)] = 0.15  # export/crops.CROP_MARGIN: context around the box, a fraction of its width / height
    input_size: Count = 224  # CLIP ViT-B/32 and DINO ViT's input side: used where the model's H or W is symbolic
    output: str = ""  # ours: the output read ("" = the model's first)
    batch: Count = 32  # ours: crops a model run, where the export's batch axis is symbolic
    tubes_per_task: Count = 64  # ours: tubes a Ray task embeds (and a file holds): what a kill can lose
    device: Annotated[str, OneOf(("auto", "cpu", "cuda"))] = "auto"  # ours: auto = CUDA where onnxruntime has it and Ray gave a GPU
    actors: Annotated[int, Range(-1)] = -1  # ours: -1 = one per cluster GPU, or one per CPU without GPUs; 0 = one per CPU, no GPU; N = N actors
    gpus_per_actor: Annotated[float, Range(0.0)] = 1.0  # ours: as run.gpus_per_proposal_actor: one model per GPU
    intra_op_num_threads: Count = 1  # ours: onnxruntime threads within an operator (Ray parallelises over actors)


@dataclass
class RunConfig:
    max_retries: int = 3  # ours: Ray retries of a window's task after a system failure (a dead worker or node)
    # Calibration sanity, checked for every planned sequence before a job starts
    # (mining.sources.base.check_calib); outside these a calibration is refused, not mined.
    calib_fov_deg: tuple[float, float] = (5.0, 170.0)  # ours: plausible horizontal field of view of a rectified camera (fx = 0 or a 10× typo falls outside)
    calib_baseline_m: tuple[float, float] = (0.01, 5.0)  # ours: plausible stereo baseline (a baseline given in millimetres falls outside)
    calib_aspect: tuple[float, float] = (0.5, 2.0)  # ours: plausible fy / fx (rectified pixels are near square)
    # ours: the interface a local Ray of the job's own binds every port to (pipeline/localray.py): 127.0.0.1,
    # or every interface asked for by name, 0.0.0.0 or :: (announced); any other address is refused (Ray would not keep to it)
    bind_host: str = "127.0.0.1"
    # The proposal stage (pipeline/proposal_stage.py): the proposer's model parts on actors of their own;
    # without one the models run inside the CPU workers.
    proposal_actors: Annotated[int, Range(-1)] = -1  # ours: -1 = one actor per cluster GPU when the proposer runs a network (none without GPUs); 0 = never; N = N actors
    gpus_per_proposal_actor: Annotated[float, Range(0.0)] = 1.0  # ours: one model per GPU (0 = actors on CPUs, for a test or a CPU-only pool)
    gpu_wait_s: Annotated[float, Range(0.0)] = 900.0  # ours: how long a job asking for N proposal actors waits for a cluster's autoscaler to bring their GPUs (a cloud GPU node boots in 5-10 min)
    proposal_batch: Count = 8  # ours: frames per model call; torch batches them again by proposals.torch.batch_size
    proposal_queue: Count = 2  # ours: batches a window sends ahead: bounds the object store at workers × queue × batch left images


@dataclass
class JobConfig:
    source: SourceConfig = field(default_factory=SourceConfig)
    geometry: GeometryConfig = field(default_factory=GeometryConfig)
    proposals: ProposalConfig = field(default_factory=ProposalConfig)
    localise: LocaliseConfig = field(default_factory=LocaliseConfig)
    tubes: TubeConfig = field(default_factory=TubeConfig)
    score: ScoreConfig = field(default_factory=ScoreConfig)
    select: SelectConfig = field(default_factory=SelectConfig)
    export: ExportConfig = field(default_factory=ExportConfig)
    window: WindowConfig = field(default_factory=WindowConfig)
    run: RunConfig = field(default_factory=RunConfig)
    embed: EmbedConfig = field(default_factory=EmbedConfig)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @property
    def params_hash(self) -> str:
        """Hash of everything that changes results (the source's location excluded)."""
        d = self.to_dict()
        d["source"] = {k: v for k, v in d["source"].items() if k not in ("root", "sequences")}
        d.pop("run")  # retries change how a result is reached, not the result
        d.pop("embed")  # embeddings are written beside the tubes and never change them
        blob = json.dumps(d, sort_keys=True, default=str).encode()
        return hashlib.sha256(blob).hexdigest()[:16]


# The settings whose value depends on a mode, each a table keyed by that mode's values (no mode twins such as
# a ``*_calibrated`` field beside its plain one): dotted table → the setting that names the mode.
BY_MODE: dict[str, str] = {
    "select.price": "score.model",  # by the unary the scores come from ("auto" resolves to one of the two)
    "select.overlap_weight": "score.model",  # likewise
    "tubes.association_floor": "tubes.association",
    "score.known_margin": "score.class_confidence",
}


def _build(cls: type, data: dict[str, Any], where: str, prefix: str = "") -> Any:
    """Instantiate dataclass ``cls`` from a nested dict, rejecting unknown keys and values
    that break a field's type or rules (``mining.checks``)."""
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: {prefix.rstrip('.') or 'config'}: expected a table, got {type(data).__name__}")
    hints = typing.get_type_hints(cls, include_extras=True)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - names
    if unknown:
        keys = sorted(prefix + k for k in unknown)
        moved = [f"{k} {moved_key(k)}" for k in keys if moved_key(k) is not None]
        hint = f" (moved: {'; '.join(moved)})" if moved else ""
        near = [f"{prefix}{k} → {prefix}{m[0]}" for k in sorted(unknown)
                if (m := difflib.get_close_matches(k, names, n=1))]  # a typo of a real key of this table
        hint += f"; did you mean {', '.join(near)}?" if near else ""
        raise ConfigError(f"{where}: unknown key(s) {keys}{hint}; known: {sorted(names)}")
    kwargs = {}
    for key, value in data.items():
        hint = hints[key]
        if dataclasses.is_dataclass(split_hint(hint)[0]):
            kwargs[key] = _build(split_hint(hint)[0], value, where, f"{prefix}{key}.")
        else:
            try:
                kwargs[key] = coerce(hint, value, prefix + key)
            except ConfigError as e:
                new = RENAMED_VALUES.get(prefix + key, {}).get(value) if isinstance(value, str) else None
                hint = f" ({value!r} is now {new!r})" if new is not None else ""
                raise ConfigError(f"{where}: {e}{hint}") from None
    return cls(**kwargs)


def section_from_dict(cls: type, data: dict[str, Any], where: str) -> Any:
    """One config section (e.g. ``GeometryConfig``) from its table in a recorded job
    (``job.json``'s ``config``); ConfigError naming ``where`` for unknown keys or values
    that break a field's type or rules."""
    return _build(cls, data, where)


# Keys a recorded job (``job.json``'s ``config``) may hold from an older version of the code:
# old dotted key → its new dotted key (a tuple: every place it now fills), or None where the
# setting is gone. A key moved here is refused in a job file or ``--set``
# with a hint naming its new place.
RENAMED_KEYS: dict[str, str | tuple[str, ...] | None] = {
    "tubes.kalman.velocity_noise_factor": "localise.velocity_noise_factor",  # moved at da118f8
    "proposals.filters": "localise.filters",  # the geometric proposal filter, a localisation setting (issue 27)
    # mode twins became tables keyed by their mode (issue 38, BY_MODE)
    "select.epsilon1": "select.price.reference",
    "select.epsilon1_calibrated": "select.price.calibrated",
    "select.epsilon2": "select.overlap_weight.reference",
    "select.epsilon2_calibrated": "select.overlap_weight.calibrated",
    "tubes.min_association": "tubes.association_floor.reference",
    # one floor served both rules relative to the density's peak
    "tubes.min_association_normalised": ("tubes.association_floor.normalised", "tubes.association_floor.innovation"),
    "score.known_log_margin": "score.known_margin.reference",
    "score.known_log_margin_calibrated": "score.known_margin.calibrated",
    # issue 39: only a tube no classifier looked at is unclassified; its call no longer depends on the evidence
    "score.min_class_evidence": None,
}
# Values a recorded job may hold from an older version: dotted key → {old value: its new name}. Refused
# in a job file or ``--set`` with a hint naming the new one.
RENAMED_VALUES: dict[str, dict[str, str]] = {
    "score.unknown_gate": {"unclassified": "call"},  # issue 39: the gate's outcome is the call "clutter"
}


def renamed_to(new: str | tuple[str, ...] | None) -> tuple[str, ...]:
    """The new places of a ``RENAMED_KEYS`` entry (none for a removed key)."""
    return () if new is None else (new,) if isinstance(new, str) else tuple(new)


def moved_key(key: str) -> str | None:
    """What became of a dotted key of an older version ("is now localise.filters", "was removed"),
    or None for a key RENAMED_KEYS does not name. A key inside a moved table moves with it:
    ``proposals.filters.noise_sigmas`` is now ``localise.filters.noise_sigmas``."""
    for old, new in RENAMED_KEYS.items():
        if key == old or key.startswith(old + "."):
            if new is None:
                return "was removed"
            return "is now " + " and ".join(f"{n}{key[len(old):]}" for n in renamed_to(new))
    return None


def _renamed(data: dict[str, Any]) -> dict[str, Any]:
    out = json.loads(json.dumps(data, default=str))
    for key, values in RENAMED_VALUES.items():
        *path, leaf = key.split(".")
        node = out
        for p in path:
            node = node.get(p) if isinstance(node, dict) else None
        if isinstance(node, dict) and isinstance(node.get(leaf), str) and node[leaf] in values:
            node[leaf] = values[node[leaf]]
    for old, new in RENAMED_KEYS.items():
        *path, leaf = old.split(".")
        node = out
        for p in path:
            node = node.get(p) if isinstance(node, dict) else None
        if not isinstance(node, dict) or leaf not in node:
            continue
        value = node.pop(leaf)
        for place in renamed_to(new):
            *npath, nleaf = place.split(".")
            dst = out
            for p in npath:
                dst = dst.setdefault(p, {})
            dst.setdefault(nleaf, copy.deepcopy(value))
    return out


def job_config_from_record(data: dict[str, Any], where: str) -> JobConfig:
    """The typed JobConfig of a recorded job (``job.json``'s ``config``, as ``to_dict`` wrote it),
    with keys of older code versions moved to their new names (``RENAMED_KEYS``); ConfigError
    naming ``where`` and the key for anything else that does not fit today's config."""
    return _build(JobConfig, _renamed(data), where)


def validate(cfg: JobConfig, where: str = "config") -> None:
    """Check a config made or changed in code (``--option``, tests) as the loader checks a
    file: every field's type and rules, and the source options against the source."""
    _check_job(_build(JobConfig, cfg.to_dict(), where), where)
    from mining.sources import check_options

    check_options(cfg.source.dataset, cfg.source.options)


def merge(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in override.items():
        out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def parse_override(text: str) -> dict[str, Any]:
    """``geometry.stereo.num_disparities=128`` → nested dict; the value is parsed as TOML."""
    if "=" not in text:
        raise ConfigError(f"override {text!r}: expected KEY=VALUE")
    key, raw = text.split("=", 1)
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except (tomllib.TOMLDecodeError, RecursionError):  # RecursionError: nested past tomllib's recursion
        value = raw  # bare strings need no quotes on the command line
    out: dict[str, Any] = {}
    node = out
    parts = key.strip().split(".")
    for p in parts[:-1]:
        node = node.setdefault(p, {})
    node[parts[-1]] = value
    return out


def load_config(path: str | Path | None = None, overrides: list[str] | None = None) -> JobConfig:
    """Defaults, then the TOML file, then ``KEY=VALUE`` overrides."""
    data: dict[str, Any] = {}
    if path is not None:
        p = Path(path)
        try:
            data = tomllib.loads(read_text(p, "job config"))
        except FileNotFoundError:
            raise ConfigError(f"file {p}: job config not found") from None
        except tomllib.TOMLDecodeError as e:
            raise ConfigError(f"file {p}: not valid TOML: {e}") from None
        except RecursionError:  # tomllib recurses once per nested array or table
            raise ConfigError(f"file {p}: not valid TOML: nested deeper than the parser can read") from None
        except OSError as e:  # a folder, no permission
            raise ConfigError(f"file {p}: job config cannot be read ({e.strerror or e})") from None
    where = str(path) if path else "config"
    _build(JobConfig, data, where)  # the file's own faults are the file's
    for o in overrides or []:
        data = merge(data, parse_override(o))
        where = f"--set {o.split('=', 1)[0].strip()}"  # an override's fault names its key, not the file
        _build(JobConfig, data, where)
    return _check_job(_build(JobConfig, data, where), where)


def _check_job(cfg: JobConfig, where: str) -> JobConfig:
    """Rules across sections, checked before any work starts: the unary score's weights
    must exist for the job's proposer (``score.model = "calibrated"``)."""
    from mining.score.unary import unary_weights

    try:
        unary_weights(cfg.score, cfg.proposals.proposer)
    except ConfigError as e:
        raise ConfigError(f"{where}: {e}") from None
    # A recorded job may hold a negative margin (the default was −1 before issue 39); a new one may not.
    for mode, margin in dataclasses.asdict(cfg.score.known_margin).items():
        if margin < 0:
            raise ConfigError(f"{where}: score.known_margin.{mode} = {margin:g}: must be ≥ 0, or a tube is called known "
                              "while unknown has more of its posterior than the class named (mining/score/call.py)")
    return cfg
