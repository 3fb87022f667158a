"""Learning from demonstration (thesis ch. 5): Gaussian HMM, GMR with forward-variable weights, features."""

import itertools

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import multivariate_normal

from defgraspnets.tactile.contour_sim import indented_points
from defgraspnets.tactile.lfd.features import (
    FEATURE_SIZES,
    MinMaxNormalizer,
    demonstration_observations,
    end_effector_velocity,
    feature_matrix,
    orient_principal_vectors,
    tactile_features,
)
from defgraspnets.tactile.lfd.gmr import ForwardGMR, GaussianMixtureRegression
from defgraspnets.tactile.lfd.hmm import GaussianHMM, kmeans


def true_hmm() -> GaussianHMM:
    cov = np.array([[[0.3, 0.1], [0.1, 0.2]], [[0.2, -0.05], [-0.05, 0.3]], [[0.25, 0.0], [0.0, 0.25]]])
    return GaussianHMM(3).set_parameters(
        [0.6, 0.3, 0.1],
        [[0.90, 0.08, 0.02], [0.05, 0.90, 0.05], [0.03, 0.07, 0.90]],
        [[0.0, 0.0], [3.0, 1.0], [-1.0, 3.0]],
        cov,
    )


def demos(model, lengths, seed=0):
    rng = np.random.default_rng(seed)
    return [model.sample(t, rng)[0] for t in lengths]


# ----------------------------------------------------------------------------- HMM


def brute_force(model: GaussianHMM, x: np.ndarray):
    """Enumerate every state path: log p(O), filtered p(Q_t | o_1..t) and the best path."""
    n, t_len = model.n_states, x.shape[0]
    b = np.column_stack([multivariate_normal(model.means[i], model.covariances[i]).pdf(x) for i in range(n)])
    joint = {}
    for path in itertools.product(range(n), repeat=t_len):
        p = model.start_prob[path[0]] * b[0, path[0]]
        for t in range(1, t_len):
            p *= model.transition[path[t - 1], path[t]] * b[t, path[t]]
        joint[path] = p
    total = sum(joint.values())
    filtered = np.zeros((t_len, n))
    for t in range(t_len):
        # alpha_i(t) = sum over prefixes ending in i of p(o_1..t, path_1..t)
        for prefix in itertools.product(range(n), repeat=t + 1):
            p = model.start_prob[prefix[0]] * b[0, prefix[0]]
            for k in range(1, t + 1):
                p *= model.transition[prefix[k - 1], prefix[k]] * b[k, prefix[k]]
            filtered[t, prefix[-1]] += p
        filtered[t] /= filtered[t].sum()
    best = max(joint, key=joint.get)
    return np.log(total), filtered, np.array(best), np.log(joint[best])


def test_forward_variables_and_viterbi_match_path_enumeration():
    model = true_hmm()
    x = demos(model, [5], seed=3)[0]
    log_p, filtered, best, best_lp = brute_force(model, x)
    alpha, ll = model.forward_variables(x)
    assert ll == pytest.approx(log_p, rel=1e-10)
    assert model.score([x]) == pytest.approx(log_p, rel=1e-10)
    assert np.allclose(alpha, filtered, atol=1e-12)
    path, lp = model.viterbi(x)
    assert np.array_equal(path, best) and lp == pytest.approx(best_lp, rel=1e-10)
    gamma = model.posteriors(x)
    assert np.allclose(gamma.sum(axis=1), 1.0) and np.allclose(gamma[-1], alpha[-1])


def test_forward_is_stable_for_long_sequences():
    model = true_hmm()
    x = demos(model, [5000], seed=1)[0] * 3.0  # far-out observations: densities underflow in linear space
    alpha, ll = model.forward_variables(x)
    assert np.isfinite(ll) and np.isfinite(alpha).all()
    assert np.allclose(alpha.sum(axis=1), 1.0)


def test_baum_welch_log_likelihood_never_decreases_and_recovers_the_model():
    truth = true_hmm()
    data = demos(truth, [150, 220, 180, 200, 170], seed=0)
    model = GaussianHMM(3, covariance_regularization=0.0, max_iter=60, tol=0.0, random_state=0).fit(data)
    hist = np.array(model.log_likelihood_history)
    assert hist.size == 60
    assert (np.diff(hist) >= -1e-9 * np.abs(hist[1:])).all()
    assert hist[-1] > hist[0] + 1.0
    order = [int(np.argmin(np.linalg.norm(model.means - m, axis=1))) for m in truth.means]
    assert sorted(order) == [0, 1, 2]
    assert np.allclose(model.means[order], truth.means, atol=0.15)
    assert np.allclose(model.transition[np.ix_(order, order)], truth.transition, atol=0.05)
    assert np.allclose(model.covariances[order], truth.covariances, atol=0.06)
    assert model.score(data) >= truth.score(data)  # the MLE fits its own data at least as well


def test_regularized_em_objective_never_decreases_on_degenerate_features():
    rng = np.random.default_rng(4)
    # a constant feature (like the no-contact defaults) makes plain ML covariances singular
    seqs = [
        np.column_stack([rng.normal(size=80), np.zeros(80), rng.normal(size=80) + (np.arange(80) > 40) * 4])
        for _ in range(3)
    ]
    with pytest.raises(ValueError, match="singular"):
        GaussianHMM(2, covariance_regularization=0.0, random_state=0).fit(seqs)
    model = GaussianHMM(2, covariance_regularization=1e-3, max_iter=40, tol=0.0, random_state=0).fit(seqs)
    obj = np.array(model.objective_history)
    assert (np.diff(obj) >= -1e-9 * np.abs(obj[1:])).all()
    assert (np.linalg.eigvalsh(model.covariances) > 0).all()


def test_restarts_keep_the_best_baum_welch_run_and_never_fit_worse_than_one_run():
    # an over-complete model (5 states on 3-state data) has many local maxima of the likelihood
    data = demos(true_hmm(), [60, 80, 70], seed=3)
    single = GaussianHMM(5, covariance_regularization=1e-3, random_state=3).fit(data)
    multi = GaussianHMM(5, covariance_regularization=1e-3, random_state=3, n_restarts=8).fit(data)
    objectives = np.array(multi.restart_objectives)
    assert objectives.size == 8 and len(single.restart_objectives) == 1
    # run 0 is the single-run fit; the kept parameters are those of the best run
    assert objectives[0] == pytest.approx(single.restart_objectives[0], rel=1e-12)
    assert multi.score(data) + multi._log_prior() == pytest.approx(objectives.max(), rel=1e-12)
    assert objectives.max() >= objectives[0]
    assert objectives.max() > single.score(data) + single._log_prior() + 5.0  # measured: -339.2 vs -350.3
    assert multi.objective_history[-1] <= objectives.max() + 1e-9  # histories are those of the kept run
    with pytest.raises(ValueError, match="n_restarts"):
        GaussianHMM(2, n_restarts=0)


def test_baum_welch_matches_hmmlearn_from_the_same_initialization():
    hmm = pytest.importorskip("hmmlearn.hmm", reason="hmmlearn (test-only reference) is not installed")
    truth = true_hmm()
    data = demos(truth, [120, 90, 150, 100], seed=7)
    psi, n_iter = 1e-2, 12
    ours = GaussianHMM(3, covariance_regularization=psi, max_iter=n_iter, tol=-np.inf, random_state=0)
    ours.initialize(data)
    init = (ours.start_prob.copy(), ours.transition.copy(), ours.means.copy(), ours.covariances.copy())
    ours.fit(data, initialize=False)

    ref = hmm.GaussianHMM(
        n_components=3,
        covariance_type="full",
        n_iter=n_iter,
        tol=-np.inf,
        init_params="",
        params="stmc",
        covars_prior=psi * np.eye(2),
        covars_weight=1,
    )
    ref.startprob_, ref.transmat_, ref.means_, ref.covars_ = init
    ref.fit(np.concatenate(data), lengths=[len(d) for d in data])

    assert np.allclose(ours.log_likelihood_history, list(ref.monitor_.history), rtol=1e-9)
    assert np.allclose(ours.start_prob, ref.startprob_, atol=1e-8)
    assert np.allclose(ours.transition, ref.transmat_, atol=1e-8)
    assert np.allclose(ours.means, ref.means_, atol=1e-8)
    assert np.allclose(ours.covariances, ref.covars_, atol=1e-8)
    assert ours.score(data) == pytest.approx(
        ref.score(np.concatenate(data), [len(d) for d in data]), rel=1e-10
    )


def test_kmeans_and_input_validation():
    rng = np.random.default_rng(0)
    centres = np.array([[0.0, 0.0], [5.0, 0.0], [0.0, 5.0]])
    pts = np.concatenate([c + 0.1 * rng.normal(size=(50, 2)) for c in centres])
    found = kmeans(pts, 3, rng)
    assert np.sort(np.linalg.norm(found[:, None] - centres[None], axis=2).min(axis=0)).max() < 0.1
    with pytest.raises(ValueError, match="same D"):
        GaussianHMM(2).fit([np.zeros((5, 2)), np.zeros((5, 3))])
    with pytest.raises(ValueError, match="non-finite"):
        GaussianHMM(2).fit([np.full((5, 2), np.nan)])
    with pytest.raises(RuntimeError, match="no parameters"):
        GaussianHMM(2).score([np.zeros((3, 2))])


# ----------------------------------------------------------------------------- GMR


def test_gmr_reproduces_a_linear_mapping():
    rng = np.random.default_rng(5)
    w, b = np.array([[1.5, -0.5], [0.3, 2.0]]), np.array([0.2, -0.1])
    # a single joint Gaussian: GMR is exactly the linear least-squares regression
    s = rng.normal(size=(2000, 2)) @ np.array([[1.0, 0.4], [0.0, 0.7]])
    a = s @ w.T + b + 0.01 * rng.normal(size=(2000, 2))
    joint = np.hstack([s, a])
    gmr = GaussianMixtureRegression(
        [1.0], joint.mean(0)[None], np.cov(joint.T, bias=True)[None], [0, 1], [2, 3]
    )
    test_s = rng.normal(size=(50, 2))
    pred = gmr.predict(test_s)
    assert np.allclose(pred.action, test_s @ w.T + b, atol=0.01)
    assert np.allclose(pred.covariance, 1e-4 * np.eye(2), atol=3e-5)  # the residual noise variance

    # an HMM over sequences that visit three input regions: every state carries the same map
    def sequence(n):
        centres = np.array([[-2.0, 0.0], [0.0, 2.0], [2.0, 0.0]])
        s = np.concatenate([c + 0.4 * rng.normal(size=(n, 2)) for c in centres])
        return np.hstack([s, s @ w.T + b + 0.01 * rng.normal(size=s.shape)])

    model = GaussianHMM(3, covariance_regularization=1e-6, random_state=0).fit(
        [sequence(40) for _ in range(4)]
    )
    test = sequence(20)
    forward = ForwardGMR.from_hmm(model, [0, 1], [2, 3]).predict(test[:, :2])
    assert np.abs(forward.action - test[:, :2] @ w.T - b).max() < 0.06
    assert np.allclose(forward.weights.sum(axis=1), 1.0)


def test_forward_weights_follow_eqs_5_17_and_5_18():
    model = true_hmm()
    rng = np.random.default_rng(2)
    # treat dim 0 as input, dim 1 as output
    gmr = ForwardGMR.from_hmm(model, [0], [1])
    s = rng.normal(size=(6, 1)) * 2
    pred = gmr.predict(s)
    dens = np.column_stack(
        [multivariate_normal(model.means[i, :1], model.covariances[i, :1, :1]).pdf(s) for i in range(3)]
    )
    h = model.start_prob * dens[0]
    h /= h.sum()  # (5.18)
    assert np.allclose(pred.weights[0], h)
    for t in range(1, 6):
        h = dens[t] * (h @ model.transition)
        h /= h.sum()  # (5.17)
        assert np.allclose(pred.weights[t], h)
    local = model.means[:, 1] + model.covariances[:, 1, 0] / model.covariances[:, 0, 0] * (
        s[-1, 0] - model.means[:, 0]
    )
    assert pred.action[-1, 0] == pytest.approx(h @ local)
    # online execution gives the same as batch prediction, and reset restarts at eq. (5.18)
    gmr.reset()
    online = np.array([gmr.step(x)[0] for x in s])
    assert np.allclose(online, pred.action)
    gmr.reset()
    assert np.allclose(gmr.step(s[0])[0], pred.action[0])
    with pytest.raises(ValueError, match="overlap"):
        ForwardGMR.from_hmm(model, [0], [0])


# ----------------------------------------------------------------------------- features


def pose(rotation: np.ndarray, position) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = rotation
    t[:3, 3] = position
    return t


def test_features_of_an_elongated_contact_in_the_world_frame():
    rng = np.random.default_rng(0)
    local = rng.normal(size=(3000, 3)) * [0.02, 0.005, 0.001] + [0.0, 0.0, 0.07]
    rot = Rotation.from_euler("zyx", [30, 10, 180], degrees=True).as_matrix()
    t = pose(rot, [0.4, -0.2, 0.5])
    f = tactile_features(local, t)
    assert f.in_contact and f.n_points == 3000
    assert f.centroid == pytest.approx(rot @ local.mean(0) + [0.4, -0.2, 0.5])
    assert f.principal_variances == pytest.approx([0.02**2, 0.005**2, 0.001**2], rel=0.1)
    assert np.all(np.diff(f.principal_variances) <= 0)
    assert abs(f.e1 @ rot[:, 0]) > 0.999  # the long axis, rotated into the world frame
    assert np.allclose(f.principal_vectors @ f.principal_vectors.T, np.eye(3), atol=1e-9)
    # sign convention: the largest-magnitude element of each principal vector is positive
    for v in f.principal_vectors:
        assert v[np.argmax(np.abs(v))] > 0
    # invariance to the arbitrary sign of the eigen-solver
    g = tactile_features(local[::-1].copy(), t)
    assert np.allclose(g.principal_vectors, f.principal_vectors)
    assert f.vector(("principal_variances", "e1")).shape == (6,)
    assert f.vector().shape == (9,)
    assert sum(FEATURE_SIZES.values()) == 15
    assert orient_principal_vectors(np.array([0.1, -0.9, 0.2])) == pytest.approx([-0.1, 0.9, -0.2])


def test_uniform_weights_give_the_unweighted_features_and_bad_weights_are_rejected():
    rng = np.random.default_rng(1)
    local = rng.normal(size=(500, 3)) * [0.02, 0.005, 0.001] + [0.0, 0.0, 0.07]
    t = pose(Rotation.from_euler("zyx", [-40, 5, 180], degrees=True).as_matrix(), [0.1, 0.0, 0.3])
    f = tactile_features(local, t)
    for w in (np.ones(500), np.full(500, 3.7)):  # the scale of the weights does not matter
        g = tactile_features(local, t, weights=w)
        assert g.in_contact and g.n_points == 500
        np.testing.assert_allclose(g.centroid, f.centroid, rtol=0, atol=1e-15)
        np.testing.assert_allclose(g.principal_variances, f.principal_variances, rtol=1e-12, atol=1e-20)
        np.testing.assert_allclose(g.principal_vectors, f.principal_vectors, rtol=0, atol=1e-12)
    # weights move the centroid toward the heavy points (weighted mean)
    w = np.where(local[:, 0] > 0, 1.0, 0.0)
    g = tactile_features(local, t, weights=w)
    np.testing.assert_allclose(g.centroid, t[:3, :3] @ local[w > 0].mean(0) + t[:3, 3], atol=1e-12)
    assert not tactile_features(local, t, weights=np.zeros(500)).in_contact  # no weight: no contact
    for bad in (np.ones(499), -np.ones(500), np.full(500, np.nan)):
        with pytest.raises(ValueError, match="weights"):
            tactile_features(local, t, weights=bad)


def _synthetic_core_yaw(yaw_deg: float, weighted: bool) -> float:
    """e1 angle [deg] of an elliptic-paraboloid indentation (24 x 16 mm at the rim, 5 mm deep) rotated by
    ``yaw_deg``, seen on a fixed 2 mm pixel grid; the contact core is the pixels indented > 0.7 x the
    deepest (as the LfD sensor), weighted by their indentation beyond that cut or counted once."""
    g = np.arange(-0.02, 0.02 + 1e-9, 0.002)
    x, y = np.meshgrid(g, g)
    th = np.deg2rad(yaw_deg)
    u, v = np.cos(th) * x + np.sin(th) * y, -np.sin(th) * x + np.cos(th) * y
    ind = 0.005 * np.clip(1.0 - (u / 0.012) ** 2 - (v / 0.008) ** 2, 0.0, None)
    ref = np.full(x.shape, 0.05)
    pts, excess = indented_points(np.dstack([x, y, ref - ind]), ref - ind, ref, 1e-3, 0.7, return_excess=True)
    e1 = tactile_features(pts, np.eye(4), weights=excess if weighted else None).e1
    return float((np.rad2deg(np.arctan2(e1[1], e1[0])) + 90.0) % 180.0 - 90.0)


def test_depth_weighted_e1_follows_a_rotating_indentation_continuously():
    yaws = np.arange(0.0, 10.01, 0.25)
    counted = np.array([_synthetic_core_yaw(y, False) for y in yaws])
    weighted = np.array([_synthetic_core_yaw(y, True) for y in yaws])
    # counted once, the core's outline follows the pixels: e1 reads the yaw in steps (a staircase)
    assert len(np.unique(np.round(counted, 3))) <= 5
    assert np.abs(counted - yaws).max() > 3.0
    # weighted by the indentation beyond the cut (0 at the outline), e1 turns with the indentation
    assert np.all(np.diff(weighted) > 0.05)
    assert np.abs(weighted - yaws).max() < 1.5


def test_no_contact_defaults_are_the_camera_frame_in_the_world():
    rot = Rotation.from_euler("xyz", [180, 0, 45], degrees=True).as_matrix()
    t = pose(rot, [0.1, 0.2, 0.3])
    for pts in (np.zeros((0, 3)), np.ones((2, 3))):  # empty, or fewer than min_points
        f = tactile_features(pts, t)
        assert not f.in_contact
        assert f.centroid == pytest.approx([0.1, 0.2, 0.3])
        assert f.principal_variances == pytest.approx(np.zeros(3))
        assert np.allclose(f.principal_vectors, rot.T)  # rows: camera x, y, z axes in the world
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        tactile_features(np.zeros((3, 2)), t)
    with pytest.raises(ValueError, match="rotation"):
        tactile_features(np.zeros((0, 3)), np.diag([1.0, 1.0, 2.0, 1.0]))


def test_velocity_actions_and_min_max_normalization():
    dt = 0.2
    poses = np.stack(
        [
            pose(Rotation.from_rotvec([0, 0, 0.1 * k]).as_matrix(), [0.01 * k, 0.0, -0.02 * k])
            for k in range(5)
        ]
    )
    vel = end_effector_velocity(poses, dt)
    assert vel.shape == (4, 6)
    assert np.allclose(vel, [[0.05, 0.0, -0.1, 0.0, 0.0, 0.5]] * 4)
    obs = demonstration_observations(np.arange(10.0).reshape(5, 2), poses, dt)
    assert obs.shape == (4, 8) and np.allclose(obs[:, :2], np.arange(8.0).reshape(4, 2))
    data = np.array([[0.0, 5.0, 1.0], [2.0, 5.0, 3.0], [1.0, 5.0, 2.0]])
    norm = MinMaxNormalizer.fit(data)
    x = norm.transform(data)
    assert x.min(0) == pytest.approx([0.0, 0.0, 0.0]) and x.max(0) == pytest.approx([1.0, 0.0, 1.0])
    assert norm.inverse_transform(x) == pytest.approx(data)
    again = MinMaxNormalizer.from_dict(norm.to_dict())
    assert again.transform([1.0, 5.0, 2.0]) == pytest.approx([0.5, 0.0, 0.5])


def test_edge_following_pipeline_generalizes_to_a_new_edge_direction():
    """§5.4 in miniature: lower until contact, then slide along the edge (y > 0 by convention)."""
    rng = np.random.default_rng(11)
    cam = np.diag([1.0, -1.0, -1.0])  # looking down
    speed = 0.01

    def demonstration(edge_yaw):
        e = np.array([np.cos(edge_yaw), np.sin(edge_yaw), 0.0])
        feats, actions = [], []
        for k in range(30):
            if k < 12:  # lowering, no contact: default features, action -z
                pts = np.zeros((0, 3))
                act = [0.0, 0.0, -speed]
            else:  # contact: an elongated patch along the edge, action along e1 with positive y
                pts = (
                    np.outer(rng.normal(size=400) * 0.015, cam.T @ e)
                    + rng.normal(size=(400, 3)) * 0.002
                    + [0.0, 0.0, 0.07]
                )
                act = list(speed * e)
            f = tactile_features(pts, pose(cam, [0.0, 0.0, 0.3]))
            feats.append(f.vector(("principal_variances", "e1")))
            actions.append(np.array(act) + 1e-4 * rng.normal(size=3))
        return np.hstack([np.array(feats), np.array(actions)])

    train = [demonstration(y) for y in np.radians([60, 75, 90, 105, 120, 70])]
    norm = MinMaxNormalizer.fit(np.concatenate(train))
    model = GaussianHMM(2, covariance_regularization=1e-3, random_state=0).fit(
        [norm.transform(d) for d in train]
    )
    test = norm.transform(
        demonstration(np.radians(40))
    )  # an edge direction outside the demonstrated 60-120 deg
    pred = ForwardGMR.from_hmm(model, range(6), range(6, 9)).predict(test[:, :6])
    action = norm.inverse_transform(np.hstack([test[:, :6], pred.action]))[:, 6:]
    assert np.allclose(action[:12], [0.0, 0.0, -speed], atol=1e-3)  # lowers while not in contact
    e = np.array([np.cos(np.radians(40)), np.sin(np.radians(40)), 0.0])
    cos = action[12:] @ e / np.linalg.norm(action[12:], axis=1)
    assert cos.min() > 0.9  # follows the unseen edge
    assert pred.weights[:12].argmax(1).tolist() == [pred.weights[0].argmax()] * 12
    assert pred.weights[12:].argmax(1).min() == pred.weights[12:].argmax(1).max() != pred.weights[0].argmax()
    assert np.allclose(feature_matrix([tactile_features(np.zeros((0, 3)), np.eye(4))], ("e1",)), [[1, 0, 0]])
