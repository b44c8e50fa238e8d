"""Test and benchmark helpers, not used by the pipeline.

* ``fixtures`` — writers that build RobotCar-layout traversals and ROS 2 MCAP logs from
  real frames, so the ``oxford`` and ``mcap`` adapters are tested on real image content.
* ``sharding`` — do two catalogues hold the same tubes? (sharding invariance).

Only ``tests/`` and ``mining/bench/`` import it; no pipeline module may.
"""
