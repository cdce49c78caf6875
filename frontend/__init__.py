"""Frontend: the classical odometry (Open3D RGB-D / ICP registration, KISS-ICP) and the keyframe policy (numpy only).

Dataset readers and the synthetic generator live in :mod:`lrslam.datasets`; loop closure and the keyframe link
(the graph's measurements) in :mod:`lrslam.backend`.
"""
