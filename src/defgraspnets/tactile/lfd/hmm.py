"""Gaussian hidden Markov model fitted by Baum-Welch over several demonstrations (thesis §5.2).

An HMM ``Lambda = (A, B, pi)`` with N hidden states has Gaussian emissions (eq. 5.1)

    b_j(o_t) = N(o_t | mu_j, Sigma_j),

transition matrix ``a_ij = p(Q_t = j | Q_{t-1} = i)`` and initial distribution ``pi_i``.
Baum-Welch (EM) maximizes ``p(O | Lambda)`` (eq. 5.2) over M demonstrations ``O^1..O^M`` with
the forward (eqs 5.3-5.5) and backward (eqs 5.6-5.8) recursions, the state posteriors
``gamma`` (5.9) and pair posteriors ``xi`` (5.10), and the updates (5.11)-(5.14):

    pi_i  = 1/M sum_m gamma_i^m(1)
    mu_i  = sum_{m,t} gamma_i^m(t) o_t^m / sum_{m,t} gamma_i^m(t)
    Sigma_i = [ sum_{m,t} gamma_i^m(t) (o_t^m - mu_i)(o_t^m - mu_i)^T + psi I ] / sum_{m,t} gamma_i^m(t)
    a_ij  = sum_{m, t<T_m} xi_ij^m(t) / sum_{m, t<T_m} gamma_i^m(t)

The ``psi I`` term (``covariance_regularization``) is not in the thesis: it keeps every
covariance positive definite when a state sees (near-)constant features, e.g. the no-contact
defaults of §5.3. It is the exact MAP update under the prior
``log p(Sigma_i) = -1/2 tr(psi Sigma_i^-1)``, so each iteration provably does not decrease
``log p(O | Lambda) + sum_i log p(Sigma_i)`` (reported as ``objective_history``); with
``psi = 0`` it is the plain maximum-likelihood update of eq. (5.13). This is the same update
as hmmlearn's ``GaussianHMM(covariance_type="full", covars_prior=psi * I, covars_weight=1)``.

Numerics: the recursions use the scaled forward-backward algorithm, vectorized over the
demonstrations (padded to the longest one). Emission log-densities are shifted by their
per-step maximum before exponentiation, so neither the Gaussians nor ``alpha`` underflow; the
log-likelihood is ``sum_t (log c_t + shift_t)`` with the scaling factors ``c_t``.

Initialization follows the thesis where it is specific: ``pi`` uniform, ``mu_i`` the k-means
centres (k-means++ seeding, best of ``n_init`` runs). The thesis initializes covariances
randomly; here every ``Sigma_i`` starts as the covariance of all data plus ``psi I``
(deterministic given the seed, and never ill-conditioned), and ``A`` starts uniform.

Restarts: EM only finds a local maximum. :meth:`GaussianHMM.fit_restarts` runs Baum-Welch from
``n_restarts`` initializations and returns every fitted run; with ``n_restarts = R > 1``,
:meth:`GaussianHMM.fit` keeps the run with the highest final objective (training data only). The
first run is exactly the single-run fit (k-means best of ``n_init``); the others draw their k-means++
seeds from the same generator and run k-means once each, so they start from different clusterings.
Hence the kept objective is never below the single run's. A caller may select among the runs of
:meth:`GaussianHMM.fit_restarts` by another training-data criterion.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

__all__ = ["GaussianHMM", "gaussian_log_density", "kmeans"]

_LOG_2PI = np.log(2.0 * np.pi)
_TINY = np.finfo(np.float64).tiny


def gaussian_log_density(x: np.ndarray, means: np.ndarray, covariances: np.ndarray) -> np.ndarray:
    """``log N(x | mu_k, Sigma_k)`` for every sample and component.

    Args:
        x: (..., D) samples.
        means: (K, D).
        covariances: (K, D, D) symmetric positive definite.

    Returns:
        (..., K) log-densities.
    """
    d = means.shape[1]
    try:
        chol = np.linalg.cholesky(covariances)
    except np.linalg.LinAlgError as err:
        raise ValueError("a covariance matrix is not positive definite") from err
    chol_inv = np.linalg.inv(chol)  # (K, D, D), lower triangular
    log_det = 2.0 * np.log(np.diagonal(chol, axis1=1, axis2=2)).sum(axis=1)
    diff = x[..., None, :] - means  # (..., K, D)
    z = np.einsum("kij,...kj->...ki", chol_inv, diff)
    return -0.5 * (d * _LOG_2PI + log_det + (z * z).sum(axis=-1))


def kmeans(
    data: np.ndarray, n_clusters: int, rng: np.random.Generator, n_init: int = 10, max_iter: int = 300
) -> np.ndarray:
    """Lloyd's k-means with k-means++ seeding; returns the (n_clusters, D) centres of the best run.

    An emptied cluster is re-seeded at the point farthest from its centre.
    """
    x = np.asarray(data, dtype=np.float64)
    n = x.shape[0]
    if np.unique(x, axis=0).shape[0] < n_clusters:
        raise ValueError(f"k-means needs at least {n_clusters} distinct points, got fewer")
    best, best_inertia = None, np.inf
    for _ in range(n_init):
        centres = np.empty((n_clusters, x.shape[1]))
        centres[0] = x[rng.integers(n)]
        d2 = ((x - centres[0]) ** 2).sum(axis=1)
        for k in range(1, n_clusters):
            total = d2.sum()
            idx = rng.choice(n, p=d2 / total) if total > 0 else rng.integers(n)
            centres[k] = x[idx]
            d2 = np.minimum(d2, ((x - centres[k]) ** 2).sum(axis=1))
        labels = None
        for _ in range(max_iter):
            dist = ((x[:, None, :] - centres[None]) ** 2).sum(axis=2)
            new_labels = dist.argmin(axis=1)
            if labels is not None and np.array_equal(new_labels, labels):
                break
            labels = new_labels
            empty = np.setdiff1d(np.arange(n_clusters), labels)
            if empty.size:  # re-seed each empty cluster at the worst-fitted remaining point
                own = dist[np.arange(n), labels]
                for k, far in zip(empty, np.argsort(own)[::-1]):
                    labels[far] = k
            counts = np.bincount(labels, minlength=n_clusters)
            sums = np.zeros_like(centres)
            np.add.at(sums, labels, x)
            centres = sums / counts[:, None]
        inertia = ((x - centres[labels]) ** 2).sum()
        if inertia < best_inertia:
            best, best_inertia = centres.copy(), inertia
    return best


def _pad(sequences: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Stack sequences (T_m, D) into (M, T_max, D) zero-padded plus a (M, T_max) validity mask."""
    if len(sequences) == 0:
        raise ValueError("need at least one demonstration sequence")
    seqs = [np.asarray(s, dtype=np.float64) for s in sequences]
    dims = {s.shape[1] if s.ndim == 2 else None for s in seqs}
    if None in dims or len(dims) != 1:
        raise ValueError(
            f"every sequence must be (T, D) with the same D, got shapes {[s.shape for s in seqs]}"
        )
    for i, s in enumerate(seqs):
        if s.shape[0] < 1:
            raise ValueError(f"sequence {i} is empty")
        if not np.isfinite(s).all():
            raise ValueError(f"sequence {i} contains non-finite values")
    t_max = max(s.shape[0] for s in seqs)
    x = np.zeros((len(seqs), t_max, dims.pop()))
    mask = np.zeros((len(seqs), t_max), dtype=bool)
    for i, s in enumerate(seqs):
        x[i, : s.shape[0]] = s
        mask[i, : s.shape[0]] = True
    return x, mask


@dataclass
class GaussianHMM:
    """Full-covariance Gaussian HMM with Baum-Welch training on several sequences.

    Attributes:
        n_states: N hidden states.
        covariance_regularization: ``psi`` >= 0 added to each state's scatter matrix (units of
            feature^2 times a count of samples); see the module docstring.
        max_iter: maximum EM iterations.
        tol: stop when the total log-likelihood improves by less than this.
        n_init: k-means restarts for the initial means (of the first Baum-Welch run).
        n_restarts: Baum-Welch runs from different k-means initializations; the run with the highest
            final objective is kept (see the module docstring). 1 = a single run.
        random_state: seed of the k-means initializations.
        start_prob, transition, means, covariances: the parameters ``pi`` (N,), ``A`` (N, N),
            ``mu`` (N, D), ``Sigma`` (N, D, D), set by :meth:`fit` or :meth:`set_parameters`.
        log_likelihood_history: ``log p(O | Lambda)`` evaluated at the start of each iteration.
        objective_history: the same plus the covariance log-prior (the EM-monotone objective).
        restart_objectives: objective of the final parameters of every Baum-Welch run of the last
            :meth:`fit` (one per restart; the kept run is the argmax).
    """

    n_states: int
    covariance_regularization: float = 1e-6
    max_iter: int = 100
    tol: float = 1e-4
    n_init: int = 10
    n_restarts: int = 1
    random_state: int | None = None
    start_prob: np.ndarray | None = field(default=None, repr=False)
    transition: np.ndarray | None = field(default=None, repr=False)
    means: np.ndarray | None = field(default=None, repr=False)
    covariances: np.ndarray | None = field(default=None, repr=False)
    log_likelihood_history: list[float] = field(default_factory=list, repr=False)
    objective_history: list[float] = field(default_factory=list, repr=False)
    restart_objectives: list[float] = field(default_factory=list, repr=False)

    def __post_init__(self):
        if int(self.n_states) != self.n_states or self.n_states < 1:
            raise ValueError(f"n_states must be a positive integer, got {self.n_states}")
        if not self.covariance_regularization >= 0:
            raise ValueError(f"covariance_regularization must be >= 0, got {self.covariance_regularization}")
        if self.max_iter < 0:
            raise ValueError(f"max_iter must be >= 0, got {self.max_iter}")
        if int(self.n_restarts) != self.n_restarts or self.n_restarts < 1:
            raise ValueError(f"n_restarts must be a positive integer, got {self.n_restarts}")

    # ------------------------------------------------------------------ parameters

    @property
    def n_features(self) -> int:
        self._require_fitted()
        return self.means.shape[1]

    def _require_fitted(self) -> None:
        if self.means is None:
            raise RuntimeError("the HMM has no parameters yet: call fit() or set_parameters()")

    def set_parameters(self, start_prob, transition, means, covariances) -> GaussianHMM:
        """Set ``(pi, A, mu, Sigma)`` explicitly (validated); returns self."""
        n = self.n_states
        pi = np.asarray(start_prob, dtype=np.float64)
        a = np.asarray(transition, dtype=np.float64)
        mu = np.asarray(means, dtype=np.float64)
        cov = np.asarray(covariances, dtype=np.float64)
        if pi.shape != (n,) or not np.isclose(pi.sum(), 1.0) or (pi < 0).any():
            raise ValueError(f"start_prob must be a probability vector of length {n}")
        if a.shape != (n, n) or not np.allclose(a.sum(axis=1), 1.0) or (a < 0).any():
            raise ValueError(f"transition must be a row-stochastic ({n}, {n}) matrix")
        if mu.ndim != 2 or mu.shape[0] != n or not np.isfinite(mu).all():
            raise ValueError(f"means must be a finite ({n}, D) array, got shape {mu.shape}")
        d = mu.shape[1]
        if cov.shape != (n, d, d) or not np.allclose(cov, np.swapaxes(cov, 1, 2)):
            raise ValueError(f"covariances must be symmetric ({n}, {d}, {d}) matrices, got {cov.shape}")
        if (np.linalg.eigvalsh(cov) <= 0).any():
            raise ValueError("covariances must be positive definite")
        self.start_prob, self.transition, self.means, self.covariances = pi, a, mu, cov
        return self

    def initialize(
        self,
        sequences: Sequence[np.ndarray],
        rng: np.random.Generator | None = None,
        n_init: int | None = None,
    ) -> GaussianHMM:
        """Uniform ``pi`` and ``A``, k-means means, pooled data covariance (+ psi I) for every state.

        ``rng`` (default: a new generator seeded with ``random_state``) seeds k-means, ``n_init``
        (default ``self.n_init``) is its number of runs.
        """
        x, mask = _pad(sequences)
        data = x[mask]
        n, d = self.n_states, data.shape[1]
        rng = np.random.default_rng(self.random_state) if rng is None else rng
        means = kmeans(data, n, rng, n_init=self.n_init if n_init is None else n_init)
        cov = np.cov(data.T, bias=True).reshape(d, d) + self.covariance_regularization * np.eye(d)
        if (np.linalg.eigvalsh(cov) <= 0).any():
            raise ValueError(
                "the pooled data covariance is singular (a constant feature?); "
                "set covariance_regularization > 0"
            )
        return self.set_parameters(
            np.full(n, 1.0 / n), np.full((n, n), 1.0 / n), means, np.repeat(cov[None], n, 0)
        )

    # ------------------------------------------------------------------ inference

    def _check_data(self, x: np.ndarray) -> None:
        if x.shape[-1] != self.n_features:
            raise ValueError(f"observations have {x.shape[-1]} features, the model {self.n_features}")

    def _forward_backward(self, x: np.ndarray, mask: np.ndarray, backward: bool = True):
        """Scaled forward-backward over a padded batch.

        Returns ``alpha_hat`` (M, T, N) (filtered posteriors ``p(Q_t | o_1..t)``), ``beta_hat``
        (M, T, N) or None, ``c`` (M, T) scaling factors, ``b_hat`` (M, T, N) shifted emission
        likelihoods and the per-sequence log-likelihoods (M,).
        """
        m_seq, t_max, _ = x.shape
        log_b = gaussian_log_density(x, self.means, self.covariances)
        log_b[~mask] = 0.0  # padded steps: b = 1 for every state, so they leave alpha and c unchanged
        shift = log_b.max(axis=2)
        b_hat = np.exp(log_b - shift[..., None])
        a = self.transition
        alpha = np.empty((m_seq, t_max, self.n_states))
        c = np.empty((m_seq, t_max))
        alpha_t = self.start_prob * b_hat[:, 0]  # (5.4)
        for t in range(t_max):
            if t > 0:
                alpha_t = (alpha_t @ a) * b_hat[:, t]  # (5.5)
            c[:, t] = np.maximum(alpha_t.sum(axis=1), _TINY)
            alpha_t = alpha_t / c[:, t, None]
            alpha[:, t] = alpha_t
        log_lik = (np.log(c) + shift).sum(axis=1)
        beta = None
        if backward:
            beta = np.empty_like(alpha)
            beta[:, -1] = 1.0  # (5.7); padded tails keep beta = 1 back to each sequence's end
            for t in range(t_max - 2, -1, -1):
                beta[:, t] = ((b_hat[:, t + 1] * beta[:, t + 1]) @ a.T) / c[:, t + 1, None]  # (5.8)
        return alpha, beta, c, b_hat, log_lik

    def _log_prior(self) -> float:
        psi = self.covariance_regularization
        if psi == 0:
            return 0.0
        return float(-0.5 * psi * np.trace(np.linalg.inv(self.covariances), axis1=1, axis2=2).sum())

    def score(self, sequences: Sequence[np.ndarray]) -> float:
        """Total ``log p(O | Lambda) = sum_m log p(O^m | Lambda)`` [nats]."""
        self._require_fitted()
        x, mask = _pad(sequences)
        self._check_data(x)
        return float(self._forward_backward(x, mask, backward=False)[4].sum())

    def forward_variables(self, sequence: np.ndarray) -> tuple[np.ndarray, float]:
        """Normalized forward variables ``alpha_i(t) / sum_j alpha_j(t) = p(Q_t = i | o_1..o_t)``.

        Returns (T, N) filtered state probabilities and the sequence log-likelihood.
        """
        self._require_fitted()
        x, mask = _pad([sequence])
        self._check_data(x)
        alpha, _, _, _, ll = self._forward_backward(x, mask, backward=False)
        return alpha[0], float(ll[0])

    def posteriors(self, sequence: np.ndarray) -> np.ndarray:
        """State posteriors ``gamma_i(t)`` of eq. (5.9), (T, N)."""
        self._require_fitted()
        x, mask = _pad([sequence])
        self._check_data(x)
        alpha, beta, *_ = self._forward_backward(x, mask)
        return alpha[0] * beta[0]

    def viterbi(self, sequence: np.ndarray) -> tuple[np.ndarray, float]:
        """Most likely state path (T,) and its log-probability (log-space Viterbi)."""
        self._require_fitted()
        x, _ = _pad([sequence])
        self._check_data(x)
        log_b = gaussian_log_density(x[0], self.means, self.covariances)
        with np.errstate(divide="ignore"):
            log_a = np.log(self.transition)
            delta = np.log(self.start_prob) + log_b[0]
        back = np.zeros(log_b.shape, dtype=np.int64)
        for t in range(1, log_b.shape[0]):
            scores = delta[:, None] + log_a
            back[t] = scores.argmax(axis=0)
            delta = scores.max(axis=0) + log_b[t]
        path = np.empty(log_b.shape[0], dtype=np.int64)
        path[-1] = delta.argmax()
        for t in range(log_b.shape[0] - 1, 0, -1):
            path[t - 1] = back[t, path[t]]
        return path, float(delta.max())

    # ------------------------------------------------------------------ learning

    def _em_step(self, x: np.ndarray, mask: np.ndarray) -> float:
        """One Baum-Welch iteration; returns the log-likelihood before the update."""
        alpha, beta, c, b_hat, log_lik = self._forward_backward(x, mask)
        gamma = alpha * beta * mask[..., None]  # (5.9), zero on padding
        # sum_t xi_ij(t) of (5.10) over transitions t -> t+1 inside each sequence
        nxt = (b_hat[:, 1:] * beta[:, 1:]) / c[:, 1:, None] * mask[:, 1:, None]
        xi_sum = self.transition * np.einsum("mti,mtj->ij", alpha[:, :-1], nxt)

        occupancy = gamma.sum(axis=(0, 1))  # sum_{m,t} gamma_i^m(t)
        used = occupancy > 1e-10 * mask.sum()
        start = gamma[:, 0].mean(axis=0)  # (5.11)
        start_prob = start / start.sum()
        rows = xi_sum.sum(axis=1, keepdims=True)
        transition = np.where(rows > 0, xi_sum / np.where(rows > 0, rows, 1.0), self.transition)  # (5.14)

        means = self.means.copy()
        covariances = self.covariances.copy()
        weighted = np.einsum("mti,mtd->id", gamma, x)
        means[used] = weighted[used] / occupancy[used, None]  # (5.12)
        d = x.shape[2]
        for i in np.flatnonzero(used):
            diff = (x - means[i]) * np.sqrt(gamma[..., i])[..., None]
            scatter = np.einsum("mtd,mte->de", diff, diff)
            covariances[i] = (scatter + self.covariance_regularization * np.eye(d)) / occupancy[i]  # (5.13)
            covariances[i] = 0.5 * (covariances[i] + covariances[i].T)
        self.start_prob, self.transition, self.means, self.covariances = (
            start_prob,
            transition,
            means,
            covariances,
        )
        return float(log_lik.sum())

    def fit(self, sequences: Sequence[np.ndarray], initialize: bool = True) -> GaussianHMM:
        """Baum-Welch on the demonstrations ``sequences`` (list of (T_m, D) arrays); returns self.

        Args:
            sequences: the M demonstrations.
            initialize: run :meth:`initialize` first (``n_restarts`` times, keeping the best run);
                False runs once from the current parameters.
        """
        if initialize:
            runs = self.fit_restarts(sequences)
            objectives = [r.restart_objectives[0] for r in runs]
            vars(self).update(vars(runs[int(np.argmax(objectives))]))  # the runs are copies of self
            self.restart_objectives = objectives
            return self
        self._require_fitted()
        x, mask = _pad(sequences)
        self._check_data(x)
        self._check_count(mask)
        self._baum_welch(x, mask)
        self.restart_objectives = [self._objective(x, mask)]
        return self

    def fit_restarts(self, sequences: Sequence[np.ndarray]) -> list[GaussianHMM]:
        """Baum-Welch from ``n_restarts`` initializations (see the module docstring); returns one fitted
        copy per run, run 0 being the single-run fit. Each copy's ``restart_objectives`` holds its own final
        objective. ``self`` is left unchanged."""
        x, mask = _pad(sequences)
        self._check_count(mask)
        rng = np.random.default_rng(self.random_state)
        runs = []
        for r in range(self.n_restarts):
            run = copy.deepcopy(self)
            # run 0 is the single-run fit (k-means best of n_init); later runs: one k-means run each
            run.initialize(sequences, rng=rng, n_init=self.n_init if r == 0 else 1)
            run._baum_welch(x, mask)
            run.restart_objectives = [run._objective(x, mask)]
            runs.append(run)
        return runs

    def _baum_welch(self, x: np.ndarray, mask: np.ndarray) -> None:
        self.log_likelihood_history, self.objective_history = [], []
        for _ in range(self.max_iter):
            prior = self._log_prior()
            ll = self._em_step(x, mask)
            self.log_likelihood_history.append(ll)
            self.objective_history.append(ll + prior)
            hist = self.log_likelihood_history
            if len(hist) >= 2 and abs(hist[-1] - hist[-2]) < self.tol:
                break

    def _objective(self, x: np.ndarray, mask: np.ndarray) -> float:
        """``log p(O | Lambda) + log p(Sigma)`` of the current parameters (the histories hold the values
        before each update)."""
        return float(self._forward_backward(x, mask, backward=False)[4].sum()) + self._log_prior()

    def _check_count(self, mask: np.ndarray) -> None:
        if mask.sum() < self.n_states:
            raise ValueError(f"{mask.sum()} observations cannot train {self.n_states} states")

    def sample(self, length: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Draw one sequence of ``length`` observations; returns (observations (T, D), states (T,))."""
        self._require_fitted()
        states = np.empty(length, dtype=np.int64)
        states[0] = rng.choice(self.n_states, p=self.start_prob)
        for t in range(1, length):
            states[t] = rng.choice(self.n_states, p=self.transition[states[t - 1]])
        chol = np.linalg.cholesky(self.covariances)
        noise = rng.standard_normal((length, self.n_features))
        obs = self.means[states] + np.einsum("tij,tj->ti", chol[states], noise)
        return obs, states
