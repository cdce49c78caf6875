"""Backend: GTSAM pose graph over keyframes."""
