r"""The residual distance field: a hypernetwork that generates one small MLP per instance.

``F_n(p) = B_n(p) + R_n(p)`` with ``R_n(p) = r_max * sigmoid(G(x; phi_n) - shift) >= 0``, so the
surface stays inside its box. ``G`` is a small per-instance MLP (48 -> 16 -> 16 -> 16 -> 16 -> 1,
GELU, parameter-free layer norm before each hidden activation) whose 1617 weights
``phi_n = H(z_n; psi)`` come from a shared hypernetwork ``H`` (256 -> 4 x (256, LayerNorm, GELU)
-> 1617) applied to a learnable embedding ``z_n``. The input ``x`` is the box-local point
mirrored in x (left/right symmetry), scaled by ``1/100`` and encoded with 8 sinusoidal
frequencies ``2^k pi`` (48 features). The shifted sigmoid bounds the residual's reach by
``r_max``, which lets the integrators cull instances with a box enlarged by a known margin;
``shift`` (default 3) starts the residual near ``0.05 r_max`` so switching the field on does not
shrink every silhouette.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterator, Sequence

import drjit as dr
import drjit.nn as nn
import mitsuba as mi
import numpy as np

from ..common import concat, sigmoid
from .lattice import ResidualLattice
from .mlp import (FusedResidual, bucket_width, gelu, layer_norm_and_scale, layer_norm_cols, layer_norm_features,
                  row_major_view, tensor, weight_and_bias_index, gelu_and_slope)

@dataclass(frozen=True)
class ResidualConfig:
    """Architecture of the residual distance field (the paper's sizes, see the module docstring)."""

    embedding_dim: int = 256
    hyper_width: int = 256
    hyper_layers: int = 4
    mlp_width: int = 16
    mlp_layers: int = 4
    frequencies: int = 8
    input_scale: float = 0.01  # box-local metres -> encoder input
    max_residual: float = 1.0  # r_max (metres)
    shift: float = 3.0  # residual = r_max * sigmoid(g - shift)
    seed: int = 0
    #: How gradients reach the MLP's inputs and weights: ``"fused"`` (:class:`FusedResidual`: the
    #: forward pass one cooperative-vector kernel, the backward pass one kernel plus a GEMM per
    #: layer for the weights; LLVM only, other backends use ``"tensor"``) or ``"tensor"`` (Dr.Jit
    #: AD through tensor-mode matmuls, the reference the fused derivatives are tested against).
    gradients: str = "fused"

    @property
    def in_features(self) -> int:
        return 6 * self.frequencies

    def mlp_shapes(self) -> list[tuple[int, int]]:
        """(out, in) of each layer of the per-instance MLP G."""
        dims = [self.in_features] + [self.mlp_width] * self.mlp_layers + [1]
        return [(dims[i + 1], dims[i]) for i in range(len(dims) - 1)]

    def mlp_layout(self) -> list[tuple[int, int, int, int]]:
        """``(out, in, weight offset, bias offset)`` of each layer of G in its flat parameter
        vector (per layer the row-major weights, then the bias)."""
        layout, offset = [], 0
        for o, fi in self.mlp_shapes():
            layout.append((o, fi, offset, offset + o * fi))
            offset += o * fi + o
        return layout

    @property
    def num_mlp_params(self) -> int:
        return sum(o * i + o for o, i in self.mlp_shapes())



class ResidualField:
    """Hypernetwork-generated per-instance residual MLPs (see module docstring).

    Parameters (flat Dr.Jit arrays): ``embedding`` (N * D) and per hypernetwork layer ``hyper_w{i}``
    (out * in, row-major) and ``hyper_b{i}`` (out). Computations use transposed (features, n)
    tensors so per-point values come out contiguous.
    """

    def __init__(self, num_instances: int, cfg: ResidualConfig):
        self.cfg = cfg
        self.n = num_instances
        rng = np.random.default_rng(cfg.seed)
        self.params: dict[str, mi.Float] = {}
        self.params["embedding"] = mi.Float(
            rng.normal(0.0, 1.0, size=num_instances * cfg.embedding_dim).astype(np.float32))
        dims = [cfg.embedding_dim] + [cfg.hyper_width] * cfg.hyper_layers + [cfg.num_mlp_params]
        for i in range(len(dims) - 1):
            fan_in, fan_out = dims[i], dims[i + 1]
            bound = math.sqrt(6.0 / fan_in)  # Kaiming-uniform for GELU-ish activations
            if i == len(dims) - 2:
                bound *= 0.1  # small generated weights: G starts close to its biases
            w = rng.uniform(-bound, bound, size=(fan_out, fan_in)).astype(np.float32)
            self.params[f"hyper_w{i}"] = mi.Float(w.ravel())
            self.params[f"hyper_b{i}"] = mi.Float(np.zeros(fan_out, dtype=np.float32))
        self.num_hyper_layers = len(dims) - 1
        self._dims = dims
        #: per MLP layer where its ``[W | b]`` entries go in the parameter vector (the fused backward pass)
        self.weight_and_bias_index = [weight_and_bias_index(o, fi, w_at, b_at) for o, fi, w_at, b_at in cfg.mlp_layout()]

    def generate_weights(self) -> mi.TensorXf:
        """Hypernetwork forward for all instances: a (num_mlp_params, N) tensor."""
        x = tensor(self.params["embedding"], (self.n, self.cfg.embedding_dim))
        # (D, N) layout: transpose the embedding through a gather
        idx = dr.arange(mi.UInt32, self.n * self.cfg.embedding_dim)
        d = self.cfg.embedding_dim
        col = idx // self.n
        row = idx % self.n
        x = tensor(dr.gather(mi.Float, x.array, row * d + col), (d, self.n))
        for i in range(self.num_hyper_layers):
            out_f, in_f = self._dims[i + 1], self._dims[i]
            w = tensor(self.params[f"hyper_w{i}"], (out_f, in_f))
            b = tensor(dr.repeat(self.params[f"hyper_b{i}"], self.n), (out_f, self.n))
            x = w @ x + b
            if i < self.num_hyper_layers - 1:
                x = gelu(layer_norm_cols(x))
        return x

    def encode(self, p_local: mi.Vector3f) -> list[mi.Float]:
        """Mirrored, scaled sinusoidal encoding of box-local points: 48 feature arrays
        ``sin(2^k pi c), cos(2^k pi c)``, ``k = 0..frequencies-1``, per coordinate ``c``.

        One ``sincos`` per coordinate; the higher frequencies follow by the double-angle
        formulas ``sin 2a = 2 sin a cos a``, ``cos 2a = (cos a - sin a)(cos a + sin a)``: the
        fused residual MLP ran 1.15x faster than with a ``sincos`` per feature, residuals equal to
        1.2e-7 (each doubling at most doubles the rounding error: < 1e-5 in a feature at 8
        frequencies)."""
        cfg = self.cfg
        coords = [dr.abs(p_local.x) * cfg.input_scale, p_local.y * cfg.input_scale,
                  p_local.z * cfg.input_scale]
        feats = []
        for c in coords:
            s, co = dr.sincos(c * math.pi)
            for k in range(cfg.frequencies):
                feats += [s, co]
                if k + 1 < cfg.frequencies:
                    s, co = 2.0 * s * co, (co - s) * (co + s)
        return feats

    def evaluate(self, weights: mi.TensorXf, k: int, p_local: mi.Vector3f) -> mi.Float:
        """Residual ``R_k(p)`` (>= 0) at box-local points of instance ``k``."""
        return self.evaluate_grouped(weights, [k], [p_local])[0]

    def lattice(self, weights: mi.TensorXf, extents: np.ndarray, spacing: float) -> ResidualLattice:
        """Tabulate every instance's residual on a :class:`ResidualLattice` covering the box-local
        boxes of half sizes ``extents`` (``(N, 3)`` NumPy, margin included) at ``spacing``
        (detached; one fused MLP kernel per instance, sizes opaque: nothing recompiles when the
        boxes change)."""
        counts = ResidualLattice.node_counts(extents, spacing)
        sizes = counts.prod(axis=1)
        base = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        ext = np.asarray(extents, dtype=np.float32)
        low = [np.zeros(self.n, dtype=np.float32), -ext[:, 1], -ext[:, 2]]
        h = dr.opaque(mi.Float, spacing)
        with dr.suspend_grad():
            points = []
            for k in range(self.n):
                ny, nz = dr.opaque(mi.UInt32, int(counts[k, 1])), dr.opaque(mi.UInt32, int(counts[k, 2]))
                idx = dr.arange(mi.UInt32, int(sizes[k]))
                yz = idx % (ny * nz)
                node = [idx // (ny * nz), yz // nz, yz % nz]
                points.append(mi.Vector3f(*[dr.fma(mi.Float(node[a]) - 1.0, h, dr.opaque(mi.Float, float(low[a][k])))
                                            for a in range(3)]))
            values = concat(self.evaluate_grouped(dr.detach(weights), list(range(self.n)), points))
            dr.eval(values)
        # from Python lists, evaluated: a width-1 array (one instance) made from a NumPy view is
        # read with the view's alignment, which the kernel's code (and its hash) records, so
        # the lookups compiled anew whenever that changed
        meta = ([mi.UInt32(base.tolist())] + [mi.UInt32(counts[:, a].tolist()) for a in range(3)]
                + [mi.Float(v.tolist()) for v in low])
        dr.make_opaque(*meta)
        return ResidualLattice(values, meta[0], tuple(meta[1:4]), tuple(meta[4:]),
                               dr.opaque(mi.Float, 1.0 / spacing), self.n)

    def evaluate_grouped(self, weights: mi.TensorXf, instances: Sequence[int],
                         points: Sequence[mi.Vector3f]) -> list[mi.Float]:
        """Residuals ``R_k`` of several instances (group ``g``: box-local points ``points[g]`` of
        instance ``instances[g]``).

        On the LLVM backend each group is one fused kernel of cooperative-vector matvecs
        (:meth:`evaluate_fused`: 1M points 0.084 s instead of 0.340 s in tensor mode, which writes
        and reads every layer's activations); where the weights or the points need a gradient it
        runs inside :class:`FusedResidual`, whose backward pass is written out (a coop matvec
        uses one weight matrix per kernel, and Dr.Jit's own coop backward accumulates the weight
        gradient with atomics, 2-3x slower than tensor mode on x86, ``docs/integrators.md``). Elsewhere,
        or with ``gradients="tensor"``, each group runs as tensor-mode matmuls
        (:meth:`evaluate_tensor`).
        """
        llvm = dr.backend_v(weights.array) == dr.JitBackend.LLVM
        want_w, want_p = dr.grad_enabled(weights), [dr.grad_enabled(p) for p in points]
        needs_grad = want_w or any(want_p)
        if not llvm or (needs_grad and self.cfg.gradients == "tensor"):
            return [self.evaluate_tensor(weights, k, p) for k, p in zip(instances, points)]
        if not needs_grad:
            out = [self.evaluate_fused(weights, k, p) for k, p in zip(instances, points)]
        else:
            out = [dr.custom(FusedResidual, weights, p, self, k, (want_w, wp))
                   for k, p, wp in zip(instances, points, want_p)]
        # each group in a kernel of its own: left lazy, two groups of equal width (instances
        # whose lanes happened to be as many) were evaluated together, in a kernel of both MLPs
        # that compiled anew whenever that happened (12 boxes, 1k rays: after warm-up)
        for r in out:
            dr.eval(r)
        return out

    def _layers(self, weights: mi.TensorXf, k: int) -> Iterator[tuple[int, int, mi.Float, mi.Float]]:
        """``(out, in, W, b)`` per layer of instance ``k``'s MLP (``W`` row-major), gathered from the
        hypernetwork's ``(num_mlp_params, N)`` output; ``k`` is opaque (one set of kernels for
        every instance)."""
        kk = dr.opaque(mi.UInt32, k)
        for o, fi, w_at, b_at in self.cfg.mlp_layout():
            w = dr.gather(mi.Float, weights.array, (w_at + dr.arange(mi.UInt32, o * fi)) * self.n + kk)
            b = dr.gather(mi.Float, weights.array, (b_at + dr.arange(mi.UInt32, o)) * self.n + kk)
            yield o, fi, w, b

    def output(self, g):
        """``R = r_max sigmoid(g - shift)`` from the MLP's output ``g``."""
        return self.cfg.max_residual * sigmoid(g - self.cfg.shift)

    def output_slope(self, g):
        """``dR/dg = r_max sigma (1 - sigma)`` at the MLP's output ``g`` (:meth:`output`)."""
        sg = sigmoid(g - self.cfg.shift)
        return self.cfg.max_residual * sg * (1.0 - sg)

    def instance_params(self, weights: mi.TensorXf, k: int) -> mi.TensorXf:
        """Instance ``k``'s column of the ``(num_mlp_params, N)`` weights: its MLP's parameters,
        per layer the row-major weights then the bias (:meth:`ResidualConfig.mlp_layout`)."""
        n_params = self.cfg.num_mlp_params
        return tensor(dr.gather(mi.Float, weights.array, dr.arange(mi.UInt32, n_params) * self.n
                                 + dr.opaque(mi.UInt32, k)), (n_params,))

    def trace(self, params: mi.TensorXf, feats: list[mi.Float]) -> tuple[list, list[tuple], mi.Float]:
        """The MLP ``G`` on encoded ``feats`` with instance parameters ``params`` (cooperative
        vectors), with what its derivatives need: per layer its input (a list of feature
        arrays), per hidden layer ``(normed, gelu slope, layer-norm scale)``, and the output ``g``."""
        layout = self.cfg.mlp_layout()
        inputs, hidden = [list(feats)], []
        for i, (o, fi, w_at, b_at) in enumerate(layout):
            z = list(nn.matvec(row_major_view(params, w_at, o, fi), nn.CoopVec(*inputs[-1]),
                               row_major_view(params, b_at, o, 1)))
            if i == len(layout) - 1:
                return inputs, hidden, z[0]
            normed, inv = layer_norm_and_scale(z)
            act = [gelu_and_slope(v) for v in normed]
            hidden.append((normed, [a[1] for a in act], inv))
            inputs.append([a[0] for a in act])
        raise AssertionError("the MLP has an output layer")

    def evaluate_fused(self, weights: mi.TensorXf, k: int, points: mi.Vector3f) -> mi.Float:
        """``R_k`` at ``points`` as one fused kernel (``drjit.nn`` cooperative vectors; primal
        only). Instance ``k``'s parameters are gathered into one row-major vector and each
        layer's weight matrix and bias are views into it (``nn.pack`` copied every layer in a
        kernel of its own: 17 kernels per call instead of 3, same values)."""
        return self.output(self.trace(self.instance_params(weights, k), self.encode(points))[2])

    def encoding_tangent(self, feats: list[mi.Float], p_local: mi.Vector3f,
                         dp: mi.Vector3f) -> list[mi.Float]:
        """The derivative of :meth:`encode` (values ``feats`` at ``p_local``) along ``dp``:
        ``d sin(w u) = w cos(w u) du``, ``d cos(w u) = -w sin(w u) du``, ``w = 2^k pi``,
        ``u`` the scaled (mirrored) coordinate."""
        du = self._coordinate_scales(p_local)
        out = []
        for a, d in enumerate((dp.x, dp.y, dp.z)):
            dua = du[a] * d
            for kf, w in enumerate(self._frequencies()):
                j = 2 * (a * self.cfg.frequencies + kf)
                out += [w * feats[j + 1] * dua, -w * feats[j] * dua]
        return out

    def encoding_adjoint(self, feats: list[mi.Float], p_local: mi.Vector3f,
                         dfeats: list[mi.Float]) -> mi.Vector3f:
        """The transpose of :meth:`encoding_tangent`: the gradient w.r.t. ``p_local`` of
        ``sum_j dfeats[j] feats[j]``."""
        du = self._coordinate_scales(p_local)
        out = []
        for a in range(3):
            acc = mi.Float(0.0)
            for kf, w in enumerate(self._frequencies()):
                j = 2 * (a * self.cfg.frequencies + kf)
                acc = dr.fma(w, dfeats[j] * feats[j + 1] - dfeats[j + 1] * feats[j], acc)
            out.append(acc * du[a])
        return mi.Vector3f(*out)

    def _frequencies(self) -> list[float]:
        return [math.pi * 2.0 ** kf for kf in range(self.cfg.frequencies)]

    def _coordinate_scales(self, p_local: mi.Vector3f) -> list:
        """``du/dp`` per axis of the encoded coordinates (x mirrored: its sign)."""
        scale = self.cfg.input_scale
        return [dr.select(p_local.x < 0.0, -scale, scale), scale, scale]

    def evaluate_tensor(self, weights: mi.TensorXf, k: int, points: mi.Vector3f) -> mi.Float:
        """``R_k`` at ``points``, padded to :func:`bucket_width`, the MLP as tensor matmuls (Dr.Jit
        AD differentiates it: the ``gradients="tensor"`` path and the reference of
        :class:`FusedResidual`'s derivatives).

        Kernel shapes depend only on the bucket, so a training loop compiles each layer once per
        bucket instead of once per step and instance (the point counts change every step)."""
        n = dr.width(points.x)
        # at least one padding lane: with none, the final gather of the n values is an identity
        # that Dr.Jit elides, fusing the output into its consumer: other kernels whenever a
        # group's count is exactly a power of two (a compile in the middle of a run)
        width = bucket_width(n + 1)
        coords = [concat([points[axis]], width) for axis in range(3)]
        feats = self.encode(mi.Vector3f(*coords))
        x = tensor(dr.concat(feats), (1, len(feats), width))
        layers = list(self._layers(weights, k))
        for i, (o, fi, w, b) in enumerate(layers):
            x = tensor(w, (1, o, fi)) @ x + tensor(b, (1, o, 1))
            if i < len(layers) - 1:
                x = gelu(layer_norm_features(x))
        return dr.gather(mi.Float, self.output(x.array), dr.arange(mi.UInt32, n))



