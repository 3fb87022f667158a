"""Normalization of DefGraspNets inputs and targets, stored with the model as buffers.

Feature standardization
    Every input feature channel ``x_c`` is standardized with the mean and standard deviation measured on
    the training split, ``z_c = (x_c - mu_c) / s_c`` (MeshGraphNets-style normalizers, but computed once on
    the training split instead of online). A channel that is constant on the training split (``s_c ~ 0``)
    gets ``s_c = 1`` so that it stays finite at test time.

Target scaling (why not plain MSE in Pa and m)
    Grasp stresses span ~1e2..1e8 Pa (zero force at the first ramp steps, Hertz-like peaks under the finger
    edges, moduli 1e4..1e7 Pa), and displacements scale like ``F / (E L)``, i.e. over three decades across
    the moduli of one object. An MSE in real units would only fit the stiffest/most-loaded samples.

    * Stress: ``y_sigma = log1p(sigma / sigma_ref)`` with ``sigma_ref = 1 kPa`` by default: linear below the
      reference (no blow-up at the many near-zero stresses far from the fingers), logarithmic above, so that
      the loss weighs relative errors evenly from kPa to hundreds of MPa. Inverse:
      ``sigma = sigma_ref * expm1(y)`` clamped to ``>= 0`` (von Mises stress is non-negative).
    * Displacement: ``y_d = d * (E / E_ref) / (1 + E / E_sat)`` with ``E_ref = 1 MPa``: linear elasticity
      gives ``d ~ F/(E L)``, so multiplying by the (known, input) modulus removes the dominant 1/E dependence
      while keeping the vector field linear (signs and directions intact, differentiable). Inverse:
      ``d = y_d * (E_ref / E) * (1 + E / E_sat)``. The saturation modulus ``E_sat`` (default infinite: plain
      ``d E / E_ref``) stops the scaling where the grasped object's rigid motion (rotating into the pads,
      sliding in its zero-gravity squeeze), which does not shrink with E, outweighs the elastic part. On the
      25-object data set (E = 0.3-10 MPa) the mean displacement vector of a 50 mm cube is 2.19 mm at 10 MPa
      for a mean displacement magnitude of 2.28 mm: ``d E / E_ref`` scaled that motion 33x more than a soft
      object's deformation of the same size, and the stiffest samples dominated the loss. ``E_sat = 1 MPa``
      compresses the 33x range of scale factors of E = 0.3-10 MPa to 4x.

    The scaled stress is then standardized with training-split mean and standard deviation, the scaled
    displacement divided by its training-split RMS (one scale for the three components: the normalization
    must not depend on the orientation of the object frame). The model predicts these standardized values
    and :class:`TargetScaling` maps them back to Pa and m.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

__all__ = ["Normalizer", "TargetScaling"]


class Normalizer(nn.Module):
    """Per-channel standardization ``z = (x - mean) / std`` with statistics accumulated from data.

    Usage: call :meth:`accumulate` on (n, D) samples of the training split, then :meth:`finalize`.
    ``mean``/``std`` are buffers, so they are saved in checkpoints and move with ``.to(device)``.

    Args:
        dim: number of channels D.
        name: label for error messages.
        isotropic: one scale for all channels, ``std = sqrt(mean_c mean_n x_c^2)``, and no centring (for the
            components of a vector field, whose scaling must not depend on the orientation of the frame).
    """

    def __init__(self, dim: int, name: str = "features", isotropic: bool = False):
        super().__init__()
        self.dim = int(dim)
        self.name = name
        self.isotropic = bool(isotropic)
        self.register_buffer("mean", torch.zeros(self.dim))
        self.register_buffer("std", torch.ones(self.dim))
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))
        self._sum = torch.zeros(self.dim, dtype=torch.float64)
        self._sumsq = torch.zeros(self.dim, dtype=torch.float64)
        self._n = 0

    def reset(self) -> None:
        """Forget accumulated samples (the current ``mean``/``std`` stay until :meth:`finalize`)."""
        self._sum = torch.zeros(self.dim, dtype=torch.float64)
        self._sumsq = torch.zeros(self.dim, dtype=torch.float64)
        self._n = 0

    @property
    def num_accumulated(self) -> int:
        return self._n

    @property
    def initialized(self) -> bool:
        return bool(self.count > 0)

    @torch.no_grad()
    def accumulate(self, x: Tensor) -> None:
        """Add samples ``x`` (n, D) to the running sums (float64)."""
        if x.ndim != 2 or x.shape[1] != self.dim:
            raise ValueError(f"{self.name}: expected samples of shape (n, {self.dim}), got {tuple(x.shape)}")
        if not torch.isfinite(x).all():
            raise ValueError(f"{self.name}: non-finite values in the statistics samples")
        x = x.detach().to("cpu", torch.float64)
        self._sum += x.sum(0)
        self._sumsq += (x * x).sum(0)
        self._n += x.shape[0]

    @torch.no_grad()
    def finalize(self, min_std: float = 1e-12) -> None:
        """Set ``mean``/``std`` from the accumulated samples (constant channels get std 1)."""
        if self._n == 0:
            raise RuntimeError(f"{self.name}: no samples accumulated before finalize()")
        if self.isotropic:
            mean = torch.zeros(self.dim, dtype=torch.float64)
            std = (self._sumsq.sum() / (self._n * self.dim)).sqrt().expand(self.dim)
        else:
            mean = self._sum / self._n
            std = (self._sumsq / self._n - mean * mean).clamp_min(0.0).sqrt()
        std = torch.where(std > min_std, std, torch.ones_like(std))
        self.mean.copy_(mean.to(self.mean))
        self.std.copy_(std.to(self.std))
        self.count.fill_(float(self._n))

    def forward(self, x: Tensor) -> Tensor:
        return (x - self.mean) / self.std

    def inverse(self, z: Tensor) -> Tensor:
        return z * self.std + self.mean

    def extra_repr(self) -> str:
        return f"dim={self.dim}, name={self.name!r}, isotropic={self.isotropic}, count={int(self.count)}"


class TargetScaling(nn.Module):
    """Physical scaling of the predicted fields (see the module docstring for the equations).

    Args:
        stress_reference: ``sigma_ref`` [Pa] of ``y = log1p(sigma / sigma_ref)``.
        modulus_reference: ``E_ref`` [Pa] of ``y = d (E / E_ref) / (1 + E / E_sat)``.
        modulus_saturation: ``E_sat`` [Pa]; ``None`` (infinite) gives ``y = d E / E_ref``.
        max_stress: clamp of the inverse stress map [Pa] (keeps ``expm1`` finite on extrapolation).
    """

    def __init__(
        self,
        stress_reference: float = 1e3,
        modulus_reference: float = 1e6,
        max_stress: float = 1e10,
        modulus_saturation: float | None = None,
    ):
        super().__init__()
        if stress_reference <= 0 or modulus_reference <= 0:
            raise ValueError("stress_reference and modulus_reference must be positive [Pa]")
        if modulus_saturation is not None and not (
            math.isfinite(modulus_saturation) and modulus_saturation > 0
        ):
            raise ValueError(
                f"modulus_saturation must be a positive modulus [Pa] or None, got {modulus_saturation!r}"
            )
        self.stress_reference = float(stress_reference)
        self.modulus_reference = float(modulus_reference)
        self.modulus_saturation = None if modulus_saturation is None else float(modulus_saturation)
        self.max_log_stress = math.log1p(max_stress / stress_reference)

    def stress_to_target(self, stress: Tensor) -> Tensor:
        """``log1p(sigma / sigma_ref)``; stress (n,) [Pa]."""
        return torch.log1p(stress.clamp_min(0.0) / self.stress_reference)

    def stress_from_target(self, y: Tensor) -> Tensor:
        """``sigma_ref expm1(y)`` [Pa], clamped to ``[0, max_stress]``."""
        return self.stress_reference * torch.expm1(y.clamp(max=self.max_log_stress)).clamp_min(0.0)

    def displacement_factor(self, youngs_modulus: Tensor) -> Tensor:
        """``(E / E_ref) / (1 + E / E_sat)`` (n, 1), ``y = d * factor``; youngs_modulus (n,) [Pa] per node."""
        factor = youngs_modulus / self.modulus_reference
        if self.modulus_saturation is not None:
            factor = factor / (1.0 + youngs_modulus / self.modulus_saturation)
        return factor.unsqueeze(-1)

    def displacement_to_target(self, displacement: Tensor, youngs_modulus: Tensor) -> Tensor:
        """``d (E / E_ref) / (1 + E / E_sat)``; displacement (n, 3) [m], youngs_modulus (n,) [Pa] per node."""
        return displacement * self.displacement_factor(youngs_modulus)

    def displacement_from_target(self, y: Tensor, youngs_modulus: Tensor) -> Tensor:
        """``y (E_ref / E) (1 + E / E_sat)`` [m]."""
        return y / self.displacement_factor(youngs_modulus)

    def extra_repr(self) -> str:
        sat = "inf" if self.modulus_saturation is None else f"{self.modulus_saturation:g}"
        return (
            f"stress_reference={self.stress_reference:g} Pa, "
            f"modulus_reference={self.modulus_reference:g} Pa, modulus_saturation={sat} Pa"
        )
