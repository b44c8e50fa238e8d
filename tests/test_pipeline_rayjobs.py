"""The command line ``mine submit --address http://…`` hands to a cluster (no cluster needed:
the Ray Jobs round trip itself is tests/test_submit_ray_jobs.py, marked slow)."""

from __future__ import annotations

import os

from mining.cli import build_parser
from mining.pipeline.rayjobs import _forwarded_argv


def test_forwarded_command_line_drops_the_address_and_makes_paths_absolute(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    argv = ["submit", "--config", "jobs/kitti.toml", "--address", "http://head:8265", "--root=data/kitti",
            "--set", "window.core=50", "--out", "s3://bucket/cat"]
    fwd = _forwarded_argv(argv, "out/catalog")
    assert fwd == ["submit", "--config", os.path.join(str(tmp_path), "jobs/kitti.toml"),
                   "--root", os.path.join(str(tmp_path), "data/kitti"), "--set", "window.core=50",
                   "--out", "s3://bucket/cat"]  # a URI passes as it is
    args = build_parser().parse_args(fwd)  # the cluster's `mine` accepts it
    assert args.address is None and args.out == "s3://bucket/cat"


def test_forwarded_command_line_names_the_default_out(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    fwd = _forwarded_argv(["submit", "--address=http://head:8265", "--dataset", "synthetic"], "out/catalog")
    assert fwd == ["submit", "--dataset", "synthetic", "--out", os.path.join(str(tmp_path), "out/catalog")]
