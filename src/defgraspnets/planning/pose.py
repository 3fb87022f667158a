r"""Local 6-D coordinates of a gripper pose, for gradient-based grasp refinement.

A pose ``T = [R | t]`` (gripper frame in the object frame) is perturbed in the gripper's own frame by
``xi = (v, omega)``: a translation ``v`` [m] along the gripper axes and a rotation ``omega`` [rad] about
the tool centre point (the point midway between the finger pads),

    T(xi) = [R exp([omega]_x) | t + R v],

so ``xi = 0`` is ``T`` itself, ``v_y`` moves along the closing axis, ``v_z`` along the approach, and
rotations turn the gripper about the grasp centre rather than about the object origin. ``exp`` is
Rodrigues' formula with a Taylor expansion near zero (exact gradients at ``omega = 0``).
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["perturb_pose", "rotation_exp"]


def _skew(w: Tensor) -> Tensor:
    z = torch.zeros_like(w[..., 0])
    return torch.stack(
        [
            torch.stack([z, -w[..., 2], w[..., 1]], -1),
            torch.stack([w[..., 2], z, -w[..., 0]], -1),
            torch.stack([-w[..., 1], w[..., 0], z], -1),
        ],
        -2,
    )


def rotation_exp(omega: Tensor) -> Tensor:
    """(..., 3, 3) rotation ``exp([omega]_x) = I + a K + b K^2`` for rotation vectors ``omega`` (..., 3),
    ``a = sin(th)/th``, ``b = (1 - cos th)/th^2``; both from their Taylor series below th = 1e-3."""
    th2 = (omega**2).sum(-1)
    small = th2 < 1e-6
    safe = torch.where(small, torch.ones_like(th2), th2)
    th = torch.sqrt(safe)
    a = torch.where(small, 1 - th2 / 6 + th2**2 / 120, torch.sin(th) / th)
    b = torch.where(small, 0.5 - th2 / 24 + th2**2 / 720, (1 - torch.cos(th)) / safe)
    K = _skew(omega)
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device).expand(K.shape)
    return eye + a[..., None, None] * K + b[..., None, None] * (K @ K)


def perturb_pose(pose: Tensor, xi: Tensor) -> Tensor:
    """(..., 4, 4) ``T(xi)`` of poses (..., 4, 4) and local coordinates xi (..., 6) = (v [m], omega [rad])."""
    R, t = pose[..., :3, :3], pose[..., :3, 3]
    R_new = R @ rotation_exp(xi[..., 3:])
    t_new = t + (R @ xi[..., :3, None]).squeeze(-1)
    top = torch.cat([R_new, t_new[..., None]], dim=-1)
    bottom = pose[..., 3:, :].expand(*top.shape[:-2], 1, 4)
    return torch.cat([top, bottom], dim=-2)
