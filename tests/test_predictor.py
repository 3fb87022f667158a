"""Inference API: checkpoint round trip, finger input variants, chunking, gradients to the gripper pose."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from lightning import Trainer
from test_data_synthetic import make_shards

from defgraspnets.data.datamodule import GraspDataModule
from defgraspnets.fem.mesh import TetMesh
from defgraspnets.models.defgraspnets_module import DefGraspNetsModule
from defgraspnets.models.predictor import DefGraspNetsPredictor, FingerGeometry, finger_contact_poses

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def fit_and_save(module: DefGraspNetsModule, dm: GraspDataModule, path, steps: int) -> None:
    """Fit ``module`` for ``steps`` optimizer steps with Lightning on the CPU and save its checkpoint."""
    trainer = Trainer(
        max_steps=steps,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        limit_val_batches=1,
        num_sanity_val_steps=0,
        accelerator="cpu",
    )
    trainer.fit(module, datamodule=dm)
    trainer.save_checkpoint(path)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny module fitted for a few steps with Lightning, and its saved checkpoint."""
    root = tmp_path_factory.mktemp("pred")
    dm = GraspDataModule(
        str(make_shards(root / "grasps", grasps=3, num_steps=2, with_real=False)),
        batch_size=2,
        statistics_samples=8,
        contact_radius=0.004,
    )
    module = DefGraspNetsModule(latent=16, num_blocks=2, lr=1e-3)
    path = root / "model.ckpt"
    fit_and_save(module, dm, path, steps=3)
    return module.eval(), dm, path


def test_checkpoint_round_trip_predicts_identically(trained):
    module, dm, path = trained
    predictor = DefGraspNetsPredictor.from_checkpoint(path)
    assert predictor.contact_radius == pytest.approx(0.004)
    batch = next(iter(dm.val_dataloader()))
    with torch.no_grad():
        s0, d0 = module.net.fields(batch)
        s1, d1 = predictor.net.fields(batch)
    assert torch.equal(s0, s1) and torch.equal(d0, d1)
    for a, b in zip(module.net.normalizers, predictor.net.normalizers):
        assert torch.equal(a.mean, b.mean) and torch.equal(a.std, b.std)
    with pytest.raises(FileNotFoundError, match="checkpoint not found"):
        DefGraspNetsPredictor.from_checkpoint(path.with_name("missing.ckpt"))


def test_global_context_checkpoint_round_trip(trained, tmp_path):
    """A module with the graph-level context saves and reloads it (config key ``model.global_context``);
    a checkpoint saved without the key (all earlier ones) loads without it."""
    _, dm, path = trained
    module = DefGraspNetsModule(latent=16, num_blocks=2, global_context=True)
    saved = tmp_path / "context.ckpt"
    fit_and_save(module, dm, saved, steps=2)
    predictor = DefGraspNetsPredictor.from_checkpoint(saved)
    assert len(predictor.net.networks[0].global_blocks) == 2
    batch = next(iter(dm.val_dataloader()))
    with torch.no_grad():
        assert torch.equal(module.eval().net.fields(batch)[0], predictor.net.fields(batch)[0])
    old = torch.load(path, map_location="cpu", weights_only=False)
    del old["hyper_parameters"]["global_context"]
    torch.save(old, tmp_path / "old.ckpt")
    assert DefGraspNetsPredictor.from_checkpoint(tmp_path / "old.ckpt").net.networks[0].global_blocks is None


def _grasp_inputs(dm):
    sh = dm.shards[0]
    mesh = TetMesh(sh.object.points, sh.object.tets)
    fingers = sh.fingers
    contact = sh.finger_contact_pose  # (G, 2, 4, 4)
    d = 0.01  # closing distance of each finger from the open gripper
    opened = contact.copy()
    opened[:, :, :3, 3] -= d * sh.closing_direction
    gripper = opened[:, 0]  # gripper frame = finger 0 frame when open
    open_pose = np.stack([np.eye(4), np.linalg.inv(gripper[0]) @ opened[0, 1]])
    geometry = FingerGeometry(fingers.vertices, fingers.faces, fingers.closing_axis, open_pose)
    return sh, mesh, geometry, gripper, np.full((len(contact), 2), d)


def test_finger_input_variants_agree(trained):
    module, dm, path = trained
    predictor = DefGraspNetsPredictor(module.net, 0.004, contact_backend="kdtree")
    sh, mesh, geometry, gripper, dist = _grasp_inputs(dm)
    poses, dirs = finger_contact_poses(
        *(torch.as_tensor(x) for x in (gripper, geometry.open_pose, geometry.closing_axis, dist))
    )
    np.testing.assert_allclose(poses.numpy(), sh.finger_contact_pose, atol=1e-12)
    np.testing.assert_allclose(dirs.numpy(), sh.closing_direction, atol=1e-12)
    force, e = torch.tensor([2.0, 5.0, 8.0]), 2e5
    a = predictor.predict(
        mesh,
        force,
        e,
        finger_vertices=sh.fingers.vertices_at(sh.finger_contact_pose),
        finger_faces=sh.fingers.faces,
        closing_direction=sh.closing_direction,
    )
    b = predictor.predict(mesh, force, e, fingers=geometry, finger_pose=sh.finger_contact_pose)
    c = predictor.predict(mesh, force, e, fingers=geometry, gripper_pose=gripper, closing_distance=dist)
    chunked = predictor.predict(
        (sh.object.points, sh.object.tets),
        force,
        e,
        fingers=geometry,
        gripper_pose=gripper,
        closing_distance=dist,
        batch_size=2,
    )
    assert a.stress.shape == (3, sh.num_vertices) and a.displacement.shape == (3, sh.num_vertices, 3)
    assert (a.contact_edges > 0).all()
    for other in (b, c, chunked):
        torch.testing.assert_close(other.stress, a.stress, rtol=1e-5, atol=1e-3)
        torch.testing.assert_close(other.displacement, a.displacement, rtol=1e-5, atol=1e-10)
    # the same grasp state as the dataset's graph gives the same fields
    ds = dm.datasets["train"]
    i = int(np.flatnonzero((ds.samples[:, 0] == 0) & (ds.samples[:, 1] == 1))[0])
    g = ds[i]
    k, gi, s = g.sample[0, 1:].tolist()
    with torch.no_grad():
        ref_s, _ = module.net.fields(g)
    one = predictor.predict(
        mesh,
        float(g.force),
        float(g.youngs_modulus),
        fingers=geometry,
        finger_pose=sh.finger_contact_pose[gi : gi + 1],
    )
    torch.testing.assert_close(one.stress[0], ref_s[: sh.num_vertices], rtol=1e-4, atol=1e-2)
    with pytest.raises(ValueError, match="open_pose"):
        predictor.predict(
            mesh,
            1.0,
            e,
            fingers=FingerGeometry(geometry.vertices, geometry.faces, geometry.closing_axis),
            gripper_pose=gripper,
            closing_distance=dist,
        )


def test_gradients_reach_gripper_pose_and_closing_distance(trained):
    module, dm, _ = trained
    predictor = DefGraspNetsPredictor(module.net, 0.004)
    sh, mesh, geometry, gripper, dist = _grasp_inputs(dm)
    pose = torch.as_tensor(gripper, dtype=torch.float32).requires_grad_(True)
    closing = torch.as_tensor(dist, dtype=torch.float32).requires_grad_(True)
    out = predictor.predict(
        mesh, 5.0, 2e5, grad=True, fingers=geometry, gripper_pose=pose, closing_distance=closing
    )
    q = out.mean_stress.sum() / 1e3 + out.mean_deformation.sum() * 1e3
    q.backward()
    assert torch.isfinite(pose.grad).all() and pose.grad[:, :3, 3].abs().sum() > 0
    assert torch.isfinite(closing.grad).all() and closing.grad.abs().sum() > 0
    with torch.no_grad():
        plain = predictor.predict(
            mesh, 5.0, 2e5, fingers=geometry, gripper_pose=gripper, closing_distance=dist
        )
    assert not plain.stress.requires_grad


@pytest.mark.gpu
def test_predictor_on_cuda_matches_cpu(trained):
    module, dm, path = trained
    sh, mesh, geometry, gripper, dist = _grasp_inputs(dm)
    cpu = DefGraspNetsPredictor.from_checkpoint(path).predict(
        mesh, 5.0, 2e5, fingers=geometry, gripper_pose=gripper, closing_distance=dist
    )
    gpu = DefGraspNetsPredictor.from_checkpoint(path, device="cuda").predict(
        mesh, 5.0, 2e5, fingers=geometry, gripper_pose=gripper, closing_distance=dist
    )
    torch.testing.assert_close(gpu.stress.cpu(), cpu.stress, rtol=1e-3, atol=1.0)


def test_precision_options(trained):
    module, dm, path = trained
    sh, mesh, geometry, gripper, dist = _grasp_inputs(dm)
    kw = dict(fingers=geometry, gripper_pose=gripper, closing_distance=dist)
    ref = DefGraspNetsPredictor.from_checkpoint(path).predict(mesh, 5.0, 2e5, **kw)
    f64 = DefGraspNetsPredictor.from_checkpoint(path, precision="fp64").predict(mesh, 5.0, 2e5, **kw)
    assert f64.stress.dtype == torch.float64
    torch.testing.assert_close(f64.stress.float(), ref.stress, rtol=1e-4, atol=1e-2)
    bf16 = DefGraspNetsPredictor.from_checkpoint(path, precision="bf16")
    assert bf16.net.networks[0].node_encoder[0].weight.dtype == torch.bfloat16 and bf16.dtype == torch.float32
    low = bf16.predict(mesh, 5.0, 2e5, **kw)
    assert low.stress.dtype == torch.float32
    rel = (low.stress - ref.stress).abs() / ref.stress.abs().clamp_min(1.0)
    assert float(rel.max()) < 0.1  # bf16 network: ~1e-2 relative error
    with pytest.raises(ValueError, match="precision"):
        DefGraspNetsPredictor.from_checkpoint(path, precision="fp8")


def test_fused_message_passing_predicts_the_same_fields(trained):
    """``fused_message_passing=True`` (Triton kernels; here in the CPU interpreter, float32) gives the
    op-by-op fields; it is off by default on the CPU, and refused where the kernels cannot run."""
    from defgraspnets.models import fused_message_passing as fe

    module, dm, path = trained
    sh, mesh, geometry, gripper, dist = _grasp_inputs(dm)
    kw = dict(fingers=geometry, gripper_pose=gripper, closing_distance=dist)
    plain = DefGraspNetsPredictor.from_checkpoint(path)
    assert not plain.fused_message_passing
    if not (fe.triton is not None and fe.triton_interpreting()):
        pytest.skip("needs Triton's CPU interpreter (TRITON_INTERPRET=1)")
    ref = plain.predict(mesh, 5.0, 2e5, **kw)
    fused = DefGraspNetsPredictor.from_checkpoint(path, fused_message_passing=True)
    out = fused.predict(mesh, 5.0, 2e5, **kw)
    torch.testing.assert_close(out.stress, ref.stress, rtol=1e-4, atol=1e-3)
    torch.testing.assert_close(out.displacement, ref.displacement, rtol=1e-4, atol=1e-9)
    grad = fused.predict(
        mesh, 5.0, 2e5, grad=True, **{**kw, "gripper_pose": torch.as_tensor(gripper).requires_grad_()}
    )
    assert grad.stress.requires_grad  # passes with gradients use the differentiable blocks


def test_fused_message_passing_is_refused_where_it_cannot_run(trained, monkeypatch):
    module, dm, path = trained
    monkeypatch.setenv("TRITON_INTERPRET", "0")
    with pytest.raises(ValueError, match="fused_message_passing needs Triton, a CUDA device"):
        DefGraspNetsPredictor.from_checkpoint(path, fused_message_passing=True)


def test_graph_mean_loss_counts_only_errors_that_shift_a_graphs_mean(trained):
    module, dm, _ = trained
    batch = next(iter(dm.val_dataloader()))
    assert batch.graph_count == 2
    target = module.net.normalized_targets(batch)
    mask_s, mask_d = module.net.loss_mask(batch)
    graph = batch.node_graph()
    # +-0.5 alternating within each graph's stress-loss nodes (an even number each): node MSE 0.25, means kept
    sign = torch.zeros(len(target))
    for g in range(batch.graph_count):
        nodes = torch.nonzero(mask_s & (graph == g)).ravel()
        nodes = nodes[: len(nodes) // 2 * 2]
        sign[nodes] = torch.tensor([1.0, -1.0]).repeat(len(nodes) // 2)
    cancel = target.clone()
    cancel[:, 0] += 0.5 * sign
    shift = target.clone()
    shift[mask_s, 0] += 0.5 * sign[mask_s].abs()
    assert module.graph_mean_loss(batch, target, target) == pytest.approx(0.0, abs=1e-10)
    assert module.graph_mean_loss(batch, cancel, target) == pytest.approx(0.0, abs=1e-10)
    # every displacement magnitude 0.3 longer: every graph's mean shifts by 0.3, adding 0.3^2
    scaled = target.clone()
    norm = target[:, 1:].norm(dim=1, keepdim=True)
    direction = torch.where(norm > 0, target[:, 1:] / norm.clamp_min(1e-30), torch.tensor([1.0, 0.0, 0.0]))
    scaled[mask_d, 1:] = direction[mask_d] * (norm[mask_d] + 0.3)
    shifted_mean = []
    for g in range(batch.graph_count):
        m = mask_s & (graph == g)
        shifted_mean.append(float((0.5 * sign[m].abs()).mean()))
    want = float(np.mean(np.square(shifted_mean)))
    assert module.graph_mean_loss(batch, shift, target).item() == pytest.approx(want, rel=1e-5)
    assert module.graph_mean_loss(batch, scaled, target).item() == pytest.approx(0.09, rel=1e-4)
    # the total adds the term with its weight; the node MSE parts are unchanged
    base_total, base_s, _ = module.loss(batch, shift)
    module.hparams.graph_mean_weight = 2.0
    try:
        total, s, _ = module.loss(batch, shift)
    finally:
        module.hparams.graph_mean_weight = 0.0
    assert s == base_s and total.item() == pytest.approx(base_total.item() + 2.0 * want, rel=1e-5)
    with pytest.raises(ValueError, match="graph_mean_weight must be >= 0"):
        DefGraspNetsModule(latent=8, num_blocks=1, graph_mean_weight=-1.0)
