"""lrslam: LRSLAM low-rank SDF fields for dense RGB-D SLAM.

Sub-packages: ``lrslam.frontend`` (frames, dataset readers, synthetic scenes, odometry),
``lrslam.field`` (the LRSLAM scene model; the only place torch is used), ``lrslam.backend``
(GTSAM pose graph), ``lrslam.pipeline`` (orchestration and evaluation).
Conventions (poses ``T_a_b``, OpenCV camera) live in :mod:`lrslam.geometry` and :mod:`lrslam.camera`.
"""

__version__ = "0.1.0"
