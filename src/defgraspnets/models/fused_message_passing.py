r"""Fused message passing of the processor blocks (Triton kernels), for inference.

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

The same functions as :class:`~defgraspnets.models.meshgraphnet.ProcessorBlock` up to floating-point rounding
and the order of the atomic sums; forward only, used where no gradient is needed (scoring, line-search
trials, inference). Needs Triton and CUDA tensors, or ``TRITON_INTERPRET=1`` (Triton's CPU interpreter,
which the tests use with float32: the interpreter does not emulate bfloat16 tensor-core products). On CUDA
they take bfloat16 or float16 latents (the half-precision inference path).
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

__all__ = ["fused_edge_update", "fused_message_passing_available", "fused_node_update"]

BLOCK_ROWS = 64  # edges or nodes per program (a 64 x l tile)
NUM_WARPS = 4


def _interpreting() -> bool:
    return os.environ.get("TRITON_INTERPRET", "0") == "1"


def fused_message_passing_available(device: torch.device | str, dtype: torch.dtype = torch.bfloat16) -> bool:
    """Whether the fused kernels run on ``device`` for latents of ``dtype``: Triton installed, and CUDA with
    bfloat16 or float16 latents (the tensor-core path they are made for; a float32 tile product would be
    compiled to scalar FMAs, slow to compile and to run), or the interpreter with any supported dtype."""
    if triton is None or dtype not in (torch.float32, torch.bfloat16, torch.float16):
        return False
    if _interpreting():
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
    def _edge_update_kernel(
        edge_ptr,  # (E, L) edge latents m
        target_term_ptr,  # (n, L) W_r h (no bias)
        source_term_ptr,  # (n, L) W_s h
        target_ptr,  # (E,) target node i
        source_ptr,  # (E,) source node j
        mask_ptr,  # (E,) bool: False zeroes the message (padding edges)
        w_first_ptr,  # (L, L) W_m, nn.Linear layout (out, in)
        b_first_ptr,  # (L,)
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
        IEEE: tl.constexpr,
    ):
        rows = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        valid = rows < num_edges
        cols = tl.arange(0, L)
        tile = rows[:, None].to(tl.int64) * L + cols[None, :]
        m = tl.load(edge_ptr + tile, mask=valid[:, None], other=0.0)
        dst = tl.load(target_ptr + rows, mask=valid, other=0).to(tl.int64)
        src = tl.load(source_ptr + rows, mask=valid, other=0).to(tl.int64)
        z = _dot(m, _weight_t(w_first_ptr, L, L), IEEE)
        z += tl.load(b_first_ptr + cols).to(tl.float32)[None, :]
        gathered = valid[:, None]
        z += tl.load(target_term_ptr + dst[:, None] * L + cols[None, :], mask=gathered, other=0.0).to(
            tl.float32
        )
        z += tl.load(source_term_ptr + src[:, None] * L + cols[None, :], mask=gathered, other=0.0).to(
            tl.float32
        )
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
        h = tl.load(node_ptr + tile, mask=valid, other=0.0)
        # the sums enter the MLP in the latent dtype, as in the unfused block
        mesh_sum = tl.load(mesh_sum_ptr + tile, mask=valid, other=0.0).to(h.dtype)
        contact_sum = tl.load(contact_sum_ptr + tile, mask=valid, other=0.0).to(h.dtype)
        z = _dot(h, _weight_t(w_first_ptr, 3 * L, L), IEEE)
        z += _dot(mesh_sum, _weight_t(w_first_ptr + L, 3 * L, L), IEEE)
        z += _dot(contact_sum, _weight_t(w_first_ptr + 2 * L, 3 * L, L), IEEE)
        z += tl.load(b_first_ptr + cols).to(tl.float32)[None, :]
        y = _mlp_tail(z, w_rest_ptr, b_rest_ptr, gamma_ptr, beta_ptr, eps, L, K, IEEE)
        tl.store(
            out_node_ptr + tile, (h.to(tl.float32) + y.to(h.dtype).to(tl.float32)).to(h.dtype), mask=valid
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


def fused_edge_update(
    mlp, edge: Tensor, node: Tensor, edge_index: Tensor, mask: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """Updated edge latents ``m + f(m, h_i, h_j)`` (E, l) of an
    :class:`~defgraspnets.models.meshgraphnet.EdgeMLP` ``f``, and the float32 sums of the messages ``f``
    over edges by target node (n, l), in one kernel (module docstring); ``mask`` (E,) bool zeroes the
    messages of padding edges. Forward only (no autograd)."""
    w_first = mlp.lin_edge.weight
    _check((edge, node), w_first, w_first.shape[0])
    w_rest, b_rest, gamma, beta, eps = _tail_parameters(mlp.rest, w_first.shape[0])
    E, latent = edge.shape
    # the node terms of the split first layer, one GEMM for both: [W_r; W_s] h
    terms = torch.nn.functional.linear(node, torch.cat([mlp.lin_target.weight, mlp.lin_source.weight]))
    target_term, source_term = terms[:, :latent].contiguous(), terms[:, latent:].contiguous()
    edge = edge.contiguous()
    out_edge = torch.empty_like(edge)
    agg = torch.zeros(node.shape[0], latent, dtype=torch.float32, device=edge.device)
    if E == 0:
        return out_edge, agg
    source, target = edge_index[0].contiguous(), edge_index[1].contiguous()
    _edge_update_kernel[(triton.cdiv(E, BLOCK_ROWS),)](
        edge,
        target_term,
        source_term,
        target,
        source,
        mask.contiguous() if mask is not None else target,  # unused without HAS_MASK
        w_first.contiguous(),
        mlp.lin_edge.bias.contiguous(),
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
        IEEE=w_first.dtype == torch.float32,
        num_warps=NUM_WARPS,
    )
    return out_edge, agg


def fused_node_update(mlp, node: Tensor, mesh_sum: Tensor, contact_sum: Tensor) -> Tensor:
    """``h + f([h, mesh_sum, contact_sum])`` (n, l) of a block's node :class:`~defgraspnets.models.
    meshgraphnet.MLP` ``f`` (first layer 3l -> l) in one kernel, without forming the concatenation;
    the float32 message sums enter ``f`` in the latent dtype, as in the unfused block. Forward only."""
    first = mlp[0]
    latent = node.shape[1]
    _check((node,), first.weight, latent)
    if tuple(first.weight.shape) != (latent, 3 * latent):
        raise ValueError(f"the node MLP's first layer must map 3 x {latent} -> {latent} features")
    w_rest, b_rest, gamma, beta, eps = _tail_parameters(list(mlp)[1:], latent)
    node = node.contiguous()
    out = torch.empty_like(node)
    n = node.shape[0]
    if n == 0:
        return out
    _node_update_kernel[(triton.cdiv(n, BLOCK_ROWS),)](
        node,
        mesh_sum.contiguous(),
        contact_sum.contiguous(),
        first.weight.contiguous(),
        first.bias.contiguous(),
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
        IEEE=first.weight.dtype == torch.float32,
        num_warps=NUM_WARPS,
    )
    return out
