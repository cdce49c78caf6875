"""lrslam: LRSLAM low-rank SDF fields for dense RGB-D SLAM.

Sub-packages (see ``docs/ARCHITECTURE.md``): ``lrslam.datasets`` (readers, the synthetic generator),
``lrslam.frontend`` (odometry, keyframe policy), ``lrslam.field`` (the LRSLAM scene model; the only place torch
computes: elsewhere it only sets threads, seeds RNGs, detects CUDA and saves checkpoints), ``lrslam.backend``
(pose graph, loop closure, graph policy), ``lrslam.pipeline`` (the SLAM loop and its run folder),
``lrslam.evaluation`` (ATE, mesh metrics: the only readers of ground truth), ``lrslam.tools`` (batches, reports),
``lrslam.cli`` (the command line).
Conventions (poses ``T_a_b``, OpenCV camera) live in :mod:`lrslam.geometry` and :mod:`lrslam.camera`.
"""

__version__ = "0.1.0"

__all__ = ["Slam", "FrameResult", "__version__"]


def __getattr__(name: str):
    """``lrslam.Slam`` / ``lrslam.FrameResult``: the streaming API (:mod:`lrslam.pipeline.slam`), imported on first
    use so ``import lrslam`` stays light."""
    if name in ("Slam", "FrameResult"):
        from lrslam.pipeline import slam

        return getattr(slam, name)
    raise AttributeError(f"module 'lrslam' has no attribute {name!r}")
