"""Tube Miner: offline mining of generic video object tubes (4D-GVT) from stereo video."""

__version__ = "0.1.0"
