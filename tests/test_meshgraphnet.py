"""DefGraspNet: batching invariance, overfitting, gradients w.r.t. finger positions, ablations."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_data_synthetic import make_shards
from torch_geometric.loader import DataLoader

from defgraspnets.data.dataset import GraspFieldDataset, sample_index
from defgraspnets.data.grasp_schema import GraspShard
from defgraspnets.models.graph import NODE_FINGER
from defgraspnets.models.meshgraphnet import DefGraspNet, EncodeProcessDecode

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def shards(tmp_path_factory):
    d = make_shards(tmp_path_factory.mktemp("grasps"), grasps=2, num_steps=3, with_real=False)
    return [GraspShard(p) for p in sorted(d.glob("*.h5"))]


def _dataset(shards, entries, steps=(-1,), ramp_stride=None):
    return GraspFieldDataset(
        shards, sample_index(shards, np.asarray(entries), list(steps)), ramp_stride=ramp_stride
    )


def _net(ds, dtype=torch.float32, **kw):
    torch.manual_seed(0)
    net = DefGraspNet(**{"latent": 16, "num_blocks": 2, **kw})
    net.fit_normalizers(DataLoader(ds, batch_size=4), progress=False)
    return net.to(dtype).eval()


@pytest.mark.parametrize("global_context", [False, True])
def test_batch_of_two_equals_two_single_passes(shards, global_context):
    ds = _dataset(shards, [[0, 0, 0], [2, 2, 1]])  # two different objects, moduli, grasps
    net = _net(ds, torch.float64, global_context=global_context)
    batch = next(iter(DataLoader(ds, batch_size=2))).to_dtype(torch.float64)
    with torch.no_grad():
        joint = net(batch)
        s_joint, d_joint = net.fields(batch)
        n0 = ds[0].num_nodes
        for i in range(2):
            single = next(iter(DataLoader([ds[i]], batch_size=1))).to_dtype(torch.float64)
            sl = slice(0, n0) if i == 0 else slice(n0, None)
            torch.testing.assert_close(net(single), joint[sl], rtol=1e-10, atol=1e-10)
            s, d = net.fields(single)
            torch.testing.assert_close(s, s_joint[sl], rtol=1e-10, atol=1e-6)
            torch.testing.assert_close(d, d_joint[sl], rtol=1e-10, atol=1e-15)


def test_global_context_reaches_past_the_message_passing_range():
    """One block passes messages one edge far: on a chain of 8 nodes the output of node 0 ignores node 7,
    unless the global context is on; it never mixes two graphs of a batch."""
    chain = torch.stack([torch.arange(7), torch.arange(1, 8)])
    mesh_index = torch.cat([chain, chain.flip(0)], dim=1)
    contact_index = torch.zeros(2, 0, dtype=torch.long)

    def outputs(net, node):
        # two copies of the chain in one batch: nodes 0-7 graph 0, nodes 8-15 graph 1
        index = torch.cat([mesh_index, mesh_index + 8], dim=1)
        graph = torch.arange(2).repeat_interleave(8)
        mesh = torch.ones(index.shape[1], 2, dtype=torch.float64)
        contact = torch.zeros(0, 3, dtype=torch.float64)
        with torch.no_grad():
            return net(node, mesh, contact, index, contact_index, node_graph=graph, num_graphs=2)

    gen = torch.Generator().manual_seed(0)
    node = torch.randn(16, 4, generator=gen, dtype=torch.float64)
    far = node.clone()
    far[7] += 1.0  # the far end of graph 0
    for context in (False, True):
        torch.manual_seed(0)
        net = EncodeProcessDecode(4, 2, 3, 1, latent=8, num_blocks=1, global_context=context).double()
        base, moved = outputs(net, node), outputs(net, far)
        changed = (moved - base).abs().squeeze(1) > 1e-12
        assert changed[6:8].all()  # node 7 and its neighbour see the change in any case
        assert bool(changed[0]) == context  # node 0 is 7 edges away
        assert bool(changed[:8].all()) == context
        assert not changed[8:].any()  # graph 1 is untouched
    # a single graph without node_graph is one graph
    single = net(
        node[:8],
        torch.ones(14, 2, dtype=torch.float64),
        torch.zeros(0, 3, dtype=torch.float64),
        mesh_index,
        contact_index,
    )
    torch.testing.assert_close(single, base[:8], rtol=1e-12, atol=1e-12)


def test_overfits_tiny_dataset(shards):
    ds = _dataset(shards, [[0, 0, 0], [0, 1, 1], [0, 2, 0], [0, 2, 1]])
    net = _net(ds, latent=32).train()
    batch = next(iter(DataLoader(ds, batch_size=4)))
    target = net.normalized_targets(batch)
    mask = batch.node_type != NODE_FINGER
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    losses = []
    for _ in range(300):
        opt.zero_grad()
        loss = (net(batch)[mask] - target[mask]).square().mean()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[0] / min(losses[-10:]) >= 100, (losses[0], losses[-10:])


def test_gradient_wrt_finger_positions_matches_finite_differences(shards):
    ds = _dataset(shards, [[0, 0, 0], [0, 1, 1]])
    net = _net(ds, torch.float64, latent=8)
    g = ds[0].to_dtype(torch.float64)
    finger = (g.node_type == NODE_FINGER).nonzero().squeeze(1)
    touching = torch.unique(g.contact_edge_index[1][torch.isin(g.contact_edge_index[1], finger)])

    def objective(pos):  # a planning objective Q: mean stress [kPa] + mean deformation [mm]
        g.pos = pos
        s, d = net.fields(g)
        obj = g.node_type != NODE_FINGER
        return s[obj].mean() / 1e3 + d[obj].norm(dim=1).mean() * 1e3

    base = g.pos.detach().clone()
    pos = base.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(objective(pos), pos)
    assert grad[touching].abs().sum() > 0
    h = 1e-7
    for node in touching[:3].tolist() + finger[:1].tolist():
        for c in range(3):
            p1, p2 = base.clone(), base.clone()
            p1[node, c] += h
            p2[node, c] -= h
            fd = (objective(p1) - objective(p2)).item() / (2 * h)
            assert fd == pytest.approx(grad[node, c].item(), rel=1e-5, abs=1e-8), (node, c)


@pytest.mark.parametrize("kw", [{"outputs": "separate"}, {"force_feature": "total"}, {"force_on": "nodes"}])
def test_ablation_variants_forward(shards, kw):
    ds = _dataset(shards, [[0, 0, 0], [1, 1, 1]])
    net = _net(ds, **kw)
    assert len(net.networks) == (2 if kw.get("outputs") == "separate" else 1)
    batch = next(iter(DataLoader(ds, batch_size=2)))
    out = net(batch)
    assert out.shape == (batch.num_nodes, 4) and torch.isfinite(out).all()
    s, d = net.fields(batch)
    assert (s >= 0).all() and torch.isfinite(d).all()


def test_multi_step_rollout(shards):
    ds = _dataset(shards, [[0, 0, 0], [1, 1, 1]], steps=(1, 2), ramp_stride=1)
    assert not torch.equal(ds[0].prev_displacement, torch.zeros_like(ds[0].displacement))  # prev = step 0
    net = _net(ds, torch.float64, prediction="multi_step", num_steps=3)
    batch = next(iter(DataLoader(ds, batch_size=2))).to_dtype(torch.float64)
    # teacher-forced targets are increments from the previous ramp state
    _, d = net.scaled_targets(batch)
    e = batch.youngs_modulus[batch.batch].unsqueeze(1)
    torch.testing.assert_close(d, (batch.displacement - batch.prev_displacement) * e / 1e6)
    with torch.no_grad():
        s, disp = net.fields(batch)
    assert torch.isfinite(s).all() and torch.isfinite(disp).all()
    for key in range(4):  # every finger moves rigidly along its closing direction
        on = (batch.batch * 2 + batch.finger_id == key) & (batch.node_type == NODE_FINGER)
        assert torch.allclose(disp[on], disp[on][:1].expand_as(disp[on]))
        assert torch.allclose(
            torch.linalg.cross(disp[on][0], batch.closing_dir[on][0]), torch.zeros(3, dtype=torch.float64)
        )
    one = _net(ds, torch.float64, prediction="multi_step", num_steps=1)
    with torch.no_grad():
        s1, d1 = one.fields(batch)
        ref_s, ref_d = one.to_physical(one(batch, batch.pos, batch.force), batch)
    obj = batch.node_type != NODE_FINGER
    torch.testing.assert_close(s1, ref_s)
    torch.testing.assert_close(d1[obj], ref_d[obj])
    with pytest.raises(KeyError, match="prev_displacement"):
        net(next(iter(DataLoader(_dataset(shards, [[0, 0, 0]]), batch_size=1))).to_dtype(torch.float64))


def test_unfitted_network_refuses_to_predict(shards):
    ds = _dataset(shards, [[0, 0, 0]])
    with pytest.raises(RuntimeError, match="normalizers are not fitted"):
        DefGraspNet(latent=8, num_blocks=1)(ds[0])


def test_edge_mlp_gathers_the_same_way_compiled_and_eager():
    """Under torch.compile the edge MLP gathers by advanced indexing (inductor fuses it), in eager mode by
    index_select: the same messages and input gradients (Dynamo's eager backend traces the compiled
    branch)."""
    from defgraspnets.models.meshgraphnet import EdgeMLP

    torch.manual_seed(0)
    mlp = EdgeMLP(8, 2)
    edge, node = torch.randn(30, 8, requires_grad=True), torch.randn(10, 8, requires_grad=True)
    index = torch.randint(0, 10, (2, 30))
    compiled = torch.compile(mlp, backend="eager", fullgraph=True)
    out_eager, out_compiled = mlp(edge, node, index), compiled(edge, node, index)
    torch.testing.assert_close(out_compiled, out_eager)
    g_eager = torch.autograd.grad(out_eager.square().sum(), (edge, node))
    g_compiled = torch.autograd.grad(out_compiled.square().sum(), (edge, node))
    for a, b in zip(g_compiled, g_eager, strict=True):
        torch.testing.assert_close(a, b)
