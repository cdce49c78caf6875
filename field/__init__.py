"""The LRSLAM scene model (CP / Six-axis / tri-plane encodings, SDF rendering, tracking, mapping).
Torch lives only here.

Components, one concept per module:
  grid (bound growth, grid sizes) -> interp (line / plane interpolation; cpu_kernels = fused numba loops,
  cpu_ops = their torch autograd wrappers, the CPU default) -> enc_cp, enc_sixaxis, enc_triplane
  (one level each) -> encodings (coarse + fine, config, factory) -> decoders -> model (SceneModel + presets);
  poses (differentiable pose parameterisations), rays (pixels -> rays), sampling (depths along rays),
  render (Eq. volume_render), losses (ESLAM losses); inputs (numpy -> tensors), keyframes (database, window
  selection), tracker, mapper, mesh; slam (the numpy facade :class:`FieldSLAM` the pipeline uses).

Import the facade from :mod:`lrslam.field.slam` (importing this package does not import torch).
"""
