"""Isotropic elastic materials (SI units).

Two hyperelastic energies, both functions of the signed singular values sigma_i of the deformation
gradient F (J = det F), both invariant to rigid rotations and both reducing exactly to linear elasticity
with the Lame parameters below at small strain:

* ``"corotated"`` (default), the *fixed co-rotated* energy (Stomakhin et al. 2012)

      Psi(F) = mu * sum_i (sigma_i - 1)^2 + lambda / 2 * (J - 1)^2,

  the energy form of co-rotational linear elasticity, the model of the thesis's FleX/Isaac Gym solver.
  It stays finite for inverted elements (no log J). That is also its weakness: its resistance to
  volume loss is bounded, so under a contact pressure of a few E elements collapse and invert
  (measured: a 50 mm box of E = 1e4 Pa in a Franka grasp inverts tets from 6.9 N on, and Newton finds
  no equilibrium past 9.3 N).

* ``"neohookean"``, the compressible Neo-Hookean energy (Bonet and Wood)

      Psi(F) = mu / 2 * (I_1 - 3) - mu * log J + lambda / 2 * (log J)^2,     I_1 = sum_i sigma_i^2,

  whose energy grows without bound as J -> 0: no element can invert (the solver's line search
  rejects inverted trial states, where Psi = +inf). Use it for soft objects under large loads
  (E ~ 1e4-1e5 Pa at 15 N, silicone membranes).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["MATERIAL_MODELS", "Material", "MaterialError"]

MATERIAL_MODELS = ("corotated", "neohookean")  # index = the kernels' model code


class MaterialError(ValueError):
    """Material parameters outside their physical range."""


@dataclass(frozen=True)
class Material:
    """Homogeneous isotropic elastic material.

    Args:
        youngs_modulus: E [Pa], 1e3 <= E <= 1e12 (soft tissue ~1e4, rubber ~1e6, ABS ~2e9).
        poisson_ratio: nu, 0 <= nu < 0.5.
        density: rho [kg/m^3] > 0.
        model: constitutive energy, ``"corotated"`` or ``"neohookean"`` (see the module docstring).
    """

    youngs_modulus: float
    poisson_ratio: float = 0.3
    density: float = 1000.0
    model: str = "corotated"

    def __post_init__(self):
        if self.model not in MATERIAL_MODELS:
            raise MaterialError(f"model must be one of {', '.join(MATERIAL_MODELS)}, got {self.model!r}")
        for name in ("youngs_modulus", "poisson_ratio", "density"):
            value = getattr(self, name)
            if isinstance(value, (str, bytes, bool)) or not np.isscalar(value) or not np.isfinite(value):
                raise MaterialError(f"{name} must be a finite number, got {value!r}")
            object.__setattr__(self, name, float(value))
        if not 1e3 <= self.youngs_modulus <= 1e12:
            raise MaterialError(f"youngs_modulus must be in [1e3, 1e12] Pa, got {self.youngs_modulus:g}")
        if not 0.0 <= self.poisson_ratio < 0.5:
            raise MaterialError(f"poisson_ratio must be in [0, 0.5), got {self.poisson_ratio:g}")
        if self.density <= 0.0:
            raise MaterialError(f"density must be > 0 kg/m^3, got {self.density:g}")

    @property
    def shear_modulus(self) -> float:
        """Lame mu = E / (2 (1 + nu)) [Pa]."""
        return self.youngs_modulus / (2.0 * (1.0 + self.poisson_ratio))

    @property
    def lame_lambda(self) -> float:
        """Lame lambda = E nu / ((1 + nu)(1 - 2 nu)) [Pa]."""
        e, nu = self.youngs_modulus, self.poisson_ratio
        return e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))

    @property
    def plane_strain_modulus(self) -> float:
        """E* = E / (1 - nu^2) [Pa] (Hertz contact of a body against a rigid surface)."""
        return self.youngs_modulus / (1.0 - self.poisson_ratio**2)
