"""Gaussian mixture regression of actions from tactile inputs (thesis §5.2, eqs 5.15-5.18).

Every state i of the learned HMM is a joint Gaussian over the observation ``o = [S, A]`` of
sensor input S and action output A (eqs 5.15-5.16):

    mu_i = [mu_i^S; mu_i^A],      Sigma_i = [[Sigma_i^SS, Sigma_i^SA], [Sigma_i^AS, Sigma_i^AA]].

Conditioning each state on the input gives a local linear regression

    A_i(S) = mu_i^A + Sigma_i^AS (Sigma_i^SS)^-1 (S - mu_i^S),
    Sigma_i^{A|S} = Sigma_i^AA - Sigma_i^AS (Sigma_i^SS)^-1 Sigma_i^SA,

and the prediction mixes them, ``A_hat = sum_i h_i A_i(S)``, with covariance
``sum_i h_i (Sigma_i^{A|S} + A_i A_i^T) - A_hat A_hat^T``.

Plain GMR uses fixed mixing weights. GMRa (Calinon et al.) uses the forward variable of the
HMM restricted to the input space, which carries the sequential information of the task:

    h_i(S_1) = pi_i N(S_1 | mu_i^S, Sigma_i^SS) / sum_k pi_k N(S_1 | mu_k^S, Sigma_k^SS)     (5.18)
    h_i(S_t) = N(S_t | mu_i^S, Sigma_i^SS) sum_j h_j(S_{t-1}) a_ji
               / sum_k N(S_t | mu_k^S, Sigma_k^SS) sum_j h_j(S_{t-1}) a_jk                 (5.17)

The weights are propagated in log space (no underflow for inputs far from every state).
:class:`ForwardGMR` is stateful for online execution (one :meth:`ForwardGMR.step` per control
cycle) and also predicts whole input sequences at once.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.special import logsumexp

from defgraspnets.tactile.lfd.hmm import GaussianHMM, gaussian_log_density

__all__ = ["ForwardGMR", "GMRPrediction", "GaussianConditionals", "GaussianMixtureRegression"]


def _dims(dims: Sequence[int], n_features: int, name: str) -> np.ndarray:
    idx = np.asarray(dims, dtype=np.int64)
    if idx.ndim != 1 or idx.size == 0:
        raise ValueError(f"{name} must be a non-empty list of feature indices")
    if (idx < 0).any() or (idx >= n_features).any() or np.unique(idx).size != idx.size:
        raise ValueError(f"{name} {idx.tolist()} must be distinct indices in [0, {n_features})")
    return idx


@dataclass(frozen=True)
class GaussianConditionals:
    """Per-state conditional Gaussians ``p(A | S, i)`` of a set of joint Gaussians.

    Attributes:
        input_means: (N, dS) ``mu_i^S``.
        input_covariances: (N, dS, dS) ``Sigma_i^SS``.
        output_means: (N, dA) ``mu_i^A``.
        regression: (N, dA, dS) ``Sigma_i^AS (Sigma_i^SS)^-1``.
        conditional_covariances: (N, dA, dA) ``Sigma_i^{A|S}``.
    """

    input_means: np.ndarray
    input_covariances: np.ndarray
    output_means: np.ndarray
    regression: np.ndarray
    conditional_covariances: np.ndarray

    @classmethod
    def from_joint(
        cls, means: np.ndarray, covariances: np.ndarray, input_dims: Sequence[int], output_dims: Sequence[int]
    ) -> GaussianConditionals:
        mu = np.asarray(means, dtype=np.float64)
        cov = np.asarray(covariances, dtype=np.float64)
        if mu.ndim != 2 or cov.shape != (mu.shape[0], mu.shape[1], mu.shape[1]):
            raise ValueError(f"means (N, D) and covariances (N, D, D) mismatch: {mu.shape}, {cov.shape}")
        s = _dims(input_dims, mu.shape[1], "input_dims")
        a = _dims(output_dims, mu.shape[1], "output_dims")
        if np.intersect1d(s, a).size:
            raise ValueError("input_dims and output_dims overlap")
        css = cov[:, s[:, None], s[None, :]]
        cas = cov[:, a[:, None], s[None, :]]
        caa = cov[:, a[:, None], a[None, :]]
        try:
            reg = np.swapaxes(np.linalg.solve(css, np.swapaxes(cas, 1, 2)), 1, 2)  # Sigma^AS (Sigma^SS)^-1
        except np.linalg.LinAlgError as err:
            raise ValueError("an input covariance Sigma^SS is singular") from err
        cond = caa - reg @ np.swapaxes(cas, 1, 2)
        return cls(mu[:, s], css, mu[:, a], reg, 0.5 * (cond + np.swapaxes(cond, 1, 2)))

    def input_log_density(self, inputs: np.ndarray) -> np.ndarray:
        """``log N(S | mu_i^S, Sigma_i^SS)``, (..., N)."""
        return gaussian_log_density(inputs, self.input_means, self.input_covariances)

    def local_predictions(self, inputs: np.ndarray) -> np.ndarray:
        """``A_i(S)`` for every state, (..., N, dA)."""
        diff = inputs[..., None, :] - self.input_means
        return self.output_means + np.einsum("nas,...ns->...na", self.regression, diff)

    def mix(self, inputs: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mixture mean (..., dA) and covariance (..., dA, dA) with weights (..., N)."""
        local = self.local_predictions(inputs)
        mean = np.einsum("...n,...na->...a", weights, local)
        second = np.einsum("...n,...nab->...ab", weights, self.conditional_covariances)
        second = second + np.einsum("...n,...na,...nb->...ab", weights, local, local)
        return mean, second - mean[..., :, None] * mean[..., None, :]


@dataclass(frozen=True)
class GMRPrediction:
    """Predicted actions for T inputs.

    Attributes:
        action: (T, dA) expected action ``A_hat``.
        covariance: (T, dA, dA) predictive covariance.
        weights: (T, N) mixing weights ``h_i``.
    """

    action: np.ndarray
    covariance: np.ndarray
    weights: np.ndarray


def _inputs(inputs, d_in: int) -> np.ndarray:
    x = np.asarray(inputs, dtype=np.float64)
    if x.ndim == 1:
        x = x[None]
    if x.ndim != 2 or x.shape[1] != d_in:
        raise ValueError(f"inputs must have shape (T, {d_in}), got {np.shape(inputs)}")
    if not np.isfinite(x).all():
        raise ValueError("inputs contain non-finite values")
    return x


class GaussianMixtureRegression:
    """Plain GMR: mixing weights ``h_i ∝ w_i N(S | mu_i^S, Sigma_i^SS)`` from fixed priors ``w``."""

    def __init__(self, priors, means, covariances, input_dims: Sequence[int], output_dims: Sequence[int]):
        w = np.asarray(priors, dtype=np.float64)
        self.conditionals = GaussianConditionals.from_joint(means, covariances, input_dims, output_dims)
        n = self.conditionals.input_means.shape[0]
        if w.shape != (n,) or (w < 0).any() or not np.isclose(w.sum(), 1.0):
            raise ValueError(f"priors must be a probability vector of length {n}")
        with np.errstate(divide="ignore"):
            self._log_priors = np.log(w)

    def predict(self, inputs) -> GMRPrediction:
        """Predict actions for inputs (T, dS) (each independently)."""
        x = _inputs(inputs, self.conditionals.input_means.shape[1])
        log_w = self._log_priors + self.conditionals.input_log_density(x)
        h = np.exp(log_w - logsumexp(log_w, axis=1, keepdims=True))
        mean, cov = self.conditionals.mix(x, h)
        return GMRPrediction(mean, cov, h)


class ForwardGMR:
    """GMR with forward-variable mixing weights (GMRa, eqs 5.17-5.18).

    Args:
        start_prob: (N,) ``pi``.
        transition: (N, N) ``A``.
        means, covariances: joint Gaussians of the states over ``[S, A]``.
        input_dims, output_dims: indices of S and A in the observation vector.
    """

    def __init__(self, start_prob, transition, means, covariances, input_dims, output_dims):
        self.conditionals = GaussianConditionals.from_joint(means, covariances, input_dims, output_dims)
        n = self.conditionals.input_means.shape[0]
        pi = np.asarray(start_prob, dtype=np.float64)
        a = np.asarray(transition, dtype=np.float64)
        if pi.shape != (n,) or (pi < 0).any() or not np.isclose(pi.sum(), 1.0):
            raise ValueError(f"start_prob must be a probability vector of length {n}")
        if a.shape != (n, n) or (a < 0).any() or not np.allclose(a.sum(axis=1), 1.0):
            raise ValueError(f"transition must be a row-stochastic ({n}, {n}) matrix")
        self.start_prob, self.transition = pi, a
        self._weights: np.ndarray | None = None

    @classmethod
    def from_hmm(cls, hmm: GaussianHMM, input_dims, output_dims) -> ForwardGMR:
        if hmm.means is None:
            raise ValueError("the HMM is not fitted")
        return cls(hmm.start_prob, hmm.transition, hmm.means, hmm.covariances, input_dims, output_dims)

    @property
    def weights(self) -> np.ndarray | None:
        """The last mixing weights ``h(S_{t})`` (None before the first step)."""
        return None if self._weights is None else self._weights.copy()

    def reset(self) -> None:
        """Start a new execution: the next step uses eq. (5.18)."""
        self._weights = None

    def _next_weights(self, log_density: np.ndarray, previous: np.ndarray | None) -> np.ndarray:
        with np.errstate(divide="ignore"):
            log_prior = np.log(self.start_prob if previous is None else previous @ self.transition)
        log_h = log_prior + log_density
        return np.exp(log_h - logsumexp(log_h))

    def step(self, sensor_input) -> tuple[np.ndarray, np.ndarray]:
        """One control cycle: weights by eq. (5.17) (eq. 5.18 after :meth:`reset`), then the action.

        Returns the expected action (dA,) and its covariance (dA, dA).
        """
        x = _inputs(sensor_input, self.conditionals.input_means.shape[1])
        if x.shape[0] != 1:
            raise ValueError("step() takes one input vector; use predict() for sequences")
        self._weights = self._next_weights(self.conditionals.input_log_density(x)[0], self._weights)
        mean, cov = self.conditionals.mix(x[0], self._weights)
        return mean, cov

    def predict(self, inputs) -> GMRPrediction:
        """Predict a whole input sequence (T, dS) from a fresh start (does not touch the online state)."""
        x = _inputs(inputs, self.conditionals.input_means.shape[1])
        log_density = self.conditionals.input_log_density(x)
        h = np.empty_like(log_density)
        prev = None
        for t in range(x.shape[0]):
            prev = h[t] = self._next_weights(log_density[t], prev)
        mean, cov = self.conditionals.mix(x, h)
        return GMRPrediction(mean, cov, h)
