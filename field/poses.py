"""Differentiable camera-pose parameterisations for tracking and joint mapping (torch).

Two choices, both giving 4x4 ``T_w_c`` (OpenCV camera) matrices with autograd:

- ``"quat"`` (ESLAM): the unit quaternion (w, x, y, z) of ``R_w_c`` and the camera centre ``t_w_c`` are the
  parameters; the quaternion is normalised on use.
- ``"lie"``: a 6-DoF increment ``[rho, v]`` applied on the right, ``T = T0 @ Exp([2 rho, v])`` (rotation
  about the camera centre, translation in the camera frame); zero at the start.

The rotation parameter is scaled so that one Adam step of size ``lr`` turns the camera by about ``2 lr`` radians
in both parameterisations (a unit-quaternion component moves by half the angle), so ESLAM's learning rates mean
the same thing for either.
"""

from __future__ import annotations


import numpy as np
import torch
from torch import nn

from lrslam.field.config import PoseParameterisation
from lrslam.geometry import exp_se3, quat_to_rot, rot_to_quat

__all__ = ["PoseParameterisation", "skew", "so3_exp", "se3_exp", "quat_to_matrix", "PoseParams"]



def skew(w: torch.Tensor) -> torch.Tensor:
    """(B, 3) -> (B, 3, 3) cross-product matrices."""
    z = torch.zeros_like(w[:, 0])
    return torch.stack([z, -w[:, 2], w[:, 1], w[:, 2], z, -w[:, 0], -w[:, 1], w[:, 0], z], dim=-1).view(-1, 3, 3)


def _coefficients(theta2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """sin(t)/t, (1-cos t)/t^2, (t - sin t)/t^3 with Taylor series near 0 (finite gradients at 0)."""
    small = theta2 < 1e-6
    t2 = torch.where(small, torch.ones_like(theta2), theta2)
    t = t2.sqrt()
    a = torch.where(small, 1 - theta2 / 6, torch.sin(t) / t)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(t)) / t2)
    c = torch.where(small, 1.0 / 6 - theta2 / 120, (t - torch.sin(t)) / (t2 * t))
    return a, b, c


def so3_exp(w: torch.Tensor) -> torch.Tensor:
    """Rotation vectors (B, 3) radians -> rotation matrices (B, 3, 3) (Rodrigues)."""
    a, b, _ = _coefficients((w * w).sum(-1))
    W = skew(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand_as(W)
    return eye + a[:, None, None] * W + b[:, None, None] * (W @ W)


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """Tangents (B, 6) ``[omega (rad), v (m)]`` -> poses (B, 4, 4) (same convention as lrslam.geometry.exp_se3)."""
    w, v = xi[:, :3], xi[:, 3:]
    a, b, c = _coefficients((w * w).sum(-1))
    W = skew(w)
    W2 = W @ W
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand_as(W)
    R = eye + a[:, None, None] * W + b[:, None, None] * W2
    V = eye + b[:, None, None] * W + c[:, None, None] * W2
    top = torch.cat([R, (V @ v.unsqueeze(-1))], dim=-1)
    bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=xi.dtype, device=xi.device).expand(len(xi), 1, 4)
    return torch.cat([top, bottom], dim=1)


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Quaternions (B, 4) as (w, x, y, z), any norm > 0 -> rotation matrices (B, 3, 3)."""
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], dim=-1).view(-1, 3, 3)


class PoseParams(nn.Module):
    """A batch of optimisable camera poses.

    Args:
        T0: (B, 4, 4) or (4, 4) float64 initial ``T_w_c``. kind: ``"quat"`` or ``"lie"``. device: torch device.
    Attributes:
        rotation, translation: the parameters (give them their own Adam learning rates).
    """

    def __init__(self, T0: np.ndarray, kind: PoseParameterisation = "quat", device: torch.device | str = "cpu"):
        super().__init__()
        T0 = np.asarray(T0, dtype=np.float64).reshape(-1, 4, 4)
        self.kind = kind
        self.T0 = T0
        self.register_buffer("T0_t", torch.tensor(T0, dtype=torch.float32, device=device))
        if kind == "quat":
            q = rot_to_quat(T0[:, :3, :3])[:, [3, 0, 1, 2]]  # xyzw -> wxyz
            self.rotation = nn.Parameter(torch.tensor(q, dtype=torch.float32, device=device))
            self.translation = nn.Parameter(torch.tensor(T0[:, :3, 3], dtype=torch.float32, device=device))
        elif kind == "lie":
            self.rotation = nn.Parameter(torch.zeros(len(T0), 3, device=device))
            self.translation = nn.Parameter(torch.zeros(len(T0), 3, device=device))
        else:
            raise ValueError(f"unknown pose parameterisation {kind!r} (use 'quat' or 'lie')")

    def __len__(self) -> int:
        return len(self.T0)

    def matrices(self) -> torch.Tensor:
        """Current poses (B, 4, 4) float32, differentiable in the parameters."""
        if self.kind == "lie":
            return self.T0_t @ se3_exp(torch.cat([2.0 * self.rotation, self.translation], dim=-1))
        R = quat_to_matrix(self.rotation)
        top = torch.cat([R, self.translation.unsqueeze(-1)], dim=-1)
        bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], device=R.device).expand(len(R), 1, 4)
        return torch.cat([top, bottom], dim=1)

    def numpy(self) -> np.ndarray:
        """Current poses (B, 4, 4) float64 (composed in float64 from the parameter values)."""
        rot = self.rotation.detach().double().cpu().numpy()
        trans = self.translation.detach().double().cpu().numpy()
        out = np.empty_like(self.T0)
        for i in range(len(out)):
            if self.kind == "lie":
                out[i] = self.T0[i] @ exp_se3(np.concatenate([2.0 * rot[i], trans[i]]))
            else:
                out[i] = np.eye(4)
                out[i, :3, :3] = quat_to_rot(rot[i, [1, 2, 3, 0]])
                out[i, :3, 3] = trans[i]
        return out

    def finite(self) -> bool:
        """False when any parameter is NaN/inf (or a quaternion has collapsed to zero)."""
        ok = bool(torch.isfinite(self.rotation).all() and torch.isfinite(self.translation).all())
        if ok and self.kind == "quat":
            ok = bool((self.rotation.norm(dim=-1) > 1e-6).all())
        return ok
