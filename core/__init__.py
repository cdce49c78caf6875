"""lrslam: LRSLAM low-rank SDF fields for dense RGB-D SLAM.

Sub-packages (see ``docs/ARCHITECTURE.md``): ``lrslam.datasets`` (readers, the synthetic generator),
``lrslam.frontend`` (odometry, keyframe policy), ``lrslam.field`` (the LRSLAM scene model; the only place torch
is used), ``lrslam.backend`` (pose graph, loop closure, graph policy), ``lrslam.pipeline`` (the SLAM loop and its
run folder), ``lrslam.evaluation`` (ATE, mesh metrics: the only readers of ground truth), ``lrslam.tools``
(batches, reports), ``lrslam.cli`` (the command line).
Conventions (poses ``T_a_b``, OpenCV camera) live in :mod:`lrslam.geometry` and :mod:`lrslam.camera`.
"""

__version__ = "0.1.0"
