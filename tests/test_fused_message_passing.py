"""Fused message passing (Triton kernels): the same function as the op-by-op processor blocks.

On a machine without CUDA the kernels run in Triton's CPU interpreter (``tests/conftest.py`` sets
``TRITON_INTERPRET=1``), in float32; the bfloat16 tensor-core path is checked on a GPU (``-m gpu``).
"""

from __future__ import annotations

import pytest
import torch

from defgraspnets.models import fused_message_passing as fe
from defgraspnets.models.meshgraphnet import EdgeMLP, EncodeProcessDecode

pytestmark = pytest.mark.usefixtures("one_torch_thread")

needs_kernels = pytest.mark.skipif(
    not (fe.triton is not None and fe.triton_interpreting()),
    reason="needs Triton's CPU interpreter (TRITON_INTERPRET=1, set by conftest without CUDA)",
)


def _perturbed(module: torch.nn.Module, seed: int = 0) -> torch.nn.Module:
    """Random non-trivial weights (also LayerNorm gains and biases, which start at 1 and 0)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.add_(0.1 * torch.randn(p.shape, generator=g))
    return module


def _graph(n=40, mesh_edges=200, contact_edges=30, seed=1):
    g = torch.Generator().manual_seed(seed)
    mesh_index = torch.randint(0, n, (2, mesh_edges), generator=g)
    contact_index = torch.randint(0, n, (2, contact_edges), generator=g)
    mask = torch.rand(contact_edges, generator=g) > 0.3
    return mesh_index, contact_index, mask, g


def _spy_on_launches(monkeypatch, kernel: str) -> list:
    """The grids of every launch of the Triton kernel ``fe.<kernel>`` from now on (the kernel still runs)."""
    calls, original = [], getattr(fe, kernel)

    class Spy:
        def __getitem__(self, grid):
            calls.append(grid)
            return original[grid]

    monkeypatch.setattr(fe, kernel, Spy())
    return calls


@needs_kernels
@pytest.mark.parametrize("hidden_layers", [1, 2, 3])
def test_fused_network_equals_the_op_by_op_network(hidden_layers):
    """Whole encode-process-decode forward, padding contact edges masked, float32: equal to rounding."""
    mesh_index, contact_index, mask, g = _graph()
    net = _perturbed(EncodeProcessDecode(7, 5, 6, 4, latent=16, num_blocks=3, hidden_layers=hidden_layers))
    node, mesh, contact = (
        torch.randn(40, 7, generator=g),
        torch.randn(200, 5, generator=g),
        torch.randn(30, 6),
    )
    with torch.no_grad():
        ref = net(node, mesh, contact, mesh_index, contact_index, mask)
        net.fused_message_passing = True
        out = net(node, mesh, contact, mesh_index, contact_index, mask)
    torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-5 * float(ref.abs().max()))
    # the masked (padding) contact edges change nothing: a graph without them gives the same outputs
    with torch.no_grad():
        kept = net(node, mesh, contact[mask], mesh_index, contact_index[:, mask])
    torch.testing.assert_close(kept, out, rtol=1e-5, atol=1e-5 * float(ref.abs().max()))


@needs_kernels
def test_fused_edge_update_gives_the_updated_latents_and_the_sums_per_target():
    mesh_index, _, _, g = _graph(n=25, mesh_edges=90)
    mlp = _perturbed(EdgeMLP(16, 2))
    edge, node = torch.randn(90, 16, generator=g), torch.randn(25, 16, generator=g)
    with torch.no_grad():
        message = mlp(edge, node, mesh_index)
        updated, sums = fe.fused_edge_update(mlp, edge, node, mesh_index)
    torch.testing.assert_close(updated, edge + message, rtol=1e-5, atol=1e-5)
    expected = torch.zeros(25, 16).index_add_(0, mesh_index[1], message)
    torch.testing.assert_close(sums, expected, rtol=1e-5, atol=1e-5)
    # a node that no edge targets gets a zero sum; no edges at all: nothing to update, zero sums
    untouched = torch.ones(25, dtype=torch.bool)
    untouched[mesh_index[1]] = False
    assert untouched.any() and torch.all(sums[untouched] == 0)
    with torch.no_grad():
        none, zero = fe.fused_edge_update(mlp, edge[:0], node, mesh_index[:, :0])
    assert none.shape == (0, 16) and torch.all(zero == 0)


@needs_kernels
def test_direct_node_terms_give_the_same_update_without_gradients():
    """``direct=True``: the kernel multiplies the gathered node latents by W_r, W_s itself (the contact
    edges' mode in passes without gradients); same latents and sums, masked edges too; refused with
    gradients."""
    _, contact_index, mask, g = _graph(n=40, contact_edges=150)
    mlp = _perturbed(EdgeMLP(16, 2)).requires_grad_(False)
    edge, node = torch.randn(150, 16, generator=g), torch.randn(40, 16, generator=g)
    with torch.no_grad():
        want = fe.fused_edge_update(mlp, edge, node, contact_index, mask)
        got = fe.fused_edge_update(mlp, edge, node, contact_index, mask, direct=True)
    for a, b in zip(got, want, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="without gradients"):
        fe.fused_edge_update(mlp, edge, node.requires_grad_(True), contact_index, mask, direct=True)


@needs_kernels
def test_messages_are_summed_by_target_across_tiles_and_around_masked_edges():
    """Edges ordered by target (as ``graph.directed`` makes them): long runs of one target that span tiles
    (64 edges), masked edges inside a run, and the same target again in a later tile all sum as
    ``index_add``; so do the gradients of the node latents."""
    g = torch.Generator().manual_seed(3)
    targets = torch.cat([torch.full((150,), 4), torch.arange(10).repeat_interleave(7), torch.full((20,), 4)])
    index = torch.stack([torch.randint(0, 12, (len(targets),), generator=g), targets])
    mask = torch.rand(len(targets), generator=g) > 0.25
    mlp = _perturbed(EdgeMLP(16, 2))
    edge = torch.randn(len(targets), 16, generator=g)
    node = torch.randn(12, 16, generator=g, requires_grad=True)
    message = mlp(edge, node, index) * mask[:, None]
    expected = torch.zeros(12, 16).index_add(0, index[1], message)
    for p in mlp.parameters():
        p.requires_grad_(False)
    _, sums = fe.fused_edge_update(mlp, edge, node, index, mask)
    torch.testing.assert_close(sums, expected.detach(), rtol=1e-5, atol=1e-5)
    weights = torch.randn(12, 16, generator=g)
    (grad_ref,) = torch.autograd.grad((expected * weights).sum(), node)
    (grad,) = torch.autograd.grad((sums * weights).sum(), node)
    torch.testing.assert_close(grad, grad_ref, rtol=1e-4, atol=1e-4 * float(grad_ref.abs().max()))


@needs_kernels
def test_trainable_weights_keep_the_op_by_op_blocks_in_passes_with_gradients(monkeypatch):
    """Training (weights that require gradients) never calls a kernel; the fused forward still serves its
    passes without gradients; calling a fused update directly with trainable weights is a clear error."""
    mesh_index, contact_index, mask, g = _graph()
    net = _perturbed(EncodeProcessDecode(7, 5, 6, 4, latent=16, num_blocks=2))
    net.fused_message_passing = True
    node = torch.randn(40, 7, generator=g, requires_grad=True)
    mesh, contact = torch.randn(200, 5, generator=g), torch.randn(30, 6, generator=g)
    calls = _spy_on_launches(monkeypatch, "_edge_update_kernel")
    out = net(node, mesh, contact, mesh_index, contact_index, mask)
    assert out.requires_grad and not calls
    out.sum().backward()
    assert net.blocks[0].node[0].weight.grad is not None  # weight gradients, for training
    with torch.no_grad():
        fused = net(node, mesh, contact, mesh_index, contact_index, mask)
    assert len(calls) == 2 * 2  # mesh and contact edges of each of the 2 blocks
    torch.testing.assert_close(fused, out.detach(), rtol=1e-5, atol=1e-5 * float(out.detach().abs().max()))
    with pytest.raises(RuntimeError, match="freeze the weights"):
        fe.fused_edge_update(
            net.blocks[0].mesh_edge, torch.randn(5, 16), torch.randn(4, 16), mesh_index[:, :5] % 4
        )


def _input_gradients(net, node, mesh, contact, mesh_index, contact_index, mask, weights):
    inputs = [x.detach().clone().requires_grad_(True) for x in (node, mesh, contact)]
    out = net(*inputs, mesh_index, contact_index, mask)
    (out * weights).sum().backward()
    return out.detach(), [x.grad for x in inputs]


@needs_kernels
@pytest.mark.parametrize("hidden_layers", [1, 2, 3])
def test_fused_gradients_equal_the_op_by_op_gradients(hidden_layers, monkeypatch):
    """Frozen weights (planning): the backward kernels give the op-by-op network's input gradients (node,
    mesh-edge and contact-edge features, through the encoders, 3 blocks with masked padding edges, the
    decoder), float32, to rounding (the op-by-op network's gradients are checked against finite differences
    in the planning tests)."""
    mesh_index, contact_index, mask, g = _graph()
    net = _perturbed(EncodeProcessDecode(7, 5, 6, 4, latent=16, num_blocks=3, hidden_layers=hidden_layers))
    net.requires_grad_(False)
    node, mesh, contact = (
        torch.randn(40, 7, generator=g),
        torch.randn(200, 5, generator=g),
        torch.randn(30, 6),
    )
    weights = torch.randn(40, 4, generator=g)
    ref_out, ref = _input_gradients(net, node, mesh, contact, mesh_index, contact_index, mask, weights)
    net.fused_message_passing = True
    calls = _spy_on_launches(monkeypatch, "_edge_update_backward_kernel")
    out, fused = _input_gradients(net, node, mesh, contact, mesh_index, contact_index, mask, weights)
    assert len(calls) == 2 * 3  # the backward ran in the kernels
    torch.testing.assert_close(out, ref_out, rtol=1e-5, atol=1e-5 * float(ref_out.abs().max()))
    for a, b in zip(fused, ref):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5 * float(b.abs().max()))
    # padding contact edges get no gradient through their (zeroed) messages, only the residual's
    assert torch.all(fused[2][~mask].abs().sum(1) == 0)  # encoder input of a padded edge: no influence


def test_availability_and_clear_errors(monkeypatch):
    monkeypatch.setenv("TRITON_INTERPRET", "0")
    # float32 tile products are not compiled for the GPU, and without the interpreter the CPU has no kernels
    assert not fe.fused_message_passing_available("cpu", torch.bfloat16)
    assert not fe.fused_message_passing_available("cuda", torch.float32)
    assert fe.fused_message_passing_available("cuda", torch.bfloat16) == (fe.triton is not None)
    assert not fe.fused_message_passing_available("cuda", torch.float64)
    if fe.triton is None:
        pytest.skip("Triton is not installed")
    mlp = EdgeMLP(16, 2)
    with pytest.raises(RuntimeError, match="CUDA with bfloat16"):
        fe.fused_edge_update(mlp, torch.zeros(3, 16), torch.zeros(4, 16), torch.zeros(2, 3, dtype=torch.long))


@needs_kernels
def test_unsupported_shapes_are_refused():
    with pytest.raises(ValueError, match="power-of-two latent"):
        fe.fused_edge_update(EdgeMLP(24, 2), torch.zeros(3, 24), torch.zeros(4, 24), torch.zeros(2, 3).long())
    with pytest.raises(ValueError, match="do not match the weights"):
        fe.fused_edge_update(
            EdgeMLP(16, 2), torch.zeros(3, 16).double(), torch.zeros(4, 16), torch.zeros(2, 3).long()
        )


@pytest.mark.gpu
def test_bf16_fused_network_is_as_accurate_as_the_bf16_op_by_op_network():
    """On CUDA: against a float32 reference, the fused bfloat16 forward errs no more than the unfused one."""
    mesh_index, contact_index, mask, g = _graph(n=3000, mesh_edges=30000, contact_edges=2000)
    net = _perturbed(EncodeProcessDecode(7, 5, 6, 4, latent=128, num_blocks=15)).cuda()
    inputs = [torch.randn(3000, 7, generator=g), torch.randn(30000, 5, generator=g), torch.randn(2000, 6)]
    idx = [mesh_index.cuda(), contact_index.cuda(), mask.cuda()]
    with torch.no_grad():
        ref = net(*[x.cuda() for x in inputs], *idx)
        net.to(torch.bfloat16)
        low = [x.cuda().bfloat16() for x in inputs]
        plain = net(*low, *idx).float()
        net.fused_message_passing = True
        fused = net(*low, *idx).float()
    err_plain = float((plain - ref).abs().mean())
    err_fused = float((fused - ref).abs().mean())
    assert err_fused < 1.5 * err_plain + 1e-4 * float(ref.abs().mean())


@pytest.mark.gpu
def test_bf16_fused_gradients_are_as_accurate_as_the_bf16_op_by_op_gradients():
    """On CUDA, frozen weights: input gradients of the fused bfloat16 network against a float32 reference err
    no more than those of the op-by-op bfloat16 network."""
    mesh_index, contact_index, mask, g = _graph(n=3000, mesh_edges=30000, contact_edges=2000)
    net = _perturbed(EncodeProcessDecode(7, 5, 6, 4, latent=128, num_blocks=15)).cuda().requires_grad_(False)
    inputs = [torch.randn(3000, 7, generator=g), torch.randn(30000, 5, generator=g), torch.randn(2000, 6)]
    weights = torch.randn(3000, 4, generator=g).cuda()
    idx = [mesh_index.cuda(), contact_index.cuda(), mask.cuda()]
    _, ref = _input_gradients(net, *[x.cuda() for x in inputs], *idx, weights)
    net.to(torch.bfloat16)
    low = [x.cuda().bfloat16() for x in inputs]
    _, plain = _input_gradients(net, *low, *idx, weights.bfloat16())
    net.fused_message_passing = True
    _, fused = _input_gradients(net, *low, *idx, weights.bfloat16())
    for r, p, f in zip(ref, plain, fused):
        err_plain = float((p.float() - r).abs().mean())
        err_fused = float((f.float() - r).abs().mean())
        assert err_fused < 1.5 * err_plain + 1e-4 * float(r.abs().mean())
