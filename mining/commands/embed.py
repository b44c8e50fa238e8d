"""``mine embed``: tube embeddings from an image encoder you bring (``discovery/embed.py``: the
contract; ``discovery/embed_run.py``: the run), into the ``tube_embeddings`` table.

    mine embed --out OUT --model clip-vit-b32-visual.onnx --preset clip
    mine embed --out OUT --model dinov2-small.onnx --preset dino --where "call = 'unknown'"
"""

from __future__ import annotations

import argparse
import os
import sys

from mining.checks import count, input_file, path_text, real

# Copies of EmbedConfig's choices (mining/config.py loads more than --help needs); tests/test_embed.py checks them.
PRESETS = ("clip", "dino", "imagenet")
DEVICES = ("auto", "cpu", "cuda")


def add_arguments(p: argparse.ArgumentParser) -> None:
    # Every setting but --out defaults to the job's [embed] section (job.json), then to EmbedConfig's defaults.
    p.add_argument("--out", type=path_text, default="out/catalog", help="catalogue folder")
    p.add_argument("--model", type=input_file, default=None,
                   help="the image encoder, ONNX: (B, 3, H, W) float32 in, (B, D) or (B, T, D) out (docs/USAGE.md); "
                        "default: the job's embed.model_path")
    p.add_argument("--where", default=None, help="SQL predicate over the tubes (as mine export's; default: selected)")
    p.add_argument("--preset", choices=list(PRESETS), default=None,
                   help="the input normalisation: clip (CLIP's mean / std, the default), dino or imagenet (ImageNet's)")
    p.add_argument("--views", type=count(1, 100), default=None, help="observed frames a tube is embedded from (default 3)")
    p.add_argument("--margin", type=real(0.0, 2.0), default=None,
                   help="context around the box, a fraction of its width / height (default 0.15, as the crops export)")
    p.add_argument("--input-size", type=count(8, 4096), default=None,
                   help="the input side where the model's H or W is symbolic (default 224)")
    p.add_argument("--output", default=None, help="the model output to read (default: its first)")
    p.add_argument("--device", choices=list(DEVICES), default=None,
                   help="auto (the default): onnxruntime's CUDA provider on actors Ray gave a GPU, else the CPU")
    p.add_argument("--actors", type=count(-1, 100_000), default=None,
                   help="model actors (default -1: one per GPU Ray lists, else one per CPU; 0: one per CPU, no GPU)")
    p.add_argument("--workers", type=count(1, 100_000), default=None,
                   help="CPUs of the local Ray (default: every CPU); not with --address")
    p.add_argument("--address", default=None, help="a running Ray cluster to run on (default: a local Ray)")
    p.add_argument("--local", action="store_true", help="no Ray: embed in this process (one CPU model)")
    p.add_argument("--lock-wait", type=real(0.0, 86400.0), default=0.0, metavar="SECONDS",
                   help="wait this long for another writer's lock on --out (default 0: refuse at once)")


FLAGS = ("model_path", "where", "preset", "views", "margin", "input_size", "output", "device", "actors")  # → EmbedConfig


def run(args: argparse.Namespace) -> int:
    import dataclasses

    from mining.config import EmbedConfig
    from mining.discovery.embed_run import embed_catalogue, print_summary
    from mining.errors import ConfigError, NothingMatched
    from mining.export.selection import read_job

    job = read_job(args.out)  # the catalogue first: a wrong --out is said before the model is looked at
    given = {"model_path": args.model, **{k: getattr(args, k) for k in FLAGS[1:]}}
    cfg = dataclasses.replace(job.embed if job is not None else EmbedConfig(),
                              **{k: (str(v) if k == "model_path" else v) for k, v in given.items() if v is not None})
    if not cfg.model_path:
        raise ConfigError("give --model FILE.onnx (the image encoder; the job's embed.model_path is not set)")
    address = args.address or os.environ.get("RAY_ADDRESS")
    started = []

    def on_ray() -> None:
        from mining.pipeline.localray import init_local_ray, prepare_local_ray

        if not address and "ray" not in sys.modules:
            prepare_local_ray()  # before `import ray`: a local Ray keeps to loopback
        import ray

        if ray.is_initialized():
            return
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            init_local_ray(args.workers)
        started.append(True)

    try:
        summary = embed_catalogue(args.out, cfg.model_path, cfg.where, cfg, use_ray=not args.local,
                                  lock_wait=args.lock_wait, on_ray=on_ray)
    finally:
        if started:  # only the Ray this command started
            import ray

            ray.shutdown()
    if not summary.matched:
        raise NothingMatched(f"no tube matches --where {cfg.where!r}; nothing embedded")
    return print_summary(summary)
