"""Frontend: frames, dataset readers, synthetic sequences, odometry, keyframes and loop closure (numpy only)."""
