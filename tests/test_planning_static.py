"""Exact speed-ups of batched grasp evaluation: padded contact edges (static shapes), the object part encoded
once per batch, padded line-search batches, no recompilation under torch.compile, and the stage timer."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from defgraspnets.grasp.datagen import structured_box
from defgraspnets.grasp.sampler import sample_antipodal_grasps
from defgraspnets.models.graph import MultigraphFeaturizer, build_grasp_batch
from defgraspnets.models.meshgraphnet import DefGraspNet
from defgraspnets.models.predictor import DefGraspNetsPredictor
from defgraspnets.planning import PRESETS, GraspPlanner, gripper_finger_geometry, perturb_pose
from defgraspnets.planning.timing import StageTimer

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _net(dtype=torch.float64, **kw) -> DefGraspNet:
    """A small random network with placeholder statistics; the stress statistics are shifted so that the
    predicted stress is positive (non-zero objective and gradients)."""
    torch.manual_seed(0)
    net = DefGraspNet(**{"latent": 16, "num_blocks": 2, **kw})
    gen = torch.Generator().manual_seed(1)
    for norm in net.normalizers:
        x = torch.randn(64, norm.dim, dtype=torch.float64, generator=gen)
        norm.accumulate(x + 3.0 if norm is net.stress_norm else x)
        norm.finalize()
    return net.to(dtype)


@pytest.fixture(scope="module")
def box():
    return structured_box((0.03, 0.03, 0.03), (4, 4, 4))


@pytest.fixture(scope="module")
def grasps(box):
    return sample_antipodal_grasps(box, 8, seed=0)


def _predict(predictor, box, grasps, grad=False, youngs=2e5):
    pose = torch.as_tensor(grasps.poses, dtype=predictor.dtype).requires_grad_(grad)
    out = predictor.predict(
        box,
        15.0,
        youngs,
        grad=grad,
        fingers=gripper_finger_geometry(),
        gripper_pose=pose,
        closing_distance=grasps.closing_distances,
    )
    if not grad:
        return out, None
    (out.stress.mean() / 1e3 + out.deformation.mean() * 1e3).backward()
    return out, pose.grad


@pytest.mark.parametrize(
    "kw",
    [
        {},
        {"outputs": "separate"},
        {"force_feature": "total"},
        {"force_on": "nodes"},
        {"global_context": True},
    ],
    ids=str,
)
def test_padding_and_shared_object_give_the_plain_outputs_and_gradients(box, grasps, kw):
    """Every combination of padded contact edges and the shared object encoding predicts the fields (and
    their gradients w.r.t. the gripper poses) of the plain path, in float64."""
    net = _net(**kw)
    results = {}
    for static in (False, True):
        for share in (False, True):
            p = DefGraspNetsPredictor(copy.deepcopy(net), 0.005, static_shapes=static, share_object=share)
            results[static, share] = _predict(p, box, grasps, grad=True)
            if static:
                capacity = p.contact_capacities[len(grasps)]
                assert capacity > 2 * int(results[static, share][0].contact_edges.sum())
    ref, ref_grad = results[False, False]
    assert ref.contact_edges.min() > 0 and ref.stress.max() > 0 and ref_grad.abs().max() > 0
    for out, grad in results.values():
        torch.testing.assert_close(out.stress, ref.stress, rtol=1e-11, atol=1e-9)
        torch.testing.assert_close(out.displacement, ref.displacement, rtol=1e-11, atol=1e-18)
        assert torch.equal(out.contact_edges, ref.contact_edges)
        torch.testing.assert_close(grad, ref_grad, rtol=1e-9, atol=1e-12 * ref_grad.abs().max().item())


def test_object_encoding_is_kept_per_object_and_modulus(box, grasps):
    """The shared path keeps the object's features and encoder latents per (template, modulus): a second
    batch reuses them (with gradients too) and predicts what a fresh predictor does; another modulus or a
    tensor modulus gets its own encoding."""
    kept = DefGraspNetsPredictor(_net(), 0.005)
    first, _ = _predict(kept, box, grasps)
    assert len(kept._object_encodings) == 1
    ((template, encoding),) = kept._object_encodings.values()
    second, grad = _predict(kept, box, grasps, grad=True)
    assert kept._object_encodings[next(iter(kept._object_encodings))][1] is encoding
    torch.testing.assert_close(second.stress.detach(), first.stress, rtol=0, atol=0)
    assert torch.isfinite(grad).all() and grad.abs().sum() > 0
    other, _ = _predict(kept, box, grasps, youngs=2e6)
    assert len(kept._object_encodings) == 2
    fresh, _ = _predict(DefGraspNetsPredictor(_net(), 0.005), box, grasps, youngs=2e6)
    torch.testing.assert_close(other.stress, fresh.stress, rtol=0, atol=0)
    assert not torch.allclose(other.stress, first.stress)
    tensor_modulus, _ = _predict(kept, box, grasps, youngs=torch.tensor(2e6, dtype=torch.float64))
    assert len(kept._object_encodings) == 2  # a device value is not a key (no host sync)
    torch.testing.assert_close(tensor_modulus.stress, fresh.stress, rtol=0, atol=0)


def test_compiled_finger_joint_states_equal_the_eager_ones(box, grasps):
    """compile_geometry: torch.compile of the dense finger joint states gives the same closing distances,
    contact flags and pose gradients (inductor on the CPU in CI); it needs the dense strategy."""
    predictor = DefGraspNetsPredictor(_net(torch.float32), 0.005)
    args = (predictor, box, 2e5, PRESETS["min_max_stress"], 15.0)
    eager = GraspPlanner(*args, dense_geometry=True)
    compiled = GraspPlanner(*args, dense_geometry=True, compile_geometry=True)
    assert compiled.compile_geometry and not eager.compile_geometry
    T = eager._poses(grasps.poses).requires_grad_(True)
    (c0, t0), (c1, t1) = eager.closing_distances(T, exact=False), compiled.closing_distances(T, exact=False)
    torch.testing.assert_close(c1, c0, rtol=1e-6, atol=1e-9)
    assert torch.equal(t1, t0) and t0.any()
    (g0,) = torch.autograd.grad(c0.sum(), T)
    (g1,) = torch.autograd.grad(c1.sum(), T)
    torch.testing.assert_close(g1, g0, rtol=1e-5, atol=1e-7)
    # unpadded batches of other sizes (refinement steps): one more compilation (dynamic shapes), no more
    from torch._dynamo.utils import counters

    before = counters["stats"]["unique_graphs"]
    for k in (5, 3, 6):
        torch.testing.assert_close(
            compiled.closing_distances(T[:k].detach(), exact=False)[0], c0[:k].detach(), rtol=1e-6, atol=1e-9
        )
    assert counters["stats"]["unique_graphs"] - before <= 1
    with pytest.raises(ValueError, match="dense_geometry"):
        GraspPlanner(*args, dense_geometry=False, compile_geometry=True)


def test_shared_object_needs_one_modulus_and_a_one_step_network(box, grasps):
    """Per-grasp moduli and multi-step networks take the plain path, with the same results."""
    shared = DefGraspNetsPredictor(_net(), 0.005)
    plain = DefGraspNetsPredictor(_net(), 0.005, share_object=False)
    youngs = np.geomspace(1e5, 1e6, len(grasps))
    torch.testing.assert_close(
        _predict(shared, box, grasps, youngs=youngs)[0].stress,
        _predict(plain, box, grasps, youngs=youngs)[0].stress,
        rtol=0,
        atol=0,
    )
    assert not _net(prediction="multi_step").shares_object_encoding
    assert not _net(force_on="nodes").shares_object_encoding


def test_padded_batch_features(box, grasps):
    """build_grasp_batch with a contact capacity: the mask marks the real edges, the padding edges are
    self-loops on node 0, the force channel counts only real edges; too small a capacity is refused."""
    p = DefGraspNetsPredictor(_net(), 0.005)
    fv, cd, finger = p.finger_state(
        fingers=gripper_finger_geometry(),
        gripper_pose=grasps.poses,
        closing_distance=grasps.closing_distances,
    )
    obj = p.object_template(box)
    args = (obj, finger, fv, cd, torch.full((len(grasps),), 15.0, dtype=torch.float64), 2e5)
    plain = build_grasp_batch(*args)
    real = plain.contact_edge_index.shape[1]
    padded = build_grasp_batch(*args, contact_capacity=real + 10)
    assert padded.contact_mask.sum() == real and not padded.contact_mask[real:].any()
    assert torch.equal(padded.contact_edge_index[:, :real], plain.contact_edge_index)
    assert (padded.contact_edge_index[:, real:] == 0).all()
    fz = MultigraphFeaturizer()
    torch.testing.assert_close(fz.graph_force(padded), fz.graph_force(plain), rtol=0, atol=0)
    _, _, contact = fz(padded)
    torch.testing.assert_close(contact[:real], fz(plain)[2], rtol=0, atol=0)
    with pytest.raises(ValueError, match="contact_capacity"):
        build_grasp_batch(*args, contact_capacity=real - 2)
    # the capacity grows by powers of two with headroom and never shrinks for a batch size
    assert p.contact_capacity(8, 1000) == 2048 and p.contact_capacity(8, 100) == 2048
    assert p.contact_capacity(8, 2100) == 4096 and p.contact_capacity(3, 10) == 64


def test_padded_line_search_and_chunks_refine_identically(box, grasps):
    """pad_trials (line-search batches padded to G, G/2 or G/4, chunks to batch_size) changes nothing."""
    runs = {}
    for pad in (False, True):
        for batch_size in (None, 3):
            planner = GraspPlanner(
                DefGraspNetsPredictor(_net(), 0.005, static_shapes=pad),
                box,
                2e5,
                PRESETS["min_max_stress"],
                batch_size=batch_size,
                pad_trials=pad,
            )
            runs[pad, batch_size] = planner.refine(grasps.poses, steps=3)
    ref = runs[False, None]
    assert (ref.accepted > 0).any() and np.any(ref.q < ref.initial_q)
    for r in runs.values():
        np.testing.assert_array_equal(r.accepted, ref.accepted)
        np.testing.assert_allclose(r.q_history, ref.q_history, rtol=1e-10)
        np.testing.assert_allclose(r.poses, ref.poses, rtol=0, atol=1e-12)


def test_padded_sizes_halve_down_to_pad_levels(box):
    predictor = DefGraspNetsPredictor(_net(), 0.005)
    planner = GraspPlanner(predictor, box, 2e5, PRESETS["min_max_stress"], pad_trials=True)
    sizes = {n: planner._padded_size(n, 100) for n in (100, 51, 50, 26, 25, 1)}
    assert sizes == {100: 100, 51: 100, 50: 50, 26: 50, 25: 25, 1: 25}
    assert [planner._padded_size(n, 7) for n in (7, 5, 4, 3, 2, 1)] == [7, 7, 4, 4, 2, 2]
    planner.pad_levels = 1
    assert planner._padded_size(1, 100) == 100
    for bad in (0, 1.5):
        with pytest.raises(ValueError, match="pad_levels"):
            GraspPlanner(predictor, box, 2e5, PRESETS["min_max_stress"], pad_levels=bad)


def test_refinement_gradient_is_that_of_the_pose_only(box, grasps):
    """The refinement's backward pass fills no weight gradients of the network."""
    predictor = DefGraspNetsPredictor(_net(), 0.005)
    planner = GraspPlanner(predictor, box, 2e5, PRESETS["min_max_stress"])
    planner.refine(grasps.poses[:2], steps=1)
    assert all(p.grad is None for p in predictor.net.parameters())


def _refine_compile_counts(box, grasps, backend):
    from torch._dynamo.testing import CompileCounterWithBackend

    torch._dynamo.reset()
    counter = CompileCounterWithBackend(backend)
    predictor = DefGraspNetsPredictor(
        _net(torch.float32), 0.005, compile={"backend": counter}, activation_checkpointing=True
    )
    assert predictor.static_shapes
    planner = GraspPlanner(predictor, box, 2e5, PRESETS["min_max_stress"])
    T = torch.as_tensor(grasps.poses, dtype=torch.float32)
    planner.evaluate(T)  # first evaluation without gradients
    xi = torch.zeros(len(T), 6, requires_grad=True)
    planner.evaluate(perturb_pose(T, xi), grad=True).q.sum().backward(inputs=[xi])  # and with
    warm = counter.frame_count
    r = planner.refine(grasps.poses, steps=3)
    planner.score(grasps.poses)
    first = counter.frame_count
    planner.refine(grasps.poses, steps=3, seed=1)
    again = counter.frame_count
    torch._dynamo.reset()
    return warm, first, again, r


def test_compiled_refinement_does_not_recompile(box, grasps):
    """With torch.compile (AOT autograd, no code generation: fast) and static shapes, the line search's
    shrinking batches (padded to G, G/2 or G/4) and the changing contact edges compile at most one more graph
    per mode (Dynamo's automatic dynamic batch size) after the first evaluations, and nothing after that."""
    warm, total, again, r = _refine_compile_counts(box, grasps, "aot_eager")
    assert (r.accepted > 0).any() and (r.accepted[1:] > 0).any()  # the line search ran
    assert warm == 2 and warm <= total <= warm + 2 and again == total  # no grad + grad, then nothing new


@pytest.mark.slow
def test_compiled_refinement_does_not_recompile_with_inductor(box, grasps):
    """Same with the default Inductor backend (C++ code generation on the CPU: about a minute)."""
    warm, total, again, _ = _refine_compile_counts(box, grasps, "inductor")
    assert warm == 2 and warm <= total <= warm + 2 and again == total


def test_stage_timer_splits_scoring_and_counts_refinement(box, grasps):
    predictor = DefGraspNetsPredictor(_net(), 0.005)
    planner = GraspPlanner(predictor, box, 2e5, PRESETS["min_max_stress"])
    timer = StageTimer("cpu")
    planner.timer = timer
    assert predictor.timer is timer
    planner.score(grasps.poses)
    s = timer.summary()
    assert set(s) == {"fingers", "graph", "features", "network", "objective"}
    assert all(v["seconds"] > 0 for v in s.values())
    assert s["fingers"]["calls"] == 2 and s["network"]["calls"] == 1  # fingers: joint states, then pads
    timer.reset()
    r = planner.refine(grasps.poses, steps=2)
    s = timer.summary()
    trials = int(np.sum([np.count_nonzero(r.accepted[k] >= 0) for k in range(2)]))
    assert s["refine.gradient"]["calls"] == 2 and s["refine.backward"]["calls"] == 2
    # every grasp in the first gradient pass; in the second, those not rejected in the first step
    rejected = int(np.count_nonzero(r.accepted[0] == 0))
    assert s["refine.gradient_grasps"]["count"] == 2 * len(grasps) - rejected
    assert s["refine.trial"]["calls"] >= 3 and s["refine.trial_grasps"]["count"] >= len(grasps) + trials // 2
    assert s["network"]["calls"] == s["refine.gradient"]["calls"] + s["refine.trial"]["calls"]
    planner.timer = None
    assert predictor.timer is None


def test_shipped_checkpoint_predicts_the_same_on_every_path(box, grasps):
    """checkpoints/defgraspnets_box30.ckpt: padded contact edges and the shared object encoding reproduce the
    plain path's fields (float32 rounding)."""
    from pathlib import Path

    ckpt = Path(__file__).resolve().parents[1] / "checkpoints" / "defgraspnets_box30.ckpt"
    outs = [
        _predict(DefGraspNetsPredictor.from_checkpoint(ckpt, **kw), box, grasps, youngs=2.385e6)[0]
        for kw in ({"share_object": False}, {}, {"static_shapes": True})
    ]
    assert outs[0].stress.mean() > 0
    for out in outs[1:]:
        torch.testing.assert_close(out.stress, outs[0].stress, rtol=1e-5, atol=1e-3)
        torch.testing.assert_close(out.displacement, outs[0].displacement, rtol=1e-5, atol=1e-10)
