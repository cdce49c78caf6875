"""The LRSLAM scene model (CP / Six-axis / tri-plane encodings, SDF rendering, tracking, mapping). Torch lives only here."""
