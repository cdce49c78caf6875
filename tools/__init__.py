"""Experiment tooling on top of the SLAM pipeline: batches of runs (:mod:`~lrslam.tools.batch`, Ray or in-process)
and the comparison report of a folder of runs (:mod:`~lrslam.tools.report`)."""
