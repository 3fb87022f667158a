r"""Grasp objectives Q (thesis §7.5): differentiable scalars of the predicted stress and deformation fields.

Each grasp g of an object with N vertices has a von Mises stress field ``sigma_g`` (N,) [Pa] and a
displacement field ``d_g`` (N, 3) [m], deformation ``|d_g|``. The objective is a weighted sum of terms

    Q_g = sum_k w_k q_k(g),         q_k in {mean_stress, max_stress, mean_deformation, max_deformation}

where the weights carry units (1/Pa for stress terms, 1/m for deformation terms; a single term with weight
1 is Q in SI units). The maxima are smooth so that ``dQ/dT`` exists everywhere:

    p-norm     smax(x) = (mean_i x_i^p)^(1/p),     max(x) N^(-1/p) <= smax(x) <= max(x)       (x >= 0)
    log-sum-exp  smax(x) = tau log(mean_i exp(x_i / tau)),   max(x) - tau log N <= smax(x) <= max(x)

The p-norm is scale-equivariant (the same p serves every Young's modulus, whose stresses span decades);
log-sum-exp needs its temperature ``tau`` in the quantity's units (Pa or m). ``sense`` says whether the
planner minimizes or maximizes Q; :meth:`GraspObjective.loss` is the quantity it *minimizes*.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

__all__ = ["OBJECTIVE_TERMS", "PRESETS", "GraspObjective", "smooth_max"]

OBJECTIVE_TERMS = ("mean_stress", "max_stress", "mean_deformation", "max_deformation")
_UNITS = {"mean_stress": "Pa", "max_stress": "Pa", "mean_deformation": "m", "max_deformation": "m"}


def smooth_max(x: Tensor, method: str = "pnorm", p: float = 20.0, temperature: float | None = None) -> Tensor:
    """Smooth maximum over the last axis of a non-negative field ``x`` (see the module docstring).

    Args:
        method: ``"pnorm"`` (uses ``p`` >= 1), ``"logsumexp"`` (uses ``temperature`` > 0, units of x) or
            ``"max"`` (the exact maximum; subgradients only).
    """
    if method == "pnorm":
        # (mean x^p)^(1/p) = m (mean (x/m)^p)^(1/p) with m = max x (detached) to avoid overflow of x^p
        m = x.detach().amax(dim=-1, keepdim=True).clamp_min(torch.finfo(x.dtype).tiny)
        return m.squeeze(-1) * ((x / m) ** p).mean(dim=-1) ** (1.0 / p)
    if method == "logsumexp":
        n = torch.tensor(float(x.shape[-1]), dtype=x.dtype, device=x.device)
        return temperature * (torch.logsumexp(x / temperature, dim=-1) - torch.log(n))
    if method == "max":
        return x.amax(dim=-1)
    raise ValueError(f"smooth max method must be 'pnorm', 'logsumexp' or 'max', got {method!r}")


@dataclass(frozen=True)
class GraspObjective:
    """A grasp quality Q to minimize or maximize.

    Args:
        terms: ``{term: weight}`` with terms from :data:`OBJECTIVE_TERMS`; weights in 1/Pa (stress) and
            1/m (deformation), e.g. ``{"mean_deformation": 1000.0, "max_stress": 1e-3}`` adds millimetres
            and kilopascals.
        sense: ``"minimize"`` or ``"maximize"``.
        smooth_max: ``"pnorm"``, ``"logsumexp"`` or ``"max"`` for the max terms.
        p: exponent of the p-norm.
        stress_temperature, deformation_temperature: log-sum-exp temperatures [Pa], [m].
        name: label (plots, JSON).
    """

    terms: dict = field(default_factory=lambda: {"max_stress": 1.0})
    sense: str = "minimize"
    smooth_max: str = "pnorm"
    p: float = 20.0
    stress_temperature: float = 1e3
    deformation_temperature: float = 1e-4
    name: str = ""

    def __post_init__(self):
        terms = dict(self.terms)
        if not terms:
            raise ValueError("an objective needs at least one term")
        unknown = sorted(set(terms) - set(OBJECTIVE_TERMS))
        if unknown:
            raise ValueError(f"unknown objective term(s) {unknown}; choose from {list(OBJECTIVE_TERMS)}")
        for k, w in terms.items():
            if not isinstance(w, (int, float)) or not torch.isfinite(torch.tensor(float(w))) or w == 0:
                raise ValueError(f"objective weight of {k!r} must be a finite non-zero number, got {w!r}")
        object.__setattr__(self, "terms", {k: float(w) for k, w in terms.items()})
        if self.sense not in ("minimize", "maximize"):
            raise ValueError(f"sense must be 'minimize' or 'maximize', got {self.sense!r}")
        if self.smooth_max not in ("pnorm", "logsumexp", "max"):
            raise ValueError(f"smooth_max must be 'pnorm', 'logsumexp' or 'max', got {self.smooth_max!r}")
        if not self.p >= 1:
            raise ValueError(f"p-norm exponent must be >= 1, got {self.p}")
        if not (self.stress_temperature > 0 and self.deformation_temperature > 0):
            raise ValueError("log-sum-exp temperatures must be positive")
        if not self.name:
            object.__setattr__(self, "name", self.default_name())

    def default_name(self) -> str:
        prefix = "min" if self.sense == "minimize" else "max"
        if len(self.terms) == 1 and next(iter(self.terms.values())) == 1.0:
            return f"{prefix}_{next(iter(self.terms))}"
        return f"{prefix}_" + "+".join(f"{w:g}*{k}" for k, w in self.terms.items())

    @property
    def units(self) -> str:
        """Units of Q: the term's SI unit for a single unit-weight term, else ``"1"`` (weighted sum)."""
        if len(self.terms) == 1 and next(iter(self.terms.values())) == 1.0:
            return _UNITS[next(iter(self.terms))]
        return "1"

    @property
    def sign(self) -> float:
        """+1 to minimize, -1 to maximize: ``loss = sign * Q``."""
        return 1.0 if self.sense == "minimize" else -1.0

    def _max(self, x: Tensor, temperature: float) -> Tensor:
        return smooth_max(x, self.smooth_max, self.p, temperature)

    def terms_of(self, stress: Tensor, displacement: Tensor) -> dict[str, Tensor]:
        """Each term (G,) for fields stress (G, N) [Pa] and displacement (G, N, 3) [m]."""
        if stress.ndim != 2 or displacement.shape != (*stress.shape, 3):
            raise ValueError(
                f"expected stress (G, N) and displacement (G, N, 3), got {tuple(stress.shape)} and "
                f"{tuple(displacement.shape)}"
            )
        out = {}
        deformation = None
        for k in self.terms:
            if k.endswith("deformation") and deformation is None:
                # |d| with a safe gradient at d = 0 (vertices that do not move)
                deformation = torch.sqrt((displacement**2).sum(-1) + torch.finfo(displacement.dtype).tiny)
            if k == "mean_stress":
                out[k] = stress.mean(-1)
            elif k == "max_stress":
                out[k] = self._max(stress.clamp_min(0.0), self.stress_temperature)
            elif k == "mean_deformation":
                out[k] = deformation.mean(-1)
            else:
                out[k] = self._max(deformation, self.deformation_temperature)
        return out

    def __call__(self, stress: Tensor, displacement: Tensor) -> Tensor:
        """Q (G,) of G grasps."""
        parts = self.terms_of(stress, displacement)
        return sum(self.terms[k] * v for k, v in parts.items())

    def loss(self, stress: Tensor, displacement: Tensor) -> Tensor:
        """(G,) the value the planner minimizes: Q, or -Q when maximizing."""
        return self.sign * self(stress, displacement)

    def better(self, a: Tensor, b: Tensor) -> Tensor:
        """Elementwise: is Q value ``a`` better than ``b``?"""
        return a < b if self.sense == "minimize" else a > b


PRESETS = {
    "min_max_stress": GraspObjective({"max_stress": 1.0}, "minimize"),
    "max_max_stress": GraspObjective({"max_stress": 1.0}, "maximize"),
    "min_mean_stress": GraspObjective({"mean_stress": 1.0}, "minimize"),
    "max_mean_stress": GraspObjective({"mean_stress": 1.0}, "maximize"),
    "min_mean_deformation": GraspObjective({"mean_deformation": 1.0}, "minimize"),
    "max_mean_deformation": GraspObjective({"mean_deformation": 1.0}, "maximize"),
}
"""Named single-term objectives (``configs/objective/*.yaml`` mirror them)."""
