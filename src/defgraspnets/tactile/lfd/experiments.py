"""Learning-from-demonstration experiments in simulation (thesis §5.4 edge following).

Edge following (§5.4): the *teacher* is the contour-following controller of ch. 4
(:func:`defgraspnets.tactile.contour_sim.run_contour_following`) on a straight 0.5" pipe in several
poses; it lowers onto the pipe (search phase) and slides along it in the direction of positive world y
(the thesis's convention). Each demonstration step gives the §5.3 input ``S = [lambda_1..3, e_1]`` of the
deformed cloud (world frame) and the action ``A = [v, omega]`` between consecutive poses
(:func:`~defgraspnets.tactile.lfd.features.demonstration_observations`, dt = 1 s). All observations are
min-max normalized (:class:`~defgraspnets.tactile.lfd.features.MinMaxNormalizer`), a 2-state
:class:`~defgraspnets.tactile.lfd.hmm.GaussianHMM` is fitted (Baum-Welch), and the policy is
:class:`~defgraspnets.tactile.lfd.gmr.ForwardGMR` (eqs 5.17-5.18). The rollout executes the predicted
twist for dt on a curved 3-D pipe the teacher never showed; success = contact kept after first contact,
no rigid-housing contact, and progress along the pipe at close to the teacher's speed.

The policy can only be as straight as its teacher. With the whole 1 mm-deformed dome as the cloud, the
teacher's edge tangent swapped between the pipe axis and its perpendicular (see
:mod:`defgraspnets.tactile.contour_sim`): its steps were 10 mm long but zig-zagged, so the contact
state's mean velocity — what GMR returns — was only ~2.8 mm/step and the rollout crawled (~5 cm in 60
steps). On the contact core (``TactileSimulation.core_fraction``) the demonstrations are straight, the
contact state's mean velocity is ~9.4 mm/step and the rollout covers ~0.55 m of the curved pipe in 60 steps.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from defgraspnets.tactile.contour import ContourParameters
from defgraspnets.tactile.contour_sim import (
    ContourScene,
    TactileSimulation,
    curved_pipe_scene,
    path_progress,
    pole_height,
    run_contour_following,
    straight_pipe_scene,
)
from defgraspnets.tactile.lfd.features import MinMaxNormalizer, demonstration_observations, tactile_features
from defgraspnets.tactile.lfd.gmr import ForwardGMR
from defgraspnets.tactile.lfd.hmm import GaussianHMM

__all__ = [
    "EDGE_FEATURES",
    "DEMONSTRATION_PIPE_POSES",
    "Demonstration",
    "EdgeFollowingPolicy",
    "PolicyRollout",
    "demonstration_action_error",
    "edge_following_demonstrations",
    "fit_edge_following_policy",
    "rollout_policy",
]

#: §5.4: principal variances and the first principal vector (the centroid is not task relevant).
EDGE_FEATURES = ("principal_variances", "e1")

#: Six straight-pipe poses of the demonstrations: (origin [m], yaw [rad] about z, pitch [rad] about x);
#: all traverse with a positive world-y component.
DEMONSTRATION_PIPE_POSES = (
    ((0.0, 0.0, 0.0), 0.0, 0.0),
    ((0.05, -0.02, 0.03), np.deg2rad(20.0), 0.0),
    ((-0.04, 0.03, -0.02), np.deg2rad(-25.0), 0.0),
    ((0.02, 0.0, 0.05), np.deg2rad(10.0), np.deg2rad(8.0)),
    ((-0.03, -0.04, 0.0), np.deg2rad(-10.0), np.deg2rad(-8.0)),
    ((0.0, 0.05, -0.04), np.deg2rad(30.0), np.deg2rad(5.0)),
)


@dataclass(frozen=True)
class Demonstration:
    """One demonstration: inputs (T, D), poses (T, 4, 4), contact flags (T,), observations (T-1, D+6)."""

    inputs: np.ndarray
    poses: np.ndarray
    in_contact: np.ndarray
    observations: np.ndarray


def _inputs(
    sim: TactileSimulation, scene: ContourScene, poses: np.ndarray, features
) -> tuple[np.ndarray, np.ndarray]:
    rows, contact = [], []
    for pose in poses:
        obs = sim.observe(scene.sdf, pose)
        rows.append(tactile_features(obs.points, pose, weights=obs.weights).vector(features))
        contact.append(obs.in_contact)
    return np.array(rows), np.array(contact, dtype=bool)


def edge_following_demonstrations(
    sim: TactileSimulation,
    teacher: ContourParameters,
    poses=DEMONSTRATION_PIPE_POSES,
    steps: int = 25,
    dt: float = 1.0,
    features=EDGE_FEATURES,
) -> list[Demonstration]:
    """Teacher runs on the straight pipe in each pose; returns the demonstrations with their §5.3 inputs."""
    if len(poses) < 1:
        raise ValueError("need at least one demonstration pose")
    demos = []
    h = pole_height(sim)
    for origin, yaw, pitch in poses:
        scene = straight_pipe_scene(h, origin=origin, yaw=yaw, pitch=pitch, steps=steps)
        if scene.travel_direction[1] <= 0:
            raise ValueError("demonstrations must traverse with a positive world-y component")
        run = run_contour_following(sim, scene, teacher)
        if run.stopped_early or run.metrics.housing_contact_steps:
            raise RuntimeError(
                f"the teacher failed on the pipe at {origin}, yaw {yaw:.2f}: {run.stopped_early}"
            )
        inputs, contact = _inputs(sim, scene, run.poses, features)
        demos.append(
            Demonstration(inputs, run.poses, contact, demonstration_observations(inputs, run.poses, dt))
        )
    return demos


@dataclass
class EdgeFollowingPolicy:
    """The learned policy: normalizer over ``[S, A]``, HMM and its forward-variable GMR."""

    normalizer: MinMaxNormalizer
    hmm: GaussianHMM
    gmr: ForwardGMR
    input_size: int
    dt: float = 1.0

    def reset(self) -> None:
        self.gmr.reset()

    def action(self, sensor_input) -> np.ndarray:
        """World twist ``[v, omega]`` (6,) [m/s, rad/s] for one raw input S."""
        s = np.asarray(sensor_input, dtype=np.float64)
        if s.shape != (self.input_size,):
            raise ValueError(f"sensor input must have shape ({self.input_size},), got {s.shape}")
        full = np.concatenate([s, np.zeros(6)])
        normalized = self.normalizer.transform(full)[: self.input_size]
        a, _ = self.gmr.step(normalized)
        full[self.input_size :] = a
        return self.normalizer.inverse_transform(full)[self.input_size :]


def demonstration_action_error(hmm: GaussianHMM, sequences, input_size: int) -> float:
    """How well the GMRa policy of ``hmm`` replays the demonstrations (training data only).

    Each normalized demonstration ``[S, A]`` (T, D) of ``sequences`` is replayed from a fresh start: the
    forward-variable GMR (eqs 5.17-5.18) predicts the actions from its inputs. Returns the squared action
    error summed over the action dimensions, averaged over the steps and then over the demonstrations.
    """
    gmr = ForwardGMR.from_hmm(hmm, list(range(input_size)), list(range(input_size, hmm.n_features)))
    errors = [
        float(((gmr.predict(x[:, :input_size]).action - x[:, input_size:]) ** 2).sum(axis=1).mean())
        for x in sequences
    ]
    return float(np.mean(errors))


def fit_edge_following_policy(
    demonstrations: list[Demonstration],
    n_states: int = 2,
    regularization: float = 1e-3,
    seed: int = 0,
    dt: float = 1.0,
    n_restarts: int = 1,
) -> EdgeFollowingPolicy:
    """Normalize the demonstrations, fit the N-state HMM (Baum-Welch) and build the GMRa policy.

    ``n_restarts > 1``: Baum-Welch from that many k-means initializations
    (:meth:`~defgraspnets.tactile.lfd.hmm.GaussianHMM.fit_restarts`, run 0 is the single-run fit), keeping
    the run whose policy best replays the demonstrated actions (:func:`demonstration_action_error`). EM
    only finds local maxima, and the joint likelihood is dominated by the 9-D input density, so it does not
    rank the policies: on the mixed-manipulation demonstrations the highest-likelihood run is no better
    than a single run, while the best-replaying one separates the capsule and prism contact states.
    """
    if len(demonstrations) < 1:
        raise ValueError("need at least one demonstration")
    data = [d.observations for d in demonstrations]
    normalizer = MinMaxNormalizer.fit(np.concatenate(data))
    sequences = [normalizer.transform(x) for x in data]
    d_in = demonstrations[0].inputs.shape[1]
    hmm = GaussianHMM(
        n_states, covariance_regularization=regularization, random_state=seed, n_restarts=n_restarts
    )
    if n_restarts == 1:
        hmm.fit(sequences)
    else:
        runs = hmm.fit_restarts(sequences)
        hmm = runs[int(np.argmin([demonstration_action_error(h, sequences, d_in) for h in runs]))]
    gmr = ForwardGMR.from_hmm(hmm, list(range(d_in)), list(range(d_in, d_in + 6)))
    return EdgeFollowingPolicy(normalizer, hmm, gmr, d_in, dt)


@dataclass(frozen=True)
class PolicyRollout:
    """A policy execution: poses (T, 4, 4), contact, housing contact (T,), inputs (T, D), weights (T, N)."""

    poses: np.ndarray
    in_contact: np.ndarray
    housing_contact: np.ndarray
    inputs: np.ndarray
    weights: np.ndarray

    @property
    def contact_fraction(self) -> float:
        """Fraction of steps in contact from the first contact on (0 if never in contact)."""
        c = self.in_contact
        return float(c[np.argmax(c) :].mean()) if c.any() else 0.0

    def pole_positions(self, height: float) -> np.ndarray:
        """(T, 3) world positions of the membrane pole (sensor-frame ``(0, 0, height)``)."""
        return self.poses[:, :3, :3] @ np.array([0.0, 0.0, float(height)]) + self.poses[:, :3, 3]

    def distance_along(self, direction) -> float:
        d = np.asarray(direction, dtype=np.float64)
        return float((self.poses[-1, :3, 3] - self.poses[0, :3, 3]) @ (d / np.linalg.norm(d)))


def rollout_policy(
    sim: TactileSimulation, policy: EdgeFollowingPolicy, scene: ContourScene, steps: int | None = None,
    features=EDGE_FEATURES, max_displacement: float = 0.03,
) -> PolicyRollout:  # fmt: skip
    """Execute the policy on ``scene`` from its start pose: observe, predict ``[v, omega]``, move for dt."""
    pose = np.asarray(scene.start_pose, dtype=np.float64).copy()
    n = scene.steps if steps is None else int(steps)
    policy.reset()
    log = {k: [] for k in ("pose", "contact", "housing", "input", "weights")}
    for _ in range(n):
        obs = sim.observe(scene.sdf, pose)
        s = tactile_features(obs.points, pose, weights=obs.weights).vector(features)
        twist = policy.action(s)
        log["pose"].append(pose.copy())
        log["contact"].append(obs.in_contact)
        log["housing"].append(obs.housing_contact)
        log["input"].append(s)
        log["weights"].append(policy.gmr.weights)
        if obs.state.max_displacement > max_displacement:
            break
        pose = pose.copy()
        pose[:3, 3] += twist[:3] * policy.dt
        pose[:3, :3] = Rotation.from_rotvec(twist[3:] * policy.dt).as_matrix() @ pose[:3, :3]
    return PolicyRollout(
        np.array(log["pose"]), np.array(log["contact"], dtype=bool), np.array(log["housing"], dtype=bool),
        np.array(log["input"]), np.array(log["weights"]),
    )  # fmt: skip


def edge_following_experiment(
    sim: TactileSimulation,
    teacher: ContourParameters,
    steps: int = 25,
    rollout_steps: int = 60,
    seed: int = 0,
) -> dict:
    """Demonstrate on the straight pipe (6 poses), learn (2-state HMM), roll out on the curved pipe.

    Returns the ``demonstrations``, the ``policy``, the ``rollout``, its ``scene``, the membrane pole's
    ``height`` above the sensor origin [m] and a JSON-ready ``report``."""
    demos = edge_following_demonstrations(sim, teacher, steps=steps)
    policy = fit_edge_following_policy(demos, seed=seed)
    height = pole_height(sim)
    scene = curved_pipe_scene(height, steps=rollout_steps)
    rollout = rollout_policy(sim, policy, scene)
    s = path_progress(scene.path, rollout.pole_positions(height))
    contact = rollout.in_contact
    first = int(np.argmax(contact)) if contact.any() else None
    steps_len = np.linalg.norm(np.diff(rollout.poses[:, :3, 3], axis=0), axis=1)
    # mean velocity of each HMM state in world units (m per dt) from the de-normalized state means
    d_in = policy.input_size
    state_means = policy.normalizer.inverse_transform(policy.hmm.means)[:, d_in : d_in + 3]
    return {
        "demonstrations": demos,
        "policy": policy,
        "rollout": rollout,
        "scene": scene,
        "height": height,
        "report": {
            "n_demonstrations": len(demos),
            "demonstration_contact_fraction": [
                float(d.in_contact[np.argmax(d.in_contact) :].mean()) for d in demos
            ],
            "hmm_states": policy.hmm.n_states,
            "hmm_log_likelihood": policy.hmm.log_likelihood_history[-1]
            if policy.hmm.log_likelihood_history
            else None,
            "rollout_steps": int(len(rollout.in_contact)),
            "rollout_first_contact_step": int(np.argmax(rollout.in_contact))
            if rollout.in_contact.any()
            else None,
            "rollout_contact_fraction": rollout.contact_fraction,
            "rollout_housing_contact_steps": int(rollout.housing_contact.sum()),
            "rollout_distance_along_y_m": rollout.distance_along((0.0, 1.0, 0.0)),
            "rollout_distance_along_pipe_m": float(s[-1] - s[0]),
            "rollout_pipe_progress_per_contact_step_m": float((s[-1] - s[first]) / max(len(s) - 1 - first, 1))
            if first is not None
            else None,
            "rollout_mean_step_m": float(steps_len.mean()) if steps_len.size else 0.0,
            "teacher_step_m": float(teacher.tracking_step),
            "hmm_state_mean_speed_m_per_step": (np.linalg.norm(state_means, axis=1) * policy.dt).tolist(),
        },
    }
