"""YAML presets per dataset and per representation (installed as lrslam.configs)."""
