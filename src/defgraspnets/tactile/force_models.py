"""Force-deformation models of the tactile membrane (thesis §2.4, eq. 2.2, Figs 2.9-2.11, Table 2.1).

The pressurized membrane at one pre-contact gas state (characterized by the product PV [N m] of
internal pressure and volume) is approximated by an equivalent linear-elastic sphere, so that a
spherical indenter obeys the Hertz contact law

    F = 4/3 E* sqrt(R*) delta^(3/2),                                                   (2.2)
    1/E* = (1 - nu_1^2)/E_1 + (1 - nu_2^2)/E_2,   1/R* = 1/R_1 + 1/R_2,

with F the axial load [N] and delta the indentation depth [m]. At small depths relative to the
sphere the measured curves are nearly linear, ``F = k delta + F_0``: each PV state gets a linear
least-squares fit, and the fitted slope k(PV) [N/m] is then fit by a 4th-order polynomial in PV
(Fig. 2.10), giving a deterministic force model for any gas state.

Force matching (Fig. 2.11) inverts the model: a desired force gives a desired indentation, and
a position-based proportional controller drives the indentation measured by the depth camera
to it. Errors ``F_actual - F_desired`` are reported as mean +- standard error (Table 2.1).

The depth-only force proxy of eq. (4.6) (ch. 4) also lives here: it is a force model too.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

__all__ = [
    "ForceMatchingCommand",
    "ForceMatchingController",
    "ForceModel",
    "HertzFit",
    "HertzModel",
    "LinearFit",
    "LinearForceModel",
    "PolynomialFit",
    "PVForceModel",
    "depth_force_proxy",
    "effective_modulus",
    "effective_radius",
    "fit_hertz",
    "fit_linear",
    "fit_linear_per_state",
    "fit_polynomial",
    "force_error_table",
    "hertz_force",
    "indentation_depth",
    "mean_and_standard_error",
]


def _vector(x, name: str, min_size: int = 1) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 1:
        raise ValueError(f"{name} must be a 1D array, got shape {a.shape}")
    if a.size < min_size:
        raise ValueError(f"{name} needs at least {min_size} values, got {a.size}")
    if not np.isfinite(a).all():
        raise ValueError(
            f"{name} contains non-finite values at indices {np.flatnonzero(~np.isfinite(a))[:8]}"
        )
    return a


def _pair(x, y, xname: str, yname: str, min_size: int) -> tuple[np.ndarray, np.ndarray]:
    a = _vector(x, xname, min_size)
    b = _vector(y, yname, min_size)
    if a.shape != b.shape:
        raise ValueError(f"{xname} {a.shape} and {yname} {b.shape} must have the same length")
    return a, b


# ----------------------------------------------------------------------------- Hertz (eq. 2.2)


def effective_modulus(
    youngs_modulus_1: float, poisson_ratio_1: float, youngs_modulus_2: float, poisson_ratio_2: float
) -> float:
    """``E* = ((1 - nu_1^2)/E_1 + (1 - nu_2^2)/E_2)^-1`` [Pa]; pass ``E = inf`` for a rigid body."""
    for e, nu, i in ((youngs_modulus_1, poisson_ratio_1, 1), (youngs_modulus_2, poisson_ratio_2, 2)):
        if not e > 0:
            raise ValueError(f"youngs_modulus_{i} must be > 0 Pa, got {e}")
        if not -1.0 < nu <= 0.5:
            raise ValueError(f"poisson_ratio_{i} must lie in (-1, 0.5], got {nu}")
    compliance = (1 - poisson_ratio_1**2) / youngs_modulus_1 + (1 - poisson_ratio_2**2) / youngs_modulus_2
    if compliance == 0:
        raise ValueError("both bodies are rigid: the effective modulus is infinite")
    return 1.0 / compliance


def effective_radius(radius_1: float, radius_2: float) -> float:
    """``R* = (1/R_1 + 1/R_2)^-1`` [m]; pass ``inf`` for a flat body."""
    for r, i in ((radius_1, 1), (radius_2, 2)):
        if not r > 0:
            raise ValueError(f"radius_{i} must be > 0 m (inf for a plane), got {r}")
    curvature = 1.0 / radius_1 + 1.0 / radius_2
    if curvature == 0:
        raise ValueError("both bodies are flat: Hertz contact needs a curved body")
    return 1.0 / curvature


def hertz_force(indentation, effective_modulus: float, effective_radius: float) -> np.ndarray:
    """Eq. (2.2): ``F = 4/3 E* sqrt(R*) delta^(3/2)`` [N]; zero for ``delta <= 0`` (no contact)."""
    if not effective_modulus > 0 or not effective_radius > 0:
        raise ValueError(f"E* and R* must be > 0, got {effective_modulus} Pa, {effective_radius} m")
    d = np.asarray(indentation, dtype=np.float64)
    return 4.0 / 3.0 * effective_modulus * np.sqrt(effective_radius) * np.maximum(d, 0.0) ** 1.5


class ForceModel(Protocol):
    """A monotone axial force-indentation law and its inverse."""

    def force(self, indentation) -> np.ndarray:
        """Axial force [N] at indentation depth [m]."""
        ...

    def indentation(self, force) -> np.ndarray:
        """Indentation depth [m] at which the model gives ``force`` [N]."""
        ...


@dataclass(frozen=True)
class HertzModel:
    """``F = c delta^(3/2)`` with ``c = 4/3 E* sqrt(R*)`` [N m^-3/2] (eq. 2.2)."""

    coefficient: float

    def __post_init__(self):
        if not self.coefficient > 0:
            raise ValueError(f"Hertz coefficient must be > 0 N/m^1.5, got {self.coefficient}")

    @classmethod
    def from_materials(cls, effective_modulus: float, effective_radius: float) -> HertzModel:
        return cls(4.0 / 3.0 * effective_modulus * np.sqrt(effective_radius))

    def force(self, indentation) -> np.ndarray:
        return self.coefficient * np.maximum(np.asarray(indentation, dtype=np.float64), 0.0) ** 1.5

    def indentation(self, force) -> np.ndarray:
        f = np.asarray(force, dtype=np.float64)
        if (f < 0).any():
            raise ValueError("a compressive indenter cannot produce a negative force")
        return (f / self.coefficient) ** (2.0 / 3.0)


@dataclass(frozen=True)
class HertzFit:
    """Least-squares fit of ``F = c delta^(3/2)`` (eq. 2.2 with the geometry lumped into c).

    Attributes:
        model: the fitted :class:`HertzModel`.
        coefficient_std: standard error of c [N m^-3/2].
        effective_modulus, effective_modulus_std: ``E* = 3 c / (4 sqrt(R*))`` [Pa] and its
            standard error, when ``R*`` was given (else NaN).
        residual_std: RMS residual with one degree of freedom removed [N].
    """

    model: HertzModel
    coefficient_std: float
    effective_modulus: float
    effective_modulus_std: float
    residual_std: float


def fit_hertz(indentation, force, effective_radius: float | None = None) -> HertzFit:
    """Fit eq. (2.2) to force-indentation data by linear least squares in ``delta^(3/2)``.

    The model ``F = c x`` with ``x = delta^(3/2)`` is linear in c:
    ``c = sum(x F) / sum(x^2)``, ``Var(c) = s^2 / sum(x^2)``, ``s^2 = RSS / (n - 1)``.
    Points with ``delta <= 0`` (before contact) must be removed by the caller.
    """
    d, f = _pair(indentation, force, "indentation", "force", 2)
    if (d <= 0).any():
        raise ValueError("indentation must be > 0 m for every sample (drop pre-contact samples)")
    x = d**1.5
    sxx = float(x @ x)
    c = float(x @ f) / sxx
    if not c > 0:
        raise ValueError(f"fitted Hertz coefficient is not positive ({c}); is the force sign right?")
    rss = float(((f - c * x) ** 2).sum())
    s2 = rss / (d.size - 1)
    c_std = np.sqrt(s2 / sxx)
    if effective_radius is None:
        e, e_std = np.nan, np.nan
    else:
        if not effective_radius > 0:
            raise ValueError(f"effective_radius must be > 0 m, got {effective_radius}")
        scale = 3.0 / (4.0 * np.sqrt(effective_radius))
        e, e_std = c * scale, c_std * scale
    return HertzFit(HertzModel(c), float(c_std), float(e), float(e_std), float(np.sqrt(s2)))


# ----------------------------------------------------------------------------- linear fits per PV


@dataclass(frozen=True)
class LinearForceModel:
    """``F = slope * delta + intercept`` [N], slope [N/m], intercept [N]."""

    slope: float
    intercept: float = 0.0

    def __post_init__(self):
        if not self.slope > 0:
            raise ValueError(f"force-indentation slope must be > 0 N/m, got {self.slope}")

    def force(self, indentation) -> np.ndarray:
        return self.slope * np.asarray(indentation, dtype=np.float64) + self.intercept

    def indentation(self, force) -> np.ndarray:
        return (np.asarray(force, dtype=np.float64) - self.intercept) / self.slope


@dataclass(frozen=True)
class LinearFit:
    """Ordinary least squares ``F = k delta + F_0`` with standard errors.

    Attributes:
        slope, intercept: k [N/m] and F_0 [N].
        slope_std, intercept_std: their standard errors (``s^2 (X^T X)^-1`` with ``s^2 = RSS/(n-2)``).
        r_squared: coefficient of determination.
        residual_std: ``s`` [N].
    """

    slope: float
    intercept: float
    slope_std: float
    intercept_std: float
    r_squared: float
    residual_std: float

    @property
    def model(self) -> LinearForceModel:
        return LinearForceModel(self.slope, self.intercept)


def fit_linear(indentation, force) -> LinearFit:
    """Least-squares line through force-indentation samples of one PV state (Fig. 2.9)."""
    d, f = _pair(indentation, force, "indentation", "force", 3)
    if np.ptp(d) == 0:
        raise ValueError("indentation samples are all equal: the slope is undetermined")
    x = np.column_stack([d, np.ones_like(d)])
    coef, *_ = np.linalg.lstsq(x, f, rcond=None)
    resid = f - x @ coef
    rss = float(resid @ resid)
    dof = d.size - 2
    s2 = rss / dof if dof > 0 else np.nan
    cov = s2 * np.linalg.inv(x.T @ x)
    tss = float(((f - f.mean()) ** 2).sum())
    r2 = 1.0 - rss / tss if tss > 0 else 1.0
    return LinearFit(
        float(coef[0]),
        float(coef[1]),
        float(np.sqrt(cov[0, 0])),
        float(np.sqrt(cov[1, 1])),
        float(r2),
        float(np.sqrt(s2)),
    )


def fit_linear_per_state(indentations: Sequence, forces: Sequence) -> list[LinearFit]:
    """One :func:`fit_linear` per gas state: ``indentations[i]``, ``forces[i]`` are that state's samples."""
    if len(indentations) != len(forces):
        raise ValueError(f"{len(indentations)} indentation series but {len(forces)} force series")
    return [fit_linear(d, f) for d, f in zip(indentations, forces)]


@dataclass(frozen=True)
class PolynomialFit:
    """Least-squares polynomial ``y = sum_k a_k ((x - x_c) / x_s)^k`` with parameter covariance.

    The abscissa is centred and scaled (``x_c`` mean, ``x_s`` half-range) for conditioning: PV
    values of ~10^2 N m would otherwise give a Vandermonde matrix spanning 10^8.

    Attributes:
        coefficients: (order + 1,) ``a_0 .. a_order`` in the scaled variable.
        covariance: (order + 1, order + 1) covariance of the coefficients (NaN for an exact fit).
        x_center, x_scale: the affine map of the abscissa.
        residual_std: ``sqrt(RSS / (n - order - 1))`` (NaN for an exact fit).
    """

    coefficients: np.ndarray
    covariance: np.ndarray
    x_center: float
    x_scale: float
    residual_std: float

    @property
    def order(self) -> int:
        return self.coefficients.size - 1

    def _design(self, x) -> np.ndarray:
        u = (np.asarray(x, dtype=np.float64) - self.x_center) / self.x_scale
        return u[..., None] ** np.arange(self.order + 1)

    def __call__(self, x) -> np.ndarray:
        return self._design(x) @ self.coefficients

    def standard_error(self, x) -> np.ndarray:
        """Standard error of the fitted curve at ``x`` (delta method on the coefficients)."""
        v = self._design(x)
        return np.sqrt(np.einsum("...i,ij,...j->...", v, self.covariance, v))


def fit_polynomial(x, y, order: int = 4) -> PolynomialFit:
    """Least-squares polynomial of ``order`` (4 for slope vs PV, Fig. 2.10)."""
    if int(order) != order or order < 0:
        raise ValueError(f"order must be an integer >= 0, got {order}")
    a, b = _pair(x, y, "x", "y", order + 1)
    if np.unique(a).size < order + 1:
        raise ValueError(f"an order-{order} polynomial needs {order + 1} distinct abscissae")
    center = float(a.mean())
    scale = float(np.ptp(a) / 2) or 1.0
    v = ((a - center) / scale)[:, None] ** np.arange(order + 1)
    coef, *_ = np.linalg.lstsq(v, b, rcond=None)
    dof = a.size - order - 1
    if dof > 0:
        resid = b - v @ coef
        s2 = float(resid @ resid) / dof
        cov = s2 * np.linalg.inv(v.T @ v)
    else:
        s2 = np.nan
        cov = np.full((order + 1, order + 1), np.nan)
    return PolynomialFit(coef, cov, center, scale, float(np.sqrt(s2)))


@dataclass(frozen=True)
class PVForceModel:
    """Force model for any gas state: slope k(PV) from a polynomial fit, ``F = k(PV) delta``.

    Attributes:
        slope_fit: polynomial k(PV) [N/m] of PV [N m] for one indenter geometry (Fig. 2.10).
        pv_range: (min, max) PV covered by the characterization data; outside it the polynomial
            is an extrapolation and :meth:`at` refuses it.
    """

    slope_fit: PolynomialFit
    pv_range: tuple[float, float]

    @classmethod
    def fit(cls, pv, slopes, order: int = 4) -> PVForceModel:
        pv_arr = _vector(pv, "pv")
        return cls(fit_polynomial(pv_arr, slopes, order), (float(pv_arr.min()), float(pv_arr.max())))

    def at(self, pv: float) -> LinearForceModel:
        """The linear force model (through the origin) at gas state ``pv`` [N m]."""
        lo, hi = self.pv_range
        if not lo <= pv <= hi:
            raise ValueError(f"PV = {pv} N m is outside the characterized range [{lo}, {hi}]")
        return LinearForceModel(float(self.slope_fit(pv)))


# ----------------------------------------------------------------------------- measurements


def indentation_depth(depth_image, reference_depth_image, percentile: float = 100.0, mask=None) -> float:
    """Indentation depth of the membrane from the depth camera [m].

    ``delta = percentile_q( D_0 - D )`` over valid pixels (and ``mask`` if given), where ``D_0``
    is the undeformed reference depth image and ``D`` the current one [m]: the membrane is
    pushed toward the camera, so its depth decreases. ``percentile = 100`` is the maximum
    (the pole indentation for an axial indenter); a lower percentile rejects depth outliers.
    Both images must come from the same camera (depth along the optical axis or along the ray,
    consistently). NaN pixels are ignored.
    """
    d = np.asarray(depth_image, dtype=np.float64)
    d0 = np.asarray(reference_depth_image, dtype=np.float64)
    if d.ndim != 2 or d.shape != d0.shape:
        raise ValueError(f"depth images must be 2D with equal shapes, got {d.shape} and {d0.shape}")
    if not 0.0 <= percentile <= 100.0:
        raise ValueError(f"percentile must be in [0, 100], got {percentile}")
    valid = np.isfinite(d) & np.isfinite(d0)
    if mask is not None:
        m = np.asarray(mask)
        if m.shape != d.shape or m.dtype != np.bool_:
            raise ValueError(f"mask must be a boolean image of shape {d.shape}")
        valid &= m
    if not valid.any():
        raise ValueError("no pixel is valid in both depth images (and the mask)")
    return float(np.percentile((d0 - d)[valid], percentile))


def depth_force_proxy(depth_image, reference_depth_image, mask=None) -> float:
    """Force-correlated measure of eq. (4.6): ``F~ = sum_i (p_i(0) - p_i(t))`` [m].

    Every pixel is treated as an independent linear spring, so the sum of the depth decreases
    over the N_p valid pixels correlates with the applied force (Fig. 4.4); multiply by a
    per-pixel stiffness [N/m] to get newtons. NaN pixels (in either image) are skipped.
    """
    d = np.asarray(depth_image, dtype=np.float64)
    d0 = np.asarray(reference_depth_image, dtype=np.float64)
    if d.ndim != 2 or d.shape != d0.shape:
        raise ValueError(f"depth images must be 2D with equal shapes, got {d.shape} and {d0.shape}")
    valid = np.isfinite(d) & np.isfinite(d0)
    if mask is not None:
        m = np.asarray(mask)
        if m.shape != d.shape or m.dtype != np.bool_:
            raise ValueError(f"mask must be a boolean image of shape {d.shape}")
        valid &= m
    if not valid.any():
        raise ValueError("no pixel is valid in both depth images (and the mask)")
    return float((d0 - d)[valid].sum())


# ----------------------------------------------------------------------------- force matching


@dataclass(frozen=True)
class ForceMatchingCommand:
    """One step of :class:`ForceMatchingController`.

    Attributes:
        displacement: commanded actuator travel along the sensor axis this step [m]
            (positive presses further into the obstacle).
        target_indentation: ``delta_des`` from the force model [m].
        indentation_error: ``delta_des - delta`` [m].
    """

    displacement: float
    target_indentation: float
    indentation_error: float


@dataclass(frozen=True)
class ForceMatchingController:
    """Position-based proportional force matching on the camera-measured indentation (§2.4).

    The force model maps the desired force to a desired indentation
    ``delta_des = model.indentation(F_des)``; each control step commands
    ``u = clip(K_p (delta_des - delta), -max_step, max_step)`` [m] of actuator travel. The
    controller is stateless: the measured indentation is the state.

    Attributes:
        model: a :class:`ForceModel` (e.g. ``PVForceModel.at(pv)`` or :class:`HertzModel`).
        gain: ``K_p`` (dimensionless, in (0, 2) for a plant whose indentation follows the
            actuator one-to-one; 1 reaches the target in one step).
        max_step: largest actuator travel per step [m].
    """

    model: ForceModel
    gain: float = 0.5
    max_step: float = 2.0e-3

    def __post_init__(self):
        if not self.gain > 0:
            raise ValueError(f"gain must be > 0, got {self.gain}")
        if not self.max_step > 0:
            raise ValueError(f"max_step must be > 0 m, got {self.max_step}")

    def target_indentation(self, desired_force: float) -> float:
        if not np.isfinite(desired_force) or desired_force < 0:
            raise ValueError(f"desired_force must be finite and >= 0 N, got {desired_force}")
        target = float(self.model.indentation(desired_force))
        return max(target, 0.0)

    def step(self, measured_indentation: float, desired_force: float) -> ForceMatchingCommand:
        if not np.isfinite(measured_indentation):
            raise ValueError(f"measured_indentation must be finite, got {measured_indentation}")
        target = self.target_indentation(desired_force)
        error = target - float(measured_indentation)
        u = float(np.clip(self.gain * error, -self.max_step, self.max_step))
        return ForceMatchingCommand(u, target, error)


# ----------------------------------------------------------------------------- statistics


def mean_and_standard_error(values) -> tuple[float, float]:
    """Sample mean and its standard error ``s / sqrt(n)`` (``s`` with ``n - 1``); SE is NaN for n = 1."""
    v = _vector(values, "values")
    se = float(v.std(ddof=1) / np.sqrt(v.size)) if v.size > 1 else np.nan
    return float(v.mean()), se


def force_error_table(pv, actual_force, desired_force) -> dict[float, tuple[float, float]]:
    """Table 2.1: per gas state PV, mean +- standard error of ``F_actual - F_desired`` [N].

    ``pv``, ``actual_force`` and ``desired_force`` are aligned 1D arrays, one entry per trial;
    all trials of one PV (over every desired force) are pooled.
    """
    p = _vector(pv, "pv")
    fa, fd = _pair(actual_force, desired_force, "actual_force", "desired_force", 1)
    if p.shape != fa.shape:
        raise ValueError(f"pv {p.shape} and forces {fa.shape} must have the same length")
    err = fa - fd
    return {float(v): mean_and_standard_error(err[p == v]) for v in np.unique(p)}
