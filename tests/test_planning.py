"""Grasp planning: objectives, pose coordinates, gradients against finite differences, scoring, refinement,
FEM verification, and the plan_grasps entry point."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation
from test_data_synthetic import make_shards
from test_predictor import fit_and_save

from defgraspnets.data.datamodule import GraspDataModule
from defgraspnets.grasp.datagen import structured_box
from defgraspnets.grasp.gripper import FRANKA_HAND
from defgraspnets.grasp.metrics import rigid_removed_deformation
from defgraspnets.grasp.sampler import sample_antipodal_grasps
from defgraspnets.models.defgraspnets_module import DefGraspNetsModule
from defgraspnets.models.meshgraphnet import DefGraspNet
from defgraspnets.models.predictor import DefGraspNetsPredictor
from defgraspnets.planning import (
    PRESETS,
    GraspObjective,
    GraspPlanner,
    GraspPoses,
    perturb_pose,
    rotation_exp,
    simulate_grasps,
    smooth_max,
    threshold_hits,
)
from defgraspnets.planning.timing import StageTimer

ROOT = Path(__file__).resolve().parents[1]


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("plan")
    dm = GraspDataModule(
        str(make_shards(root / "grasps", grasps=3, num_steps=2, with_real=False)),
        batch_size=2,
        statistics_samples=8,
        contact_radius=0.005,
    )
    dm.setup()
    return root, dm


@pytest.fixture(scope="module")
def predictor64(data):
    """A small untrained network with fitted normalization statistics, in float64 (gradient checks)."""
    torch.manual_seed(0)
    net = DefGraspNet(latent=16, num_blocks=2)
    net.fit_normalizers(data[1].statistics_dataloader(), progress=False)
    return DefGraspNetsPredictor(net, 0.005, precision="fp64")


@pytest.fixture(scope="module")
def box():
    return structured_box((0.03, 0.03, 0.03), (4, 4, 4))


@pytest.fixture(scope="module")
def grasps(box):
    return sample_antipodal_grasps(box, 12, seed=0)


# ---------------------------------------------------------------------------------------------- objectives
def test_smooth_max_brackets_the_maximum():
    x = torch.rand(4, 200, dtype=torch.float64) * 1e4
    m = x.amax(-1)
    p = smooth_max(x, "pnorm", p=20.0)
    assert torch.all(p <= m * (1 + 1e-12)) and torch.all(p >= m * 200 ** (-1 / 20))
    lse = smooth_max(x, "logsumexp", temperature=100.0)
    assert torch.all(lse <= m + 1e-9) and torch.all(lse >= m - 100.0 * np.log(200) - 1e-9)
    assert torch.equal(smooth_max(x, "max"), m)
    # scale equivariance of the p-norm (stresses of different moduli span decades)
    assert torch.allclose(smooth_max(1e3 * x, "pnorm"), 1e3 * p)
    with pytest.raises(ValueError, match="smooth max"):
        smooth_max(x, "softplus")


def test_objective_terms_weights_and_sense():
    stress = torch.tensor([[1.0, 3.0], [2.0, 2.0]])
    disp = torch.zeros(2, 2, 3)
    disp[0, 0, 0] = 3e-3
    disp[1, :, 1] = 1e-3
    mean_def = PRESETS["min_mean_deformation"]
    assert torch.allclose(mean_def(stress, disp), torch.tensor([1.5e-3, 1e-3]))
    assert torch.allclose(PRESETS["max_mean_stress"](stress, disp), torch.tensor([2.0, 2.0]))
    assert PRESETS["max_mean_stress"].loss(stress, disp).tolist() == [-2.0, -2.0]
    combo = GraspObjective({"mean_deformation": 1000.0, "mean_stress": 1e-3})
    assert torch.allclose(combo(stress, disp), torch.tensor([1.5 + 2e-3, 1.0 + 2e-3]))
    assert combo.units == "1" and mean_def.units == "m" and PRESETS["min_max_stress"].units == "Pa"
    assert PRESETS["min_max_stress"].name == "min_max_stress"
    for bad, match in (
        ({"terms": {"peak_stress": 1.0}}, "unknown objective term"),
        ({"terms": {"max_stress": 0.0}}, "non-zero"),
        ({"terms": {}}, "at least one"),
        ({"sense": "lowest"}, "sense"),
        ({"smooth_max": "soft"}, "smooth_max"),
        ({"p": 0.5}, "exponent"),
    ):
        with pytest.raises(ValueError, match=match):
            GraspObjective(**bad)
    with pytest.raises(ValueError, match="expected stress"):
        mean_def(stress, disp[:, :, :2])


# ---------------------------------------------------------------------------------------------- poses
def test_rotation_exp_matches_scipy_and_small_angles():
    w = torch.tensor([[0.3, -1.2, 0.5], [1e-5, 2e-5, -1e-5], [0.0, 0.0, 0.0]], dtype=torch.float64)
    R = rotation_exp(w).numpy()
    np.testing.assert_allclose(R, Rotation.from_rotvec(w.numpy()).as_matrix(), atol=1e-14)
    # the gradient at omega = 0 exists and is that of I + [omega]_x
    w0 = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    rotation_exp(w0)[0, 1].backward()
    np.testing.assert_allclose(w0.grad.numpy(), [0.0, 0.0, -1.0])


def test_perturb_pose_moves_in_the_gripper_frame(grasps):
    T = torch.as_tensor(grasps.poses[:2])
    assert torch.allclose(perturb_pose(T, torch.zeros(2, 6, dtype=T.dtype)), T)
    xi = torch.zeros(2, 6, dtype=T.dtype)
    xi[:, 1] = 0.004  # 4 mm along the closing axis (gripper +y)
    moved = perturb_pose(T, xi)
    np.testing.assert_allclose((moved[:, :3, 3] - T[:, :3, 3]).numpy(), 0.004 * grasps.poses[:2, :3, 1])
    xi = torch.zeros(2, 6, dtype=T.dtype)
    xi[:, 4] = 0.3  # rotation about the grasp axis keeps the tool centre point
    turned = perturb_pose(T, xi)
    assert torch.allclose(turned[:, :3, 3], T[:, :3, 3])
    assert torch.allclose(turned[:, :3, 1], T[:, :3, 1])


# ---------------------------------------------------------------------------------------------- planner
@pytest.mark.parametrize("dense", [False, True])
def test_closing_distances_match_the_sampler(predictor64, box, grasps, dense):
    planner = GraspPlanner(predictor64, box, 2e5, PRESETS["min_max_stress"], dense_geometry=dense)
    closing, touches = planner.closing_distances(torch.as_tensor(grasps.poses))
    np.testing.assert_allclose(closing.numpy(), grasps.closing_distances, atol=1e-12)
    assert touches.all()


@pytest.mark.parametrize("dense", [False, True])
def test_gradient_matches_central_differences(predictor64, box, grasps, dense):
    """dQ/dxi from autograd (through finger joint states, graph features and the network) against central
    differences of the same function, in all six pose coordinates (both finger-state strategies)."""
    planner = GraspPlanner(
        predictor64, box, 2e5, PRESETS["min_max_stress"], closing_temperature=2e-4, dense_geometry=dense
    )
    T0 = torch.as_tensor(grasps.poses[[0, 5]])
    scale = torch.tensor([0.01] * 3 + [1.0] * 3, dtype=torch.float64)

    def q_of(xi):
        return planner.evaluate(perturb_pose(T0, xi * scale), grad=xi.requires_grad).q

    xi = torch.zeros(2, 6, dtype=torch.float64, requires_grad=True)
    q_of(xi).sum().backward()
    grad = xi.grad.numpy()
    h = 1e-6
    fd = np.zeros_like(grad)
    with torch.no_grad():
        for k in range(6):
            e = torch.zeros(2, 6, dtype=torch.float64)
            e[:, k] = h
            fd[:, k] = ((q_of(e) - q_of(-e)) / (2 * h)).numpy()
    assert np.abs(grad).max() > 0
    np.testing.assert_allclose(grad, fd, rtol=1e-4, atol=1e-6 * np.abs(fd).max())


def test_activation_checkpointing_gives_the_same_gradient(predictor64, box, grasps):
    planner = GraspPlanner(predictor64, box, 2e5, PRESETS["min_mean_deformation"])
    T0 = torch.as_tensor(grasps.poses[:3])
    grads = []
    for flag in (False, True):
        for network in predictor64.net.networks:
            network.activation_checkpointing = flag
        xi = torch.zeros(3, 6, dtype=torch.float64, requires_grad=True)
        planner.evaluate(perturb_pose(T0, xi), grad=True).q.sum().backward()
        grads.append(xi.grad.clone())
    for network in predictor64.net.networks:
        network.activation_checkpointing = False
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-10, atol=0.0)


def test_score_ranks_by_objective_and_puts_infeasible_last(predictor64, box, grasps):
    poses = grasps.poses.copy()
    poses[3, :3, 3] += [0.5, 0.0, 0.0]  # half a metre away: no finger reaches the object
    planner = GraspPlanner(predictor64, box, 2e5, PRESETS["min_max_stress"])
    q, feasible, rank = planner.score(poses)
    assert not feasible[3] and feasible[np.arange(12) != 3].all()
    assert rank[-1] == 3
    assert np.all(np.diff(q[rank[:-1]]) >= 0)
    q_max, _, rank_max = GraspPlanner(predictor64, box, 2e5, PRESETS["max_max_stress"]).score(poses)
    np.testing.assert_allclose(q_max, q)
    assert np.all(np.diff(q[rank_max[:-1]]) <= 0) and rank_max[-1] == 3
    chunked = GraspPlanner(predictor64, box, 2e5, PRESETS["min_max_stress"], batch_size=5).score(poses)[0]
    np.testing.assert_allclose(chunked, q, rtol=1e-12)


@pytest.mark.parametrize("dense", [False, True])
@pytest.mark.parametrize("sense", ["minimize", "maximize"])
def test_refinement_improves_and_stays_feasible(predictor64, box, grasps, sense, dense):
    planner = GraspPlanner(predictor64, box, 2e5, PRESETS["min_max_stress"], dense_geometry=dense)
    r = planner.refine(grasps.poses[:6], steps=4, sense=sense)
    sign = 1.0 if sense == "minimize" else -1.0
    assert np.all(sign * r.q <= sign * r.initial_q + 1e-9)  # never worse than the input
    assert np.any(sign * r.q < sign * r.initial_q - 1e-6)  # and some grasps improve
    assert r.q_history.shape == (5, 6) and r.accepted.shape == (4, 6)
    assert (r.accepted > 0).any()
    moved = r.translation > 0
    assert moved.any() and np.all(r.translation < 4 * 0.2 * 0.01 + 1e-9)
    # refined poses: rotations, collision-free, both fingers touch; joint states are the exact ones
    R = r.poses[:, :3, :3]
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)
    assert not FRANKA_HAND.collides(box.surface_trimesh(), r.poses).any()
    closing, touches = FRANKA_HAND.closing_distances(box.points, r.poses, faces=box.surface_faces)
    np.testing.assert_allclose(r.closing_distance, closing, atol=1e-12)
    assert touches.all()


def test_dense_geometry_gives_the_same_refinement(predictor64, box, grasps):
    """Dense (device) finger joint states and collision checks refine exactly as the host-selected ones."""
    results = [
        GraspPlanner(predictor64, box, 2e5, PRESETS["min_max_stress"], dense_geometry=dense).refine(
            grasps.poses[:6], steps=3
        )
        for dense in (False, True)
    ]
    for key in ("poses", "q", "closing_distance", "q_history", "accepted"):
        np.testing.assert_allclose(getattr(results[1], key), getattr(results[0], key), rtol=1e-12, atol=1e-15)


def test_reusing_rejected_grasps_refines_identically_with_fewer_evaluations(predictor64, box, grasps):
    """A grasp whose pose did not change since its rejection skips the gradient and line search (the network
    is deterministic): the same refinement as re-evaluating every grasp, with fewer grasps evaluated."""
    planner = GraspPlanner(predictor64, box, 2e5, PRESETS["min_max_stress"])
    kw = {"steps": 5, "step_size": 0.5, "max_backtracks": 1, "temperature": 0.003}  # many rejections
    runs, counts = {}, {}
    for reuse in (True, False):
        planner.timer = timer = StageTimer("cpu")
        runs[reuse] = planner.refine(grasps.poses[:6], reuse_rejected=reuse, **kw)
        counts[reuse] = dict(timer.counts)
    planner.timer = None
    r, ref = runs[True], runs[False]
    np.testing.assert_array_equal(r.accepted, ref.accepted)
    for key in ("poses", "q", "closing_distance", "q_history"):
        np.testing.assert_allclose(getattr(r, key), getattr(ref, key), rtol=1e-12, atol=1e-15)
    # the settings exercise both paths: rejected twice in a row (skipped), and a rejection followed by an
    # annealing step on the stored trial
    rejected = r.accepted[:-1] == 0
    assert (rejected & (r.accepted[1:] == 0)).any() and (rejected & (r.accepted[1:] == 2)).any()
    G, steps = r.accepted.shape[1], len(r.accepted)
    assert counts[False]["refine.gradient_grasps"] == steps * G
    assert counts[True]["refine.gradient_grasps"] == steps * G - np.count_nonzero(rejected)
    assert counts[True]["refine.trial_grasps"] < counts[False]["refine.trial_grasps"]


def test_planner_rejects_bad_input(predictor64, box, grasps):
    planner = GraspPlanner(predictor64, box, 2e5, PRESETS["min_max_stress"])
    bad = grasps.poses[:2].copy()
    bad[0, 0, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        planner.score(bad)
    skew = grasps.poses[:2].copy()
    skew[0, :3, :3] *= 1.5
    with pytest.raises(ValueError, match="rotations"):
        planner.score(skew)
    with pytest.raises(ValueError, match="shape"):
        planner.score(grasps.poses[0])
    with pytest.raises(ValueError, match="youngs_modulus"):
        GraspPlanner(predictor64, box, -1.0, PRESETS["min_max_stress"])
    # a string (plan.py youngs_modulus=abc) names the key (was math.isfinite's "must be real number, not str")
    with pytest.raises(ValueError, match="youngs_modulus must be a number, got 'abc'"):
        GraspPlanner(predictor64, box, "abc", PRESETS["min_max_stress"])
    with pytest.raises(ValueError, match="force must be a number, got None"):
        GraspPlanner(predictor64, box, 2e5, PRESETS["min_max_stress"], force=None)
    with pytest.raises(ValueError, match="sense"):
        planner.refine(grasps.poses[:2], steps=1, sense="down")


# ---------------------------------------------------------------------------------------------- verification
def test_threshold_hits():
    true_q = np.array([1.0, 2.0, 3.0, 10.0, 11.0, 12.0, 5.0, 6.0, 7.0])
    perfect = threshold_hits(true_q, np.array([0, 1, 2]), np.array([3, 4, 5]))
    assert perfect["hit_rate"] == 1.0 and perfect["low_hits"] == 1.0 and perfect["failed"] == 0
    swapped = threshold_hits(true_q, np.array([3, 4, 5]), np.array([0, 1, 2]))
    assert swapped["hit_rate"] == 0.0
    true_q[0] = np.nan  # a failed simulation is excluded, not counted as a hit or a miss
    partial = threshold_hits(true_q, np.array([0, 1, 6]), np.array([3, 4, 5]))
    assert partial["low_hits"] == 1.0 and partial["failed"] == 1


def test_simulated_grasps_give_the_objective_of_the_fem_fields(box, grasps):
    sim = simulate_grasps(
        box,
        GraspPoses(grasps.poses[:2], grasps.closing_distances[:2]),
        1e6,
        PRESETS["min_mean_stress"],
        force=10.0,
        steps=2,
    )
    assert sim.converged.all()
    np.testing.assert_allclose(sim.q, sim.stress.mean(axis=1), rtol=1e-12)
    assert np.all(sim.stress > 0) and sim.displacement.shape == (2, box.num_vertices, 3)
    with pytest.raises(ValueError, match="NaN"):
        GraspPoses(np.full((1, 4, 4), np.nan), np.zeros((1, 2)))


def test_simulated_grasps_score_the_field_the_model_predicts(box, grasps):
    """A model trained on rigid-removed displacements is verified against rigid-removed FEM fields."""
    poses = GraspPoses(grasps.poses[:2], grasps.closing_distances[:2])
    args = (box, poses, 1e6, PRESETS["min_mean_deformation"])
    total = simulate_grasps(*args, force=10.0, steps=2)
    removed = simulate_grasps(*args, force=10.0, steps=2, displacement_target="rigid_removed")
    assert total.converged.all() and removed.converged.all()
    np.testing.assert_allclose(removed.stress, total.stress)
    x = box.points + total.displacement
    expected = rigid_removed_deformation(box.points, x)
    np.testing.assert_allclose(np.linalg.norm(removed.displacement, axis=-1), expected, atol=1e-12)
    np.testing.assert_allclose(removed.q, expected.mean(axis=1), rtol=1e-12)
    # the best rigid fit includes the identity: never more squared displacement than the total field
    assert np.all((removed.displacement**2).sum(axis=(1, 2)) <= (total.displacement**2).sum(axis=(1, 2)))
    with pytest.raises(ValueError, match="displacement_target"):
        simulate_grasps(*args, displacement_target="rigid")


# ---------------------------------------------------------------------------------------------- entry point
@pytest.fixture(scope="module")
def checkpoint(data):
    root, dm = data
    ckpt = root / "model.ckpt"
    fit_and_save(DefGraspNetsModule(latent=16, num_blocks=2, lr=1e-3), dm, ckpt, steps=2)
    return ckpt


def _plan_command(ckpt, out, tmp_path, *overrides):
    return [
        sys.executable,
        str(ROOT / "scripts" / "plan_grasps.py"),
        f"ckpt_path={ckpt}",
        "object=box",
        "youngs_modulus=1e6",
        "objective=max_mean_deformation",
        "n_samples=16",
        "n_select=2",
        "refine_steps=2",
        "device=cpu",
        "progress=false",
        f"out_dir={out}",
        f"hydra.run.dir={tmp_path / 'run'}",
        *overrides,
    ]


def test_plan_grasps_script(checkpoint, tmp_path):
    """`python scripts/plan_grasps.py` with a checkpoint: ranked and refined grasps in plan.json, the
    figure of the best and worst grasps; bad keys and missing checkpoints are named."""
    out = tmp_path / "plan"
    cmd = _plan_command(checkpoint, out, tmp_path)
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads((out / "plan.json").read_text())
    assert report["objective"]["name"] == "max_mean_deformation" and report["objective"]["units"] == "m"
    assert report["displacement_target"] == "total"  # the checkpoint was saved on the total field
    assert len(report["samples"]) == 16 and len(report["ranking"]) >= 4
    q = [report["samples"][i]["q"] for i in report["ranking"]]
    assert q == sorted(q, reverse=True)  # maximizing: best first
    assert len(report["refined_low"]) == 2 and len(report["refined_high"]) == 2
    for r in report["refined_high"]:
        assert r["q"] >= r["initial_q"] - 1e-9
    assert "verification" not in report
    assert (out / "grasps.png").stat().st_size > 10_000
    # bad config keys and missing checkpoints are named
    bad = subprocess.run(
        [*cmd[:2], f"ckpt_path={tmp_path / 'missing.ckpt'}", f"hydra.run.dir={tmp_path / 'run2'}"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert bad.returncode != 0 and "checkpoint not found" in bad.stderr
    typo = subprocess.run(
        [*cmd[:3], "n_sample=5", f"hydra.run.dir={tmp_path / 'run3'}"], capture_output=True, text=True
    )
    assert typo.returncode != 0 and "n_sample" in typo.stderr


@pytest.mark.slow
def test_plan_grasps_script_verifies_in_the_simulator(checkpoint, tmp_path):
    """verify=true: the threshold and refined grasps are squeezed in the FEM and compared."""
    out = tmp_path / "plan"
    cmd = _plan_command(checkpoint, out, tmp_path, "verify=true", "verify_steps=2")
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=1800)
    assert done.returncode == 0, done.stderr[-3000:]
    v = json.loads((out / "plan.json").read_text())["verification"]
    assert v["simulated"] == 6
    assert set(v["true_q"]) == {"low", "high", "random", "low refined", "high refined"}
    assert 0.0 <= v["hit_rate"] <= 1.0 or v["failed"] == 6
    assert (out / "verification.png").stat().st_size > 5_000
