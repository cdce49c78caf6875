"""Backend: everything the keyframe pose graph needs, in one place.

- :mod:`~lrslam.backend.graph`: the GTSAM pose graph (factors, robust noise, solves);
- :mod:`~lrslam.backend.keyframe_link`: the frontend's own keyframe-to-keyframe measurement (odometry factor);
- :mod:`~lrslam.backend.loop_closure`: loop candidates, their ICP verification (loop factors);
- :mod:`~lrslam.backend.policy`: :class:`GraphBackend`, the policy: which factors enter, when to solve, which
  corrected poses to write back and which keyframes to re-map.
"""
