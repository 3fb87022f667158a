r"""Fused message passing of the processor blocks (Triton kernels), for inference and planning gradients.

One message-passing block of :mod:`~defgraspnets.models.meshgraphnet` updates every edge with an MLP,
``m'_ij = LN(W_K relu(... W_1 relu(W_m m_ij + (W_r h)_i + (W_s h)_j + b) ...))``, sums the messages per
target node and updates every node with an MLP of ``[h_i, mesh sum, contact sum]``. Evaluated op by op,
each layer reads and writes an (E, l) tensor in global memory: on the planning batch (100 grasps of a
1573-vertex box: 2.7M mesh edges, l = 128, bf16) the edge GEMMs run at memory bandwidth (~0.36 ms each on an
H100), and with the gathers, the LayerNorms and the scatter the edge updates are ~80 % of the forward pass.

:func:`fused_edge_update` does an edge set in one kernel: a tile of edges is loaded once, the node terms are
gathered, the MLP layers run on tensor cores with the tile kept on chip (float32 accumulation, each layer's
input rounded to the weights' dtype as in the unfused network), LayerNorm in float32; the kernel writes the
updated latents ``m_ij + m'_ij`` and adds ``m'_ij`` to float32 per-node sums with atomics.
:func:`fused_node_update` does the node MLP the same way, with its first layer split over
``[h, mesh sum, contact sum]`` so that the concatenation is never formed. Nothing else (E, l)-sized is
written.

Gradients (``torch.autograd``) with respect to the latents, for planning, which differentiates the
network's output with respect to the grasp pose with the weights fixed: the forward saves only each
update's inputs; one backward kernel per edge set recomputes the tile's MLP on chip (the first-layer
pre-activations, the tail's for the LayerNorm), back-propagates through the LayerNorm and the layers
(``dz_{k-1} = (dz_k W_k) * [z_{k-1} > 0]``), writes the gradient of the edge latents and adds the
first-layer gradient to float32 per-node sums for the target and source terms with atomics; the node
kernel's backward likewise gives the gradients of ``h`` and of both message sums. Weight gradients are not
computed (a clear error if a weight requires one: training keeps the op-by-op blocks).

The same functions as :class:`~defgraspnets.models.meshgraphnet.ProcessorBlock` up to floating-point rounding
and the order of the atomic sums (the backward differentiates the unrounded message: the rounding of each
layer's input to bfloat16 is not differentiated, as in autograd of the op-by-op bfloat16 network). Needs
Triton and CUDA tensors, or ``TRITON_INTERPRET=1`` (Triton's CPU interpreter, which the tests use with
float32: the interpreter does not emulate bfloat16 tensor-core products). On CUDA they take bfloat16 or
float16 latents (the half-precision path). ``torch.compile`` does not trace into them (the kernels are
already fused; an inductor-compiled backward through them ended in an illegal memory access on the H100).
"""

from __future__ import annotations

import os

import torch
from torch import Tensor

try:  # Triton ships with CUDA builds of PyTorch; CPU-only installs may lack it
    import triton
    import triton.language as tl
except ImportError:  # pragma: no cover - depends on the installation
    triton = None
    tl = None

__all__ = [
    "fused_edge_update",
    "fused_message_passing_available",
    "fused_node_update",
    "triton_interpreting",
]

BLOCK_ROWS = 64  # edges or nodes per program (a 64 x l tile)
NUM_WARPS = 4
# the backward keeps more (B, l) tiles live (pre-activations and gradients); measured on an H100 (bf16,
# l = 128, 2.66M edges): edge backward 6.2 ms with 32 x 4 warps against 9.3 ms with 64 x 8 (node: 64 x 8)
EDGE_BACKWARD_BLOCK, EDGE_BACKWARD_WARPS = 32, 4
NODE_BACKWARD_BLOCK, NODE_BACKWARD_WARPS = 64, 8


def triton_interpreting() -> bool:
    """Whether Triton kernels run in its CPU interpreter (``TRITON_INTERPRET=1``, as the CPU tests do)."""
    return os.environ.get("TRITON_INTERPRET", "0") == "1"


def fused_message_passing_available(device: torch.device | str, dtype: torch.dtype = torch.bfloat16) -> bool:
    """Whether the fused kernels run on ``device`` for latents of ``dtype``: Triton installed, and CUDA with
    bfloat16 or float16 latents (the tensor-core path they are made for; a float32 tile product would be
    compiled to scalar FMAs, slow to compile and to run), or the interpreter with any supported dtype."""
    if triton is None or dtype not in (torch.float32, torch.bfloat16, torch.float16):
        return False
    if triton_interpreting():
        return True
    return torch.device(device).type == "cuda" and dtype != torch.float32


if triton is not None:

    @triton.jit
    def _dot(x, w, IEEE: tl.constexpr):
        """x (B, L) @ w (L, L) on tensor cores, float32 accumulation (IEEE float32 for float32 inputs)."""
        if IEEE:
            return tl.dot(x, w, input_precision="ieee")
        return tl.dot(x, w)

    @triton.jit
    def _weight_t(w_ptr, row_stride, L: tl.constexpr):
        """The (L, L) block at ``w_ptr`` of an nn.Linear weight (out, in) with ``row_stride`` inputs per
        output, transposed on load (``x @ result = x W^T``)."""
        cols = tl.arange(0, L)
        return tl.load(w_ptr + cols[None, :] * row_stride + cols[:, None])

    @triton.jit
    def _mlp_tail(
        z,
        w_rest_ptr,
        b_rest_ptr,
        gamma_ptr,
        beta_ptr,
        eps,
        L: tl.constexpr,
        K: tl.constexpr,
        IEEE: tl.constexpr,
    ):
        """float32 first-layer pre-activations z (B, L) -> LayerNorm(W_K relu(... relu(W_1 relu(z)) ...))
        (float32); each layer's input is rounded to the weights' dtype, as in the unfused MLP."""
        cols = tl.arange(0, L)
        for k in tl.static_range(K):
            w = _weight_t(w_rest_ptr + k * L * L, L, L)
            z = _dot(tl.maximum(z, 0.0).to(w.dtype), w, IEEE)
            z += tl.load(b_rest_ptr + k * L + cols).to(tl.float32)[None, :]
        mean = tl.sum(z, axis=1) / L
        d = z - mean[:, None]
        var = tl.sum(d * d, axis=1) / L
        y = d * (1.0 / tl.sqrt(var + eps))[:, None]
        gamma = tl.load(gamma_ptr + cols).to(tl.float32)
        beta = tl.load(beta_ptr + cols).to(tl.float32)
        return y * gamma[None, :] + beta[None, :]

    @triton.jit
    def _edge_first_layer(
        edge_ptr, target_term_ptr, source_term_ptr, term_stride, target_ptr, source_ptr, w_first_ptr,
        b_first_ptr, w_target_ptr, w_source_ptr, rows, valid, L: tl.constexpr, IEEE: tl.constexpr,
        DIRECT: tl.constexpr,
    ):  # fmt: skip
        """A tile's edge latents m, target and source nodes, and first-layer pre-activations
        ``W_m m + b + (W_r h)_i + (W_s h)_j`` (float32) of the edge rows ``rows`` (``valid`` of them); the
        node terms are rows of ``term_stride`` elements (both halves of one ``[W_r; W_s] h`` product).
        ``DIRECT``: the term pointers are the node latents h themselves and the tile multiplies the
        gathered rows by ``W_r``, ``W_s`` on chip (no node-term product in memory: for edge sets that
        touch few nodes, e.g. contact edges)."""
        cols = tl.arange(0, L)
        tile = rows[:, None].to(tl.int64) * L + cols[None, :]
        m = tl.load(edge_ptr + tile, mask=valid[:, None], other=0.0)
        dst = tl.load(target_ptr + rows, mask=valid, other=0).to(tl.int64)
        src = tl.load(source_ptr + rows, mask=valid, other=0).to(tl.int64)
        z = _dot(m, _weight_t(w_first_ptr, L, L), IEEE)
        z += tl.load(b_first_ptr + cols).to(tl.float32)[None, :]
        gathered = valid[:, None]
        target_rows = target_term_ptr + dst[:, None] * term_stride
        source_rows = source_term_ptr + src[:, None] * term_stride
        if DIRECT:
            h_target = tl.load(target_rows + cols[None, :], mask=gathered, other=0.0)
            h_source = tl.load(source_rows + cols[None, :], mask=gathered, other=0.0)
            z += _dot(h_target, _weight_t(w_target_ptr, L, L), IEEE)
            z += _dot(h_source, _weight_t(w_source_ptr, L, L), IEEE)
        else:
            z += tl.load(target_rows + cols[None, :], mask=gathered, other=0.0).to(tl.float32)
            z += tl.load(source_rows + cols[None, :], mask=gathered, other=0.0).to(tl.float32)
        return m, dst, src, z

    @triton.jit
    def _node_first_layer(
        node_ptr, mesh_sum_ptr, contact_sum_ptr, w_first_ptr, b_first_ptr, tile, valid,
        L: tl.constexpr, IEEE: tl.constexpr,
    ):  # fmt: skip
        """A tile's node latents h and first-layer pre-activations on ``[h, mesh sum, contact sum]``
        (float32; the float32 sums enter the MLP in the latent dtype, as in the unfused block)."""
        h = tl.load(node_ptr + tile, mask=valid, other=0.0)
        mesh_sum = tl.load(mesh_sum_ptr + tile, mask=valid, other=0.0).to(h.dtype)
        contact_sum = tl.load(contact_sum_ptr + tile, mask=valid, other=0.0).to(h.dtype)
        z = _dot(h, _weight_t(w_first_ptr, 3 * L, L), IEEE)
        z += _dot(mesh_sum, _weight_t(w_first_ptr + L, 3 * L, L), IEEE)
        z += _dot(contact_sum, _weight_t(w_first_ptr + 2 * L, 3 * L, L), IEEE)
        z += tl.load(b_first_ptr + tl.arange(0, L)).to(tl.float32)[None, :]
        return h, z

    @triton.jit
    def _edge_update_kernel(
        edge_ptr,  # (E, L) edge latents m
        target_term_ptr,  # (n, L) W_r h (no bias), rows of term_stride elements
        source_term_ptr,  # (n, L) W_s h, rows of term_stride elements
        term_stride,
        target_ptr,  # (E,) target node i
        source_ptr,  # (E,) source node j
        mask_ptr,  # (E,) bool: False zeroes the message (padding edges)
        w_first_ptr,  # (L, L) W_m, nn.Linear layout (out, in)
        b_first_ptr,  # (L,)
        w_target_ptr,  # (L, L) W_r (DIRECT)
        w_source_ptr,  # (L, L) W_s (DIRECT)
        w_rest_ptr,  # (K, L, L) the remaining Linear layers
        b_rest_ptr,  # (K, L)
        gamma_ptr,  # (L,) LayerNorm weight
        beta_ptr,  # (L,) LayerNorm bias
        out_edge_ptr,  # (E, L) m + m'
        agg_ptr,  # (n, L) float32 sums of m' by target (accumulated)
        num_edges,
        eps,
        L: tl.constexpr,
        K: tl.constexpr,
        BLOCK: tl.constexpr,
        HAS_MASK: tl.constexpr,
        DIRECT: tl.constexpr,
        IEEE: tl.constexpr,
    ):
        rows = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        valid = rows < num_edges
        cols = tl.arange(0, L)
        tile = rows[:, None].to(tl.int64) * L + cols[None, :]
        m, dst, src, z = _edge_first_layer(
            edge_ptr, target_term_ptr, source_term_ptr, term_stride, target_ptr, source_ptr, w_first_ptr,
            b_first_ptr, w_target_ptr, w_source_ptr, rows, valid, L, IEEE, DIRECT,
        )  # fmt: skip
        y = _mlp_tail(z, w_rest_ptr, b_rest_ptr, gamma_ptr, beta_ptr, eps, L, K, IEEE)
        keep = valid
        if HAS_MASK:
            keep = keep & (tl.load(mask_ptr + rows, mask=valid, other=0) != 0)
        # the message rounded to the latent dtype, as the unfused network adds and sums it
        y = tl.where(keep[:, None], y, 0.0).to(m.dtype).to(tl.float32)
        tl.store(out_edge_ptr + tile, (m.to(tl.float32) + y).to(m.dtype), mask=valid[:, None])
        tl.atomic_add(agg_ptr + dst[:, None] * L + cols[None, :], y, mask=keep[:, None], sem="relaxed")

    @triton.jit
    def _node_update_kernel(
        node_ptr,  # (n, L) node latents h
        mesh_sum_ptr,  # (n, L) float32 sums of mesh-edge messages
        contact_sum_ptr,  # (n, L) float32 sums of contact-edge messages
        w_first_ptr,  # (L, 3 L) first layer on [h, mesh sum, contact sum]
        b_first_ptr,  # (L,)
        w_rest_ptr,  # (K, L, L)
        b_rest_ptr,  # (K, L)
        gamma_ptr,
        beta_ptr,
        out_node_ptr,  # (n, L) h + f(h, sums)
        num_nodes,
        eps,
        L: tl.constexpr,
        K: tl.constexpr,
        BLOCK: tl.constexpr,
        IEEE: tl.constexpr,
    ):
        rows = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        valid = rows[:, None] < num_nodes
        cols = tl.arange(0, L)
        tile = rows[:, None].to(tl.int64) * L + cols[None, :]
        h, z = _node_first_layer(
            node_ptr, mesh_sum_ptr, contact_sum_ptr, w_first_ptr, b_first_ptr, tile, valid, L, IEEE
        )
        y = _mlp_tail(z, w_rest_ptr, b_rest_ptr, gamma_ptr, beta_ptr, eps, L, K, IEEE)
        tl.store(
            out_node_ptr + tile, (h.to(tl.float32) + y.to(h.dtype).to(tl.float32)).to(h.dtype), mask=valid
        )

    @triton.jit
    def _weight(w_ptr, row_stride, L: tl.constexpr):
        """The (L, L) block at ``w_ptr`` of an nn.Linear weight (out, in) as stored (``dz @ result`` is the
        gradient with respect to the layer's input)."""
        cols = tl.arange(0, L)
        return tl.load(w_ptr + cols[:, None] * row_stride + cols[None, :])

    @triton.jit
    def _tail_layer(z, w_rest_ptr, b_rest_ptr, k: tl.constexpr, L: tl.constexpr, IEEE: tl.constexpr):
        """Pre-activations of tail layer ``k``: ``W_k relu(z) + b_k`` (float32, input rounded to the weights'
        dtype)."""
        w = _weight_t(w_rest_ptr + k * L * L, L, L)
        out = _dot(tl.maximum(z, 0.0).to(w.dtype), w, IEEE)
        return out + tl.load(b_rest_ptr + k * L + tl.arange(0, L)).to(tl.float32)[None, :]

    @triton.jit
    def _mlp_tail_backward(
        z0,
        dy,
        w_rest_ptr,
        b_rest_ptr,
        gamma_ptr,
        eps,
        L: tl.constexpr,
        K: tl.constexpr,
        IEEE: tl.constexpr,
    ):
        """Gradient with respect to the first-layer pre-activations z0 (B, L) of :func:`_mlp_tail`'s output
        given its gradient dy (B, L) (float32). The tail is recomputed from z0 on chip: its pre-activations
        for the LayerNorm, then, going back through layer k, the pre-activations of layer k - 1 (K (K - 1) / 2
        extra tile products; none for K = 1)."""
        cols = tl.arange(0, L)
        z = z0
        for k in tl.static_range(K):
            z = _tail_layer(z, w_rest_ptr, b_rest_ptr, k, L, IEEE)
        mean = tl.sum(z, axis=1) / L
        d = z - mean[:, None]
        rstd = 1.0 / tl.sqrt(tl.sum(d * d, axis=1) / L + eps)
        y_hat = d * rstd[:, None]
        dy_hat = dy * tl.load(gamma_ptr + cols).to(tl.float32)[None, :]
        dz = rstd[:, None] * (
            dy_hat
            - (tl.sum(dy_hat, axis=1) / L)[:, None]
            - y_hat * (tl.sum(dy_hat * y_hat, axis=1) / L)[:, None]
        )
        for kk in tl.static_range(K):
            # back through tail layer k = K - 1 - kk, whose input is relu(z_prev)
            z_prev = z0
            for j in tl.static_range(K - 1 - kk):
                z_prev = _tail_layer(z_prev, w_rest_ptr, b_rest_ptr, j, L, IEEE)
            w = _weight(w_rest_ptr + (K - 1 - kk) * L * L, L, L)
            dz = tl.where(z_prev > 0.0, _dot(dz.to(w.dtype), w, IEEE), 0.0)
        return dz

    @triton.jit
    def _edge_update_backward_kernel(
        edge_ptr,  # (E, L) edge latents m (the forward's input)
        target_term_ptr,  # (n, L) W_r h, rows of term_stride elements
        source_term_ptr,  # (n, L) W_s h, rows of term_stride elements
        term_stride,
        target_ptr,  # (E,)
        source_ptr,  # (E,)
        mask_ptr,  # (E,) bool
        w_first_ptr,  # (L, L) W_m
        b_first_ptr,
        w_rest_ptr,
        b_rest_ptr,
        gamma_ptr,
        grad_out_edge_ptr,  # (E, L) gradient of m + m'
        grad_agg_ptr,  # (n, L) float32 gradient of the sums by target
        grad_edge_ptr,  # (E, L) out: gradient of m
        grad_target_term_ptr,  # (n, L) float32, accumulated: gradient of W_r h
        grad_source_term_ptr,  # (n, L) float32, accumulated: gradient of W_s h
        num_edges,
        eps,
        L: tl.constexpr,
        K: tl.constexpr,
        BLOCK: tl.constexpr,
        HAS_MASK: tl.constexpr,
        HAS_GRAD_AGG: tl.constexpr,
        IEEE: tl.constexpr,
    ):
        rows = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        valid = rows < num_edges
        cols = tl.arange(0, L)
        tile = rows[:, None].to(tl.int64) * L + cols[None, :]
        # the forward's first-layer pre-activations, recomputed
        m, dst, src, z0 = _edge_first_layer(
            edge_ptr, target_term_ptr, source_term_ptr, term_stride, target_ptr, source_ptr, w_first_ptr,
            b_first_ptr, w_first_ptr, w_first_ptr, rows, valid, L, IEEE, False,
        )  # fmt: skip
        target_tile = dst[:, None] * L + cols[None, :]
        source_tile = src[:, None] * L + cols[None, :]
        keep = valid
        if HAS_MASK:
            keep = keep & (tl.load(mask_ptr + rows, mask=valid, other=0) != 0)
        grad_out = tl.load(grad_out_edge_ptr + tile, mask=valid[:, None], other=0.0).to(tl.float32)
        # the message m' enters both the updated latent and the sum of its target node
        dy = grad_out
        if HAS_GRAD_AGG:
            dy += tl.load(grad_agg_ptr + target_tile, mask=valid[:, None], other=0.0)
        dy = tl.where(keep[:, None], dy, 0.0)
        dz0 = _mlp_tail_backward(z0, dy, w_rest_ptr, b_rest_ptr, gamma_ptr, eps, L, K, IEEE)
        dz0 = tl.where(keep[:, None] & (z0 > 0.0), dz0, 0.0)
        w_first = _weight(w_first_ptr, L, L)
        grad_edge = grad_out + _dot(dz0.to(w_first.dtype), w_first, IEEE)
        tl.store(grad_edge_ptr + tile, grad_edge.to(m.dtype), mask=valid[:, None])
        tl.atomic_add(grad_target_term_ptr + target_tile, dz0, mask=keep[:, None], sem="relaxed")
        tl.atomic_add(grad_source_term_ptr + source_tile, dz0, mask=keep[:, None], sem="relaxed")

    @triton.jit
    def _node_update_backward_kernel(
        node_ptr,  # (n, L) h
        mesh_sum_ptr,  # (n, L) float32
        contact_sum_ptr,  # (n, L) float32
        w_first_ptr,  # (L, 3 L)
        b_first_ptr,
        w_rest_ptr,
        b_rest_ptr,
        gamma_ptr,
        grad_out_ptr,  # (n, L) gradient of h + f
        grad_node_ptr,  # (n, L) out: gradient of h
        grad_mesh_sum_ptr,  # (n, L) float32 out
        grad_contact_sum_ptr,  # (n, L) float32 out
        num_nodes,
        eps,
        L: tl.constexpr,
        K: tl.constexpr,
        BLOCK: tl.constexpr,
        IEEE: tl.constexpr,
    ):
        rows = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        valid = rows[:, None] < num_nodes
        cols = tl.arange(0, L)
        tile = rows[:, None].to(tl.int64) * L + cols[None, :]
        h, z0 = _node_first_layer(
            node_ptr, mesh_sum_ptr, contact_sum_ptr, w_first_ptr, b_first_ptr, tile, valid, L, IEEE
        )
        grad_out = tl.load(grad_out_ptr + tile, mask=valid, other=0.0).to(tl.float32)
        dz0 = _mlp_tail_backward(z0, grad_out, w_rest_ptr, b_rest_ptr, gamma_ptr, eps, L, K, IEEE)
        dz0 = tl.where(valid & (z0 > 0.0), dz0, 0.0).to(h.dtype)
        grad_node = grad_out + _dot(dz0, _weight(w_first_ptr, 3 * L, L), IEEE)
        tl.store(grad_node_ptr + tile, grad_node.to(h.dtype), mask=valid)
        tl.store(grad_mesh_sum_ptr + tile, _dot(dz0, _weight(w_first_ptr + L, 3 * L, L), IEEE), mask=valid)
        tl.store(
            grad_contact_sum_ptr + tile, _dot(dz0, _weight(w_first_ptr + 2 * L, 3 * L, L), IEEE), mask=valid
        )


def _tail_parameters(rest, latent: int) -> tuple[Tensor, Tensor, Tensor, Tensor, float]:
    """(W (K, l, l), b (K, l), gamma, beta, eps) of the layers after the first of an MLP:
    ``[ReLU,] Linear, (ReLU, Linear)*, LayerNorm`` with every Linear l -> l."""
    from torch import nn

    layers = [m for m in rest if not isinstance(m, nn.ReLU)]
    linears, norm = layers[:-1], layers[-1] if layers else None
    if (
        not isinstance(norm, nn.LayerNorm)
        or not linears
        or not all(isinstance(m, nn.Linear) and tuple(m.weight.shape) == (latent, latent) for m in linears)
    ):
        raise ValueError(
            "fused message passing needs MLPs of Linear layers of the latent width ending in a LayerNorm"
        )
    weights = torch.stack([m.weight for m in linears]).contiguous()
    biases = torch.stack([m.bias for m in linears]).contiguous()
    return weights, biases, norm.weight.contiguous(), norm.bias.contiguous(), float(norm.eps)


def _check(latents: tuple[Tensor, ...], weight: Tensor, latent: int) -> None:
    """Clear errors unless the kernels run for ``weight``'s device and dtype, the latent size ``latent`` is a
    power of two >= 16 and the ``latents`` (·, latent) share the weights' dtype."""
    if triton is None:
        raise RuntimeError("fused message passing needs Triton (pip install triton)")
    if not fused_message_passing_available(weight.device, weight.dtype):
        raise RuntimeError(
            "fused message passing runs on CUDA with bfloat16 or float16 weights (or with "
            f"TRITON_INTERPRET=1), got {weight.dtype} on {weight.device}"
        )
    if latent & (latent - 1) or latent < 16:
        raise ValueError(f"fused message passing needs a power-of-two latent size >= 16, got {latent}")
    for x in latents:
        if x.dtype != weight.dtype or x.shape[-1] != latent:
            raise ValueError(
                f"latents {tuple(x.shape)} {x.dtype} do not match the weights ({latent}, {weight.dtype})"
            )


def _refuse_weight_gradients(module) -> None:
    """A clear error for a pass with gradients through a module whose weights require them."""
    if torch.is_grad_enabled() and any(p.requires_grad for p in module.parameters()):
        raise RuntimeError(
            "fused message passing differentiates with respect to the latents only (grasp planning); "
            "freeze the weights (requires_grad_(False)) or train with fused_message_passing off"
        )


class _FusedEdgeUpdate(torch.autograd.Function):
    """(m, W_r h, W_s h) -> (m + m', sums of m' by target); the backward kernel recomputes the MLP on chip
    from the saved inputs (nothing (E, l)-sized but the inputs is kept) and returns the gradients of the
    latents (the weights are constants)."""

    @staticmethod
    def forward(ctx, edge, target_term, source_term, target, source, mask, direct, *parameters):
        w_first, b_first, w_rest, b_rest, gamma, beta, eps = parameters
        E, latent = edge.shape
        if target_term.stride() != source_term.stride() or target_term.stride(1) != 1:
            raise ValueError("the node terms must be row-major views with one row stride")
        w_target, w_source = direct if direct is not None else (w_first, w_first)
        ctx.direct = direct is not None
        out_edge = torch.empty_like(edge)
        agg = torch.zeros(target_term.shape[0], latent, dtype=torch.float32, device=edge.device)
        if E:
            _edge_update_kernel[(triton.cdiv(E, BLOCK_ROWS),)](
                edge,
                target_term,
                source_term,
                target_term.stride(0),
                target,
                source,
                mask if mask is not None else target,  # unused without HAS_MASK
                w_first,
                b_first,
                w_target,
                w_source,
                w_rest,
                b_rest,
                gamma,
                beta,
                out_edge,
                agg,
                E,
                eps,
                L=latent,
                K=w_rest.shape[0],
                BLOCK=BLOCK_ROWS,
                HAS_MASK=mask is not None,
                DIRECT=direct is not None,
                IEEE=w_first.dtype == torch.float32,
                num_warps=NUM_WARPS,
            )
        ctx.save_for_backward(
            edge, target_term, source_term, target, source, mask, w_first, b_first, w_rest, b_rest
        )
        ctx.layer_norm = (gamma, eps)
        return out_edge, agg

    @staticmethod
    def backward(ctx, grad_out_edge, grad_agg):
        if ctx.direct:
            raise RuntimeError("the fused edge update with direct node terms has no backward")
        edge, target_term, source_term, target, source, mask, w_first, b_first, w_rest, b_rest = (
            ctx.saved_tensors
        )
        gamma, eps = ctx.layer_norm
        E, latent = edge.shape
        grad_edge = torch.empty_like(edge)
        grad_terms = torch.zeros(2, target_term.shape[0], latent, dtype=torch.float32, device=edge.device)
        if E:
            _edge_update_backward_kernel[(triton.cdiv(E, EDGE_BACKWARD_BLOCK),)](
                edge,
                target_term,
                source_term,
                target_term.stride(0),
                target,
                source,
                mask if mask is not None else target,
                w_first,
                b_first,
                w_rest,
                b_rest,
                gamma,
                grad_out_edge.contiguous(),
                grad_agg.contiguous() if grad_agg is not None else grad_terms,
                grad_edge,
                grad_terms[0],
                grad_terms[1],
                E,
                eps,
                L=latent,
                K=w_rest.shape[0],
                BLOCK=EDGE_BACKWARD_BLOCK,
                HAS_MASK=mask is not None,
                HAS_GRAD_AGG=grad_agg is not None,
                IEEE=w_first.dtype == torch.float32,
                num_warps=EDGE_BACKWARD_WARPS,
            )
        grad_terms = grad_terms.to(target_term.dtype)
        return (grad_edge, grad_terms[0], grad_terms[1]) + (None,) * 11


class _FusedNodeUpdate(torch.autograd.Function):
    """(h, mesh sums, contact sums) -> h + f([h, sums]); backward recomputed on chip, latents only."""

    @staticmethod
    def forward(ctx, node, mesh_sum, contact_sum, *parameters):
        w_first, b_first, w_rest, b_rest, gamma, beta, eps = parameters
        n, latent = node.shape
        out = torch.empty_like(node)
        if n:
            _node_update_kernel[(triton.cdiv(n, BLOCK_ROWS),)](
                node,
                mesh_sum,
                contact_sum,
                w_first,
                b_first,
                w_rest,
                b_rest,
                gamma,
                beta,
                out,
                n,
                eps,
                L=latent,
                K=w_rest.shape[0],
                BLOCK=BLOCK_ROWS,
                IEEE=w_first.dtype == torch.float32,
                num_warps=NUM_WARPS,
            )
        ctx.save_for_backward(node, mesh_sum, contact_sum, w_first, b_first, w_rest, b_rest)
        ctx.layer_norm = (gamma, eps)
        return out

    @staticmethod
    def backward(ctx, grad_out):
        node, mesh_sum, contact_sum, w_first, b_first, w_rest, b_rest = ctx.saved_tensors
        gamma, eps = ctx.layer_norm
        n, latent = node.shape
        grad_node = torch.empty_like(node)
        grad_sums = torch.empty(2, n, latent, dtype=torch.float32, device=node.device)
        if n:
            _node_update_backward_kernel[(triton.cdiv(n, NODE_BACKWARD_BLOCK),)](
                node,
                mesh_sum,
                contact_sum,
                w_first,
                b_first,
                w_rest,
                b_rest,
                gamma,
                grad_out.contiguous(),
                grad_node,
                grad_sums[0],
                grad_sums[1],
                n,
                eps,
                L=latent,
                K=w_rest.shape[0],
                BLOCK=NODE_BACKWARD_BLOCK,
                IEEE=w_first.dtype == torch.float32,
                num_warps=NODE_BACKWARD_WARPS,
            )
        return (grad_node, grad_sums[0], grad_sums[1]) + (None,) * 7


@torch.compiler.disable
def fused_edge_update(
    mlp,
    edge: Tensor,
    node: Tensor,
    edge_index: Tensor,
    mask: Tensor | None = None,
    direct: bool = False,
) -> tuple[Tensor, Tensor]:
    """Updated edge latents ``m + f(m, h_i, h_j)`` (E, l) of an
    :class:`~defgraspnets.models.meshgraphnet.EdgeMLP` ``f``, and the float32 sums of the messages ``f``
    over edges by target node (n, l), in one kernel (module docstring); ``mask`` (E,) bool zeroes the
    messages of padding edges. Differentiable with respect to ``edge`` and ``node`` (one backward kernel
    that recomputes the MLP from the inputs), not to the weights (a clear error if they require grad).

    ``direct`` (passes without gradients): the kernel multiplies the gathered node latents by the split
    first layer's ``W_r``, ``W_s`` itself instead of gathering rows of a ``[W_r; W_s] h`` product over all
    n nodes: cheaper for edge sets that touch few nodes (contact edges: H100, planning batch, one
    (n, 2 l) product less per block)."""
    w_first = mlp.lin_edge.weight
    latent = w_first.shape[0]
    _check((edge, node), w_first, latent)
    _refuse_weight_gradients(mlp)
    parameters = (w_first.contiguous(), mlp.lin_edge.bias.contiguous()) + _tail_parameters(mlp.rest, latent)
    source, target = edge_index[0].contiguous(), edge_index[1].contiguous()
    mask = mask.contiguous() if mask is not None else None
    if direct:
        if torch.is_grad_enabled() and (edge.requires_grad or node.requires_grad):
            raise ValueError("direct node terms are for passes without gradients")
        node = node.contiguous()
        weights = (mlp.lin_target.weight.contiguous(), mlp.lin_source.weight.contiguous())
        return _FusedEdgeUpdate.apply(
            edge.contiguous(), node, node, target, source, mask, weights, *parameters
        )
    # the node terms of the split first layer, one GEMM for both: [W_r; W_s] h (autograd through torch);
    # the kernels read both halves in place (rows of 2 l elements): no copies of the (n, l) halves
    # (H100, planning batch of 100 grasps: scoring 58-64 -> 54 ms)
    terms = torch.nn.functional.linear(node, torch.cat([mlp.lin_target.weight, mlp.lin_source.weight]))
    target_term, source_term = terms[:, :latent], terms[:, latent:]
    return _FusedEdgeUpdate.apply(
        edge.contiguous(), target_term, source_term, target, source, mask, None, *parameters
    )


@torch.compiler.disable
def fused_node_update(mlp, node: Tensor, mesh_sum: Tensor, contact_sum: Tensor) -> Tensor:
    """``h + f([h, mesh_sum, contact_sum])`` (n, l) of a block's node :class:`~defgraspnets.models.
    meshgraphnet.MLP` ``f`` (first layer 3l -> l) in one kernel, without forming the concatenation;
    the float32 message sums enter ``f`` in the latent dtype, as in the unfused block. Differentiable with
    respect to ``node`` and the sums (not the weights), like :func:`fused_edge_update`."""
    first = mlp[0]
    latent = node.shape[1]
    _check((node,), first.weight, latent)
    _refuse_weight_gradients(mlp)
    if tuple(first.weight.shape) != (latent, 3 * latent):
        raise ValueError(f"the node MLP's first layer must map 3 x {latent} -> {latent} features")
    parameters = (first.weight.contiguous(), first.bias.contiguous()) + _tail_parameters(
        list(mlp)[1:], latent
    )
    return _FusedNodeUpdate.apply(
        node.contiguous(), mesh_sum.contiguous(), contact_sum.contiguous(), *parameters
    )
