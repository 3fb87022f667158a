r"""DefGraspNets: a MeshGraphNets encode-process-decode network on the grasp multigraph (thesis §7.3).

Encode (three MLPs, LayerNorm on the outputs)
    ``h_i = eps_V(x_i)``, ``m_ij = eps_M(e^M_ij)``, ``c_ij = eps_C(e^C_ij)``        (latent size l = 128)
Process (L = 15 blocks with unshared weights; Pfaff et al. 2021, residual connections)
    ``m'_ij = f_M(m_ij, h_i, h_j)``,  ``c'_ij = f_C(c_ij, h_i, h_j)``
    ``h'_i = f_V(h_i, sum_{j->i in E^M} m'_ij, sum_{j->i in E^C} c'_ij)``
    ``h_i <- h_i + h'_i``,  ``m_ij <- m_ij + m'_ij``,  ``c_ij <- c_ij + c'_ij``
Global context (optional, ``global_context=True``; not in the thesis)
    after each block ``u_g = f_U(mean_{i in g} h_i)``, ``h_i <- h_i + u_{g(i)}``: every node sees a summary
    of its whole graph at every block. L blocks of message passing reach L mesh edges; mean stress and
    deformation, which grasps are ranked by, depend on how the whole object carries the load. Measured on 18
    objects it ranked grasps worse than the plain network after the same 20 epochs (test tau_s 0.52 vs 0.64;
    ``benchmarks/defgraspnets_long_training_h100.md``): an ablation, not a recommendation.
Decode (MLP without LayerNorm)
    ``y_i = delta(h_i)`` = standardized [log-stress (1), scaled displacement (3)] per node.

Every MLP has ``hidden_layers`` ReLU layers of width l. Edge MLPs are evaluated with their first layer split
over the concatenation, ``W [m, h_i, h_j] = W_m m + (W_r h)_i + (W_s h)_j``, so the node terms are computed
once per node and gathered (same function, ~3x fewer first-layer FLOPs on edges). Gathers are
``index_select`` in eager mode (whose backward is an ``index_add_``, much faster on CUDA than the sort-based
backward of advanced indexing) and advanced indexing under ``torch.compile`` (which inductor fuses).
Aggregation is a vectorized ``index_add_`` over edge targets; nothing loops over nodes or edges.

Exact reformulations for batches of grasps of one object (planning):
    padded contact edges: ``contact_mask`` (E_C,) zeroes the messages of padding edges, so a contact edge set
       padded to a fixed capacity gives the same outputs (static shapes for ``torch.compile``);
    shared object encoding (:meth:`DefGraspNet.forward_shared`): in a one-step prediction the object's node
       features (type, rest position, zero closing direction) and mesh-edge features (rest geometry,
       ``log10 E``) are the same in every graph of the batch, so their encoder latents are computed once and
       broadcast; only finger nodes, finger mesh edges and contact edges are encoded per grasp.

Fused message passing (``EncodeProcessDecode.fused_message_passing``): each block runs as three Triton
kernels (:mod:`~defgraspnets.models.fused_message_passing`; same function up to rounding) in passes without
gradients, and in passes with gradients when the blocks' weights are frozen (planning differentiates with
respect to the grasp pose only; backward kernels recompute each MLP on chip from the block's inputs).

Ablations (thesis Table 7.2) by constructor arguments of :class:`DefGraspNet`:
    V1 ``outputs="separate"``: two networks, one for stress, one for displacement ("joint": one network).
    V2 ``prediction="multi_step"``: the ramp 0 -> F_g is split in ``num_steps`` increments; each pass maps
       the current deformed state (object and finger positions) and the next force level to the stress at
       that level and the displacement increment; training uses ground-truth previous states (teacher
       forcing, pairs ``(s - stride, s)`` from the ramp), prediction rolls out from the rest state.
    V3 ``force_feature="total"``: ``F_g`` instead of ``F_g / |E^C|`` on contact edges.
    V4 ``force_on="nodes"``: the force scalar on every node instead of on contact edges.
"""

from __future__ import annotations

from collections.abc import Iterable

import torch
from torch import Tensor, nn
from torch.utils.checkpoint import checkpoint
from tqdm.auto import tqdm

from defgraspnets.data.normalization import Normalizer, TargetScaling
from defgraspnets.models.fused_message_passing import fused_edge_update, fused_node_update
from defgraspnets.models.graph import NODE_FINGER, GraspGraph, MultigraphFeaturizer

__all__ = [
    "DefGraspNet",
    "EdgeMLP",
    "EncodeProcessDecode",
    "GlobalContext",
    "MLP",
    "ProcessorBlock",
    "graph_mean",
]


class MLP(nn.Sequential):
    """``in -> [Linear(width) -> ReLU] x hidden_layers -> Linear(out) [-> LayerNorm(out)]``."""

    def __init__(
        self, in_dim: int, out_dim: int, width: int, hidden_layers: int = 2, layer_norm: bool = True
    ):
        layers: list[nn.Module] = []
        d = in_dim
        for _ in range(hidden_layers):
            layers += [nn.Linear(d, width), nn.ReLU()]
            d = width
        layers.append(nn.Linear(d, out_dim))
        if layer_norm:
            layers.append(nn.LayerNorm(out_dim))
        super().__init__(*layers)


class EdgeMLP(nn.Module):
    """Edge update ``f(m_ij, h_i, h_j)`` of an :class:`MLP` on ``[m_ij, h_i, h_j]``, first layer split.

    Args:
        latent: size of node and edge latents. hidden_layers: >= 1 hidden layers of width ``latent``.

    Shapes: edge (E, l), node (n, l), edge_index (2, E) [source j, target i] -> (E, l).
    """

    def __init__(self, latent: int, hidden_layers: int = 2):
        super().__init__()
        if hidden_layers < 1:
            raise ValueError("EdgeMLP needs at least one hidden layer")
        self.lin_edge = nn.Linear(latent, latent)
        self.lin_target = nn.Linear(latent, latent, bias=False)
        self.lin_source = nn.Linear(latent, latent, bias=False)
        self.rest = MLP(latent, latent, latent, hidden_layers - 1, layer_norm=True)

    def forward(self, edge: Tensor, node: Tensor, edge_index: Tensor) -> Tensor:
        src, dst = edge_index
        target, source = self.lin_target(node), self.lin_source(node)
        if torch.compiler.is_compiling():
            # inductor fuses advanced-indexing gathers (and their scatter-add backward) into its kernels;
            # index_select stays an extern op: H100, bf16 compiled training at batch 64, 263 -> 347 graphs/s
            z = self.lin_edge(edge) + target[dst] + source[src]
        else:
            # eager: index_select, whose backward index_add_ is much faster than advanced indexing's
            z = self.lin_edge(edge) + target.index_select(0, dst) + source.index_select(0, src)
        return self.rest(torch.relu(z))


class ProcessorBlock(nn.Module):
    """One message-passing block over mesh and contact edges (see the module docstring).

    Shapes: node (n, l), mesh (E_M, l), contact (E_C, l), indices (2, E_*) -> same shapes. The optional
    ``contact_mask`` (E_C,) bool zeroes the messages (and latent updates) of padding contact edges.
    """

    def __init__(self, latent: int, hidden_layers: int = 2):
        super().__init__()
        self.mesh_edge = EdgeMLP(latent, hidden_layers)
        self.contact_edge = EdgeMLP(latent, hidden_layers)
        self.node = MLP(3 * latent, latent, latent, hidden_layers, layer_norm=True)

    @staticmethod
    def aggregate(messages: Tensor, target: Tensor, num_nodes: int) -> Tensor:
        """(n, l) sum of ``messages`` (E, l) over edges by target node (accumulated in >= fp32)."""
        acc = torch.promote_types(messages.dtype, torch.float32)
        out = torch.zeros(num_nodes, messages.shape[1], dtype=acc, device=messages.device)
        return out.index_add_(0, target, messages.to(acc)).to(messages.dtype)

    def forward(
        self,
        node: Tensor,
        mesh: Tensor,
        contact: Tensor,
        mesh_index: Tensor,
        contact_index: Tensor,
        contact_mask: Tensor | None = None,
    ):
        new_mesh = self.mesh_edge(mesh, node, mesh_index)
        new_contact = self.contact_edge(contact, node, contact_index)
        if contact_mask is not None:
            new_contact = torch.where(contact_mask.unsqueeze(1), new_contact, torch.zeros_like(new_contact))
        n = node.shape[0]
        agg = torch.cat(
            [
                node,
                self.aggregate(new_mesh, mesh_index[1], n),
                self.aggregate(new_contact, contact_index[1], n),
            ],
            dim=1,
        )
        return node + self.node(agg), mesh + new_mesh, contact + new_contact

    def forward_fused(
        self,
        node: Tensor,
        mesh: Tensor,
        contact: Tensor,
        mesh_index: Tensor,
        contact_index: Tensor,
        contact_mask: Tensor | None = None,
    ):
        """:meth:`forward` in three fused kernels (:mod:`~defgraspnets.models.fused_message_passing`): each
        edge set updated and summed by target, then the nodes updated (differentiable with respect to the
        latents, not the weights)."""
        mesh, mesh_sum = fused_edge_update(self.mesh_edge, mesh, node, mesh_index)
        # contact edges touch few nodes: without gradients their kernel multiplies the gathered node
        # latents itself (no node-term product over all nodes)
        contact, contact_sum = fused_edge_update(
            self.contact_edge, contact, node, contact_index, contact_mask, direct=not torch.is_grad_enabled()
        )
        return fused_node_update(self.node, node, mesh_sum, contact_sum), mesh, contact


def graph_mean(values: Tensor, node_graph: Tensor, num_graphs: int) -> tuple[Tensor, Tensor]:
    """Mean of ``values`` (n, ...) over the nodes of each graph, (num_graphs, ...) in ``values``' dtype
    (accumulated in >= fp32), and the node count of each graph (num_graphs,); ``node_graph`` (n,) is the
    graph index of every node. A graph without nodes has mean 0."""
    acc = torch.promote_types(values.dtype, torch.float32)
    sums = values.new_zeros((num_graphs, *values.shape[1:]), dtype=acc)
    sums.index_add_(0, node_graph, values.to(acc))
    counts = values.new_zeros(num_graphs, dtype=acc)
    counts.index_add_(0, node_graph, torch.ones_like(node_graph, dtype=acc))
    scale = counts.clamp_min(1.0).view(num_graphs, *(1,) * (values.dim() - 1))
    return (sums / scale).to(values.dtype), counts


class GlobalContext(nn.Module):
    """Graph-level context added to every node: ``h_i <- h_i + f_U(mean_{j in g(i)} h_j)``.

    Shapes: node (n, l), node_graph (n,) graph index of every node -> (n, l). The mean is accumulated in
    >= fp32; ``f_U`` is an MLP with LayerNorm on its output (as the processor's node MLP).
    """

    def __init__(self, latent: int, hidden_layers: int = 2):
        super().__init__()
        self.mlp = MLP(latent, latent, latent, hidden_layers, layer_norm=True)

    def forward(self, node: Tensor, node_graph: Tensor, num_graphs: int) -> Tensor:
        mean, _ = graph_mean(node, node_graph, num_graphs)
        return node + self.mlp(mean).index_select(0, node_graph)


class EncodeProcessDecode(nn.Module):
    """MeshGraphNets encoder / L processor blocks / decoder on a two-edge-set multigraph.

    Args:
        node_dim, mesh_edge_dim, contact_edge_dim: input feature sizes. out_dim: outputs per node.
        latent: latent size l. num_blocks: L. hidden_layers: hidden layers of every MLP.
        global_context: a :class:`GlobalContext` after every block (default off: the thesis's network).
    """

    def __init__(
        self,
        node_dim: int,
        mesh_edge_dim: int,
        contact_edge_dim: int,
        out_dim: int,
        latent: int = 128,
        num_blocks: int = 15,
        hidden_layers: int = 2,
        global_context: bool = False,
    ):
        super().__init__()
        self.node_encoder = MLP(node_dim, latent, latent, hidden_layers)
        self.mesh_encoder = MLP(mesh_edge_dim, latent, latent, hidden_layers)
        self.contact_encoder = MLP(contact_edge_dim, latent, latent, hidden_layers)
        self.blocks = nn.ModuleList(ProcessorBlock(latent, hidden_layers) for _ in range(num_blocks))
        self.global_blocks = (
            nn.ModuleList(GlobalContext(latent, hidden_layers) for _ in range(num_blocks))
            if global_context
            else None
        )
        self.decoder = MLP(latent, out_dim, latent, hidden_layers, layer_norm=False)
        # activation checkpointing: with gradients on, keep only each block's inputs and recompute its
        # intermediate activations in the backward pass (memory ~ L x latents instead of L x MLP layers)
        self.activation_checkpointing = False
        # fused blocks (Triton) for passes without gradients or with frozen weights, see
        # :mod:`.fused_message_passing`
        self.fused_message_passing = False

    @property
    def processor_requires_grad(self) -> bool:
        """Whether any weight of the message-passing blocks requires a gradient (training)."""
        return any(p.requires_grad for p in self.blocks.parameters())

    def encode_object(self, node: Tensor, mesh: Tensor) -> tuple[Tensor, Tensor]:
        """Latents (N, l), (E_o, l) of the object part shared by all graphs of a batch (see :meth:`forward`)
        from its normalized node (N, node_dim) and mesh-edge (E_o, mesh_edge_dim) features."""
        return self.node_encoder(node), self.mesh_encoder(mesh)

    def forward(
        self,
        node: Tensor,
        mesh: Tensor,
        contact: Tensor,
        mesh_index: Tensor,
        contact_index: Tensor,
        contact_mask: Tensor | None = None,
        object_latents: tuple[Tensor, Tensor] | None = None,
        node_graph: Tensor | None = None,
        num_graphs: int = 1,
    ):
        """(n, node_dim), (E_M, ·), (E_C, ·) normalized features -> (n, out_dim).

        ``contact_mask`` (E_C,) bool: False on padding contact edges (their messages are zeroed).
        ``object_latents``: the :meth:`encode_object` latents ``(N, l), (E_o, l)`` of an object part shared by
        G graphs whose nodes are ``[object N | per-graph n - N]`` and mesh edges ``[object E_o | per-graph]``;
        then ``node`` (G, n - N, node_dim) and ``mesh`` (G, E_M / G - E_o, ·) hold only the per-graph parts
        (same result as encoding the full features, without encoding the object G times).
        ``node_graph`` (n,) graph index of every node and ``num_graphs``: the graphs the global context
        averages over (default: one graph); unused without it.
        """
        c = self.contact_encoder(contact)
        if object_latents is None:
            h, m = self.node_encoder(node), self.mesh_encoder(mesh)
        else:
            h_o, m_o = object_latents
            g = node.shape[0]
            h = torch.cat([h_o.expand(g, -1, -1), self.node_encoder(node)], dim=1).flatten(0, 1)
            m = torch.cat([m_o.expand(g, -1, -1), self.mesh_encoder(mesh)], dim=1).flatten(0, 1)
        grad = torch.is_grad_enabled()
        # the fused kernels differentiate with respect to the latents only: with gradients on, they serve
        # networks with frozen weights (planning); training keeps the op-by-op blocks
        fused = self.fused_message_passing and not (grad and self.processor_requires_grad)
        recompute = self.activation_checkpointing and grad
        if self.global_blocks is not None and node_graph is None:
            node_graph = torch.zeros(h.shape[0], dtype=torch.long, device=h.device)
            num_graphs = 1
        for i, block in enumerate(self.blocks):
            if fused:
                h, m, c = block.forward_fused(h, m, c, mesh_index, contact_index, contact_mask)
            elif recompute:
                h, m, c = checkpoint(
                    block, h, m, c, mesh_index, contact_index, contact_mask, use_reentrant=False
                )
            else:
                h, m, c = block(h, m, c, mesh_index, contact_index, contact_mask)
            if self.global_blocks is not None:
                h = self.global_blocks[i](h, node_graph, num_graphs)
        return self.decoder(h)


class DefGraspNet(nn.Module):
    """Multigraph featurization + normalization + encode-process-decode + physical output scaling.

    Args:
        latent, num_blocks, hidden_layers: network size (thesis: 128, 15, 2).
        outputs: ``"joint"`` or ``"separate"`` (V1). prediction: ``"one_step"`` or ``"multi_step"`` (V2).
        num_steps: force increments of a multi-step rollout.
        force_feature, force_on: see :class:`~defgraspnets.models.graph.MultigraphFeaturizer` (V3, V4).
        stress_reference, modulus_reference, modulus_saturation: target scaling [Pa], see
            :mod:`defgraspnets.data.normalization` (``modulus_saturation=None``: ``d E / E_ref``).
        global_context: graph-level context after every block (:class:`GlobalContext`; not the thesis's).

    ``forward`` gives standardized outputs (n, 4) = [stress, displacement xyz]; :meth:`fields` gives von Mises
    stress [Pa] (n,) and displacement [m] (n, 3) of the final state (one pass, or a multi-step rollout).
    """

    def __init__(
        self,
        latent: int = 128,
        num_blocks: int = 15,
        hidden_layers: int = 2,
        outputs: str = "joint",
        prediction: str = "one_step",
        num_steps: int = 5,
        force_feature: str = "distributed",
        force_on: str = "contact_edges",
        stress_reference: float = 1e3,
        modulus_reference: float = 1e6,
        modulus_saturation: float | None = None,
        global_context: bool = False,
    ):
        super().__init__()
        if outputs not in ("joint", "separate"):
            raise ValueError(f"outputs must be 'joint' or 'separate', got {outputs!r}")
        if prediction not in ("one_step", "multi_step"):
            raise ValueError(f"prediction must be 'one_step' or 'multi_step', got {prediction!r}")
        if num_steps < 1:
            raise ValueError(f"num_steps must be >= 1, got {num_steps}")
        self.outputs, self.prediction, self.num_steps = outputs, prediction, int(num_steps)
        self.featurizer = MultigraphFeaturizer(force_feature, force_on)
        fz = self.featurizer
        self.node_norm = Normalizer(fz.node_dim, "node features")
        self.mesh_edge_norm = Normalizer(fz.mesh_edge_dim, "mesh edge features")
        self.contact_edge_norm = Normalizer(fz.contact_edge_dim, "contact edge features")
        self.stress_norm = Normalizer(1, "stress target")
        self.displacement_norm = Normalizer(3, "displacement target", isotropic=True)
        self.scaling = TargetScaling(
            stress_reference, modulus_reference, modulus_saturation=modulus_saturation
        )
        dims = (fz.node_dim, fz.mesh_edge_dim, fz.contact_edge_dim)
        out_dims = (4,) if outputs == "joint" else (1, 3)
        self.networks = nn.ModuleList(
            EncodeProcessDecode(
                *dims,
                out_dim=o,
                latent=latent,
                num_blocks=num_blocks,
                hidden_layers=hidden_layers,
                global_context=global_context,
            )
            for o in out_dims
        )

    # -------------------------------------------------------------- normalization
    @property
    def normalizers(self) -> tuple[Normalizer, ...]:
        return (
            self.node_norm,
            self.mesh_edge_norm,
            self.contact_edge_norm,
            self.stress_norm,
            self.displacement_norm,
        )

    @property
    def normalized(self) -> bool:
        return all(n.initialized for n in self.normalizers)

    def input_positions(self, g: GraspGraph) -> Tensor:
        """Positions of the features: rest/first contact (one-step) or the previous state (multi-step)."""
        if self.prediction == "multi_step":
            prev = getattr(g, "prev_displacement", None)
            if prev is None:
                raise KeyError(
                    "multi_step prediction needs 'prev_displacement' in the batch "
                    "(set data.ramp_stride so the dataset provides previous ramp states)"
                )
            return g.pos + prev
        return g.pos

    def scaled_targets(self, g: GraspGraph) -> tuple[Tensor, Tensor]:
        """Scaled (not yet standardized) targets: log-stress (n, 1) and scaled displacement (n, 3).

        Multi-step: the displacement target is the increment ``d_s - d_{s'}`` from the previous state.
        """
        if getattr(g, "stress", None) is None or getattr(g, "displacement", None) is None:
            raise KeyError("the batch has no 'stress'/'displacement' targets")
        disp = g.displacement
        if self.prediction == "multi_step":
            disp = disp - g.prev_displacement
        e_node = g.youngs_modulus[g.node_graph()]
        return (
            self.scaling.stress_to_target(g.stress).unsqueeze(1),
            self.scaling.displacement_to_target(disp, e_node),
        )

    def normalized_targets(self, g: GraspGraph) -> Tensor:
        """(n, 4) standardized targets matching :meth:`forward`."""
        s, d = self.scaled_targets(g)
        return torch.cat([self.stress_norm(s), self.displacement_norm(d)], dim=1)

    def loss_mask(self, g: GraspGraph) -> tuple[Tensor, Tensor]:
        """Nodes in the stress and in the displacement loss: object nodes (multi-step: displacement of the
        finger nodes too, their rigid travel drives the rollout)."""
        obj = g.node_type != NODE_FINGER
        if self.prediction == "multi_step":
            return obj, torch.ones_like(obj)
        return obj, obj

    @torch.no_grad()
    def fit_normalizers(self, batches: Iterable[GraspGraph], progress: bool = True) -> None:
        """Measure feature and target statistics on training batches (stored as buffers)."""
        for norm in self.normalizers:
            norm.reset()
        try:
            total = len(batches)  # type: ignore[arg-type]
        except TypeError:
            total = None
        device = next(self.parameters()).device
        for g in tqdm(
            batches, total=total, desc="normalization statistics", disable=not progress, leave=False
        ):
            g = g.to(device)
            node, mesh, contact = self.featurizer(g, self.input_positions(g))
            if g.contact_edge_mask is not None:
                contact = contact[g.contact_edge_mask]
            self.node_norm.accumulate(node)
            self.mesh_edge_norm.accumulate(mesh)
            if contact.shape[0]:
                self.contact_edge_norm.accumulate(contact)
            s, d = self.scaled_targets(g)
            mask_s, mask_d = self.loss_mask(g)
            self.stress_norm.accumulate(s[mask_s])
            self.displacement_norm.accumulate(d[mask_d])
        if not self.contact_edge_norm.num_accumulated:
            raise RuntimeError(
                "no contact edges in the statistics batches: are the fingers within the contact "
                "radius of the object at first contact?"
            )
        for norm in self.normalizers:
            norm.finalize()

    # -------------------------------------------------------------- prediction
    def forward(self, g: GraspGraph, pos: Tensor | None = None, force: Tensor | None = None) -> Tensor:
        """(n, 4) standardized outputs for graph(s) ``g`` at positions ``pos`` and graph forces ``force``."""
        if not self.normalized:
            raise RuntimeError(
                "DefGraspNet normalizers are not fitted: call fit_normalizers() on training data "
                "or load a trained checkpoint"
            )
        node, mesh, contact = self.featurizer(g, self.input_positions(g) if pos is None else pos, force)
        dtype = node.dtype
        # features and normalization in the dtype of the positions (fp32/fp64); the encode-process-decode
        # networks may run in a lower precision (e.g. bf16 for inference, see ``DefGraspNetsPredictor``)
        net_dtype = self.network_dtype
        node, mesh, contact = (
            self.node_norm(node).to(net_dtype),
            self.mesh_edge_norm(mesh).to(net_dtype),
            self.contact_edge_norm(contact).to(net_dtype),
        )
        mask = g.contact_edge_mask
        graphs = (g.node_graph(), g.graph_count)
        outs = [
            net(node, mesh, contact, g.mesh_edge_index, g.contact_edge_index, mask, None, *graphs)
            for net in self.networks
        ]
        return (outs[0] if len(outs) == 1 else torch.cat(outs, dim=1)).to(dtype)

    @property
    def network_dtype(self) -> torch.dtype:
        """dtype of the encode-process-decode networks (may be lower than the features', e.g. bf16)."""
        return self.networks[0].node_encoder[0].weight.dtype

    @property
    def shares_object_encoding(self) -> bool:
        """Whether :meth:`forward_shared` applies: one-step prediction (object nodes at rest) with the force
        on contact edges (node features independent of the grasp)."""
        return self.prediction == "one_step" and self.featurizer.force_on == "contact_edges"

    def object_features(self, g: GraspGraph, num_object_nodes: int, num_object_edges: int) -> tuple:
        """Normalized features (network dtype) of the object part shared by the graphs of
        :meth:`forward_shared` (from graph 0): nodes (N, ·) and mesh edges (E_o, ·)."""
        if not self.shares_object_encoding:
            raise ValueError("forward_shared needs one-step prediction with force_on='contact_edges'")
        fz, N, E_o = self.featurizer, num_object_nodes, num_object_edges
        pos, node_type, closing = g.pos, g.node_type, g.closing_dir
        obj_node = self.node_norm(fz.node_features(node_type[:N], pos[:N], closing[:N]))
        log_e = torch.log10(g.youngs_modulus[:1].to(pos.dtype)).expand(E_o)
        obj_mesh = self.mesh_edge_norm(fz.mesh_edge_features(pos, g.mesh_edge_index[:, :E_o], log_e))
        return obj_node.to(self.network_dtype), obj_mesh.to(self.network_dtype)

    def object_latents(self, object_features: tuple) -> list[tuple[Tensor, Tensor]]:
        """Encoder latents of the object part (:meth:`object_features`), one pair per network: constants of
        the object, its modulus and the weights (a planner may keep them across batches)."""
        return [net.encode_object(*object_features) for net in self.networks]

    def shared_features(
        self,
        g: GraspGraph,
        num_object_nodes: int,
        num_object_edges: int,
        object_features: tuple | None = None,
    ) -> tuple:
        """Normalized features (network dtype) of :meth:`forward_shared`: object nodes (N, ·) and object mesh
        edges (E_o, ·) of graph 0 (or ``object_features`` as given, see :meth:`object_features`), finger
        nodes (G, n - N, ·), finger mesh edges (G, E_M / G - E_o, ·) and contact edges (E_C, ·)."""
        if not self.shares_object_encoding:
            raise ValueError("forward_shared needs one-step prediction with force_on='contact_edges'")
        fz = self.featurizer
        G, N, E_o = g.graph_count, num_object_nodes, num_object_edges
        n, per_graph_edges = g.num_nodes // G, g.mesh_edge_index.shape[1] // G
        pos, node_type, closing = g.pos, g.node_type, g.closing_dir
        dtype = pos.dtype
        net_dtype = self.network_dtype
        if object_features is None:
            object_features = self.object_features(g, N, E_o)
        obj_node, obj_mesh = object_features
        # the per-graph parts: finger nodes, finger mesh edges (log10 E channel zero), contact edges
        fin_node = fz.node_features(
            node_type.view(G, n)[:, N:], pos.view(G, n, 3)[:, N:], closing.view(G, n, 3)[:, N:]
        )
        fin_edges = g.mesh_edge_index.view(2, G, per_graph_edges)[:, :, E_o:].reshape(2, -1)
        fin_mesh = fz.mesh_edge_features(pos, fin_edges, pos.new_zeros(fin_edges.shape[1]))
        gforce = fz.graph_force(g).to(dtype)
        edge_force = gforce.index_select(0, g.node_graph().index_select(0, g.contact_edge_index[1]))
        contact = fz.contact_edge_features(pos, g.contact_edge_index, edge_force)
        fin_node = self.node_norm(fin_node).to(net_dtype)
        fin_mesh = self.mesh_edge_norm(fin_mesh).to(net_dtype).view(G, per_graph_edges - E_o, -1)
        contact = self.contact_edge_norm(contact).to(net_dtype)
        return obj_node, obj_mesh, fin_node, fin_mesh, contact

    def forward_shared(
        self,
        g: GraspGraph,
        num_object_nodes: int,
        num_object_edges: int,
        features: tuple | None = None,
        object_latents: list[tuple[Tensor, Tensor]] | None = None,
    ) -> Tensor:
        """:meth:`forward` of G graphs of one object that differ only in their fingers, contacts and forces,
        with the object part encoded once (see the module docstring); (n, 4) standardized outputs.

        The caller guarantees the layout of :func:`~defgraspnets.models.graph.build_grasp_batch`: every graph
        has ``n = g.num_nodes / G`` nodes, the first ``num_object_nodes`` being the same object nodes (same
        rest positions and types), and ``g.mesh_edge_index.shape[1] / G`` mesh edges, the first
        ``num_object_edges`` being the object's; and all graphs have the same Young's modulus. Needs
        :attr:`shares_object_encoding` and fitted normalizers (not checked here: no host sync).
        ``object_latents``: :meth:`object_latents` of this object and modulus, if kept from an earlier batch.
        """
        if features is None:
            features = self.shared_features(g, num_object_nodes, num_object_edges)
        obj_node, obj_mesh, fin_node, fin_mesh, contact = features
        if object_latents is None:
            object_latents = self.object_latents((obj_node, obj_mesh))
        mask = g.contact_edge_mask
        outs = [
            net(
                fin_node,
                fin_mesh,
                contact,
                g.mesh_edge_index,
                g.contact_edge_index,
                mask,
                object_latents=latents,
                node_graph=g.node_graph(),
                num_graphs=g.graph_count,
            )
            for net, latents in zip(self.networks, object_latents, strict=True)
        ]
        return (outs[0] if len(outs) == 1 else torch.cat(outs, dim=1)).to(g.pos.dtype)

    def to_physical(self, out: Tensor, g: GraspGraph) -> tuple[Tensor, Tensor]:
        """Standardized outputs (n, 4) -> von Mises stress (n,) [Pa], displacement (increment) (n, 3) [m]."""
        e_node = g.youngs_modulus[g.node_graph()].to(out.dtype)
        stress = self.scaling.stress_from_target(self.stress_norm.inverse(out[:, :1]).squeeze(1))
        disp = self.scaling.displacement_from_target(self.displacement_norm.inverse(out[:, 1:]), e_node)
        return stress, disp

    def fields(self, g: GraspGraph) -> tuple[Tensor, Tensor]:
        """Von Mises stress (n,) [Pa] and displacement (n, 3) [m] at force ``g.force`` from the first-contact
        state. Differentiable w.r.t. ``g.pos`` (finger node positions), ``g.force`` and ``g.youngs_modulus``.

        One-step: one pass. Multi-step: ``num_steps`` passes at forces ``F_g j / num_steps``; object nodes
        move by the predicted increments, each finger moves rigidly by the mean predicted increment of its
        nodes along its closing direction.
        """
        if self.prediction == "one_step":
            return self.to_physical(self.forward(g, g.pos), g)
        disp = torch.zeros_like(g.pos)
        is_finger = g.node_type == NODE_FINGER
        node_graph = g.node_graph()
        finger_key = node_graph * 2 + g.finger_id.clamp_min(0)
        nkeys = 2 * g.graph_count
        count = torch.zeros(nkeys, dtype=g.pos.dtype, device=g.pos.device).index_add_(
            0, finger_key[is_finger], torch.ones_like(finger_key[is_finger], dtype=g.pos.dtype)
        )
        stress = None
        for j in range(1, self.num_steps + 1):
            stress, inc = self.to_physical(self.forward(g, g.pos + disp, g.force * (j / self.num_steps)), g)
            along = (inc * g.closing_dir).sum(1)
            travel = torch.zeros(nkeys, dtype=inc.dtype, device=inc.device).index_add_(
                0, finger_key[is_finger], along[is_finger]
            ) / count.clamp_min(1.0)
            finger_inc = travel[finger_key].unsqueeze(1) * g.closing_dir
            disp = disp + torch.where(is_finger.unsqueeze(1), finger_inc, inc)
        return stress, disp
