r"""The residual field's per-instance MLP: activations, layer norm and hand-written derivatives.

On the LLVM backend each instance's MLP runs as one fused kernel of cooperative-vector matvecs
(:meth:`~vsrd_plugins.sdf.residual.ResidualField.evaluate_grouped`); where a gradient is needed
:class:`FusedResidual` writes its derivatives out (one kernel for the adjoints, a GEMM per layer
for the weight gradient), because a cooperative-vector matvec uses one weight matrix per kernel
and Dr.Jit's own backward pass of it accumulates weight gradients with atomics, 2-3x slower than
tensor mode on x86 (``docs/integrators.md``, "Residual MLP").
"""

from __future__ import annotations

import drjit as dr
import drjit.nn as nn
from drjit.auto.ad import ArrayXf
import mitsuba as mi
import numpy as np

from ..common import sigmoid

#: ``2 sqrt(2 / pi)``: GELU's tanh approximation written with the logistic function.
GELU_SCALE = 1.5957691216057308
#: The cubic coefficient of GELU's tanh approximation.
GELU_CUBIC = 0.044715


def gelu_gate(x):
    return sigmoid(GELU_SCALE * dr.fma(GELU_CUBIC * x, x * x, x))


def gelu(x):
    """GELU, tanh approximation (Hendrycks & Gimpel):
    ``0.5 x (1 + tanh(sqrt(2/pi) (x + 0.044715 x^3)))``, evaluated as the identical
    ``x sigmoid(2 sqrt(2/pi) (x + 0.044715 x^3))`` (``(1 + tanh z) / 2 = sigmoid(2 z)``): one
    ``exp`` instead of ``tanh``'s longer sequence; the fused residual MLP ran 1.1x faster."""
    return x * gelu_gate(x)


def gelu_and_slope(x):
    """:func:`gelu` and its derivative ``g + x g (1 - g) 2 sqrt(2/pi) (1 + 3 0.044715 x^2)``
    (``g`` the sigmoid gate), for hand-written derivatives (:class:`FusedResidual`)."""
    g = gelu_gate(x)
    return x * g, g + x * g * (1.0 - g) * GELU_SCALE * dr.fma(3.0 * GELU_CUBIC, x * x, 1.0)


def tensor(values, shape) -> mi.TensorXf:
    return mi.TensorXf(values, shape=tuple(shape))


#: Layer norm's variance floor (the hypernetwork's and the MLP's).
LAYER_NORM_EPS = 1e-5


def layer_norm_cols(x: mi.TensorXf, eps: float = LAYER_NORM_EPS) -> mi.TensorXf:
    """Parameter-free layer norm over axis 0 of a (features, n) tensor."""
    mean = dr.mean(x, axis=0)
    xc = x - mean
    var = dr.mean(xc * xc, axis=0)
    return xc / dr.sqrt(var + eps)


def layer_norm(values: list[mi.Float], eps: float = LAYER_NORM_EPS) -> list[mi.Float]:
    """Parameter-free layer norm of one feature vector per lane (a list of feature arrays); the
    per-lane form of :func:`layer_norm_features` (``test_residual_fused_forward_matches_tensor_mode``
    checks they agree)."""
    return layer_norm_and_scale(values, eps)[0]


def layer_norm_and_scale(values: list[mi.Float], eps: float = LAYER_NORM_EPS) -> tuple[list[mi.Float], mi.Float]:
    """:func:`layer_norm` and its per-lane scale ``1 / sqrt(var + eps)``."""
    mean = sum(values) * (1.0 / len(values))
    centred = [v - mean for v in values]
    inv = dr.rsqrt(sum(c * c for c in centred) * (1.0 / len(values)) + eps)
    return [c * inv for c in centred], inv


def layer_norm_derivative(normed: list[mi.Float], inv: mi.Float, dx: list[mi.Float]) -> list[mi.Float]:
    """The derivative of :func:`layer_norm` (output ``normed``, scale ``inv``) applied to ``dx``:
    ``inv (dx - mean(dx) - y mean(dx y))``. The Jacobian is symmetric, so this is both the
    forward (tangent) and the backward (adjoint) map."""
    k = 1.0 / len(dx)
    m1 = sum(dx) * k
    m2 = sum(a * y for a, y in zip(dx, normed)) * k
    return [inv * (a - m1 - y * m2) for a, y in zip(dx, normed)]


def layer_norm_features(x: mi.TensorXf, eps: float = LAYER_NORM_EPS) -> mi.TensorXf:
    """Parameter-free layer norm over axis 1 (features) of a (groups, features, n) tensor."""
    g, _, n = x.shape
    mean = tensor(dr.mean(x, axis=1).array, (g, 1, n))
    xc = x - mean
    var = tensor(dr.mean(xc * xc, axis=1).array, (g, 1, n))
    return xc / dr.sqrt(var + eps)


def row_major_view(buffer: mi.TensorXf, offset: int, rows: int, cols: int) -> nn.MatrixView:
    """A ``rows x cols`` row-major matrix view of the 1-D ``buffer`` from element ``offset``."""
    view = nn.view(buffer)
    view.offset, view.shape, view.stride, view.size = offset, (rows, cols), cols, rows * cols
    return view


#: Smallest padded group width of the batched residual MLP.
MIN_BUCKET = 256


def bucket_width(n: int) -> int:
    """Padded width for ``n`` points: the next power of two, at least :data:`MIN_BUCKET`.

    Finer buckets (``2^k * (1, 1.25, 1.5, 1.75)``, at most 25 % padding) made the integrator
    benchmark's residual step 17 % faster, but an optimisation run compiled 1.7x as many kernels
    (each bucket is a kernel shape) and its residual steps were 9 % slower."""
    return max(MIN_BUCKET, 1 << max(int(n) - 1, 0).bit_length())


def weight_and_bias_index(o: int, fi: int, w_at: int, b_at: int) -> mi.UInt32:
    """Where the entries of a layer's ``(o, fi + 1)`` matrix ``[W | b]`` sit in its MLP's
    parameter vector (row-major weights at ``w_at``, the bias at ``b_at``)."""
    i, j = np.divmod(np.arange(o * (fi + 1)), fi + 1)
    index = mi.UInt32(np.where(j < fi, w_at + i * fi + j, b_at + i).tolist())  # from a list: aligned
    dr.make_opaque(index)
    return index


class FusedResidual(dr.CustomOp):
    r"""``R_k`` at box-local points with hand-written derivatives (:meth:`ResidualField.evaluate_grouped`
    on LLVM where a gradient is needed).

    Inputs: the hypernetwork's ``(num_mlp_params, N)`` weights, the points ``p`` (either may carry
    gradients), the field, the instance ``k`` and which of the two carry gradients. The value is :meth:`ResidualField.evaluate_fused`.
    With the MLP ``z_l = W_l a_{l-1} + b_l``, ``a_l = gelu(LN(z_l))`` (``a_0`` the encoding of
    ``p``), ``R = r_max sigmoid(z_L - shift)``, the backward pass is one kernel per call that
    recomputes the layers and runs the adjoints down them,

    .. math::

        \delta z_L = \delta R\, r_{max}\, \sigma (1 - \sigma), \quad
        \delta a_{l-1} = W_l^\top \delta z_l, \quad
        \delta z_{l-1} = LN'(gelu'(n_{l-1}) \odot \delta a_{l-1}),

    writing ``a_{l-1}`` and ``\delta z_l`` (point-major tables ``A_{l-1}``, ``\Delta_l``) and
    ``\delta p`` (the encoding's adjoint); the weight gradient is then a GEMM per layer,
    ``[dW_l | db_l] = \Delta_l^\top [A_{l-1} | 1]``, scattered into column ``k``.
    The forward (tangent) pass is the same recursion upwards:
    ``\dot z_l = W_l \dot a_{l-1} + \dot W_l a_{l-1} + \dot b_l``.

    Tensor-mode AD of the same MLP (:meth:`ResidualField.evaluate_tensor`) writes and reads
    every layer's activations in kernels of their own and pads each group to a bucket: on 6 x
    14k points (the integrator benchmark's adaptive step) forward + backward took 0.28 s in
    tensor mode and 0.09 s here, hypernetwork included; gradients agree to 1e-6
    (``test_fused_residual_derivatives_match_tensor_mode``).
    """

    def eval(self, weights, points, field, k, wants):
        # the inputs arrive detached: ``wants`` says which of them carry a gradient
        self.weights, self.points, self.field, self.k, self.wants = weights, points, field, k, wants
        return field.evaluate_fused(weights, k, points)

    def forward(self):
        f = self.field
        params = f.instance_params(self.weights, self.k)
        tangent = f.instance_params(self.grad_in("weights"), self.k)
        feats = f.encode(self.points)
        inputs, hidden, g = f.trace(params, feats)
        dx = f.encoding_tangent(feats, self.points, mi.Vector3f(self.grad_in("points")))
        for i, ((o, fi, w_at, b_at), x) in enumerate(zip(f.cfg.mlp_layout(), inputs)):
            dz = [a + b for a, b in zip(nn.matvec(row_major_view(params, w_at, o, fi), nn.CoopVec(*dx)),
                                        nn.matvec(row_major_view(tangent, w_at, o, fi), nn.CoopVec(*x),
                                                  row_major_view(tangent, b_at, o, 1)))]
            if i < len(hidden):
                normed, slope, inv = hidden[i]
                dx = [sl * d for sl, d in zip(slope, layer_norm_derivative(normed, inv, dz))]
        self.set_grad_out(f.output_slope(g) * dz[0])

    def backward(self):
        f = self.field
        n_points = dr.width(self.points.x)
        want_w, want_p = self.wants
        params = f.instance_params(self.weights, self.k)
        feats = f.encode(self.points)
        inputs, hidden, g = f.trace(params, feats)
        dz = [self.grad_out() * f.output_slope(g)]
        layout = f.cfg.mlp_layout()
        deltas = [None] * len(layout)
        for i in range(len(layout) - 1, -1, -1):
            o, fi, w_at, _ = layout[i]
            deltas[i] = dz
            da = list(nn.matvec(row_major_view(params, w_at, o, fi), nn.CoopVec(*dz), transpose=True))
            if i > 0:
                normed, slope, inv = hidden[i - 1]
                dz = layer_norm_derivative(normed, inv, [sl * a for sl, a in zip(slope, da)])
        dp = f.encoding_adjoint(feats, self.points, da) if want_p else None
        if want_w and n_points:
            # point-major (points, features) tables in the same kernel as dp (dr.ravel, order
            # "F": one kernel, the width opaque; order "C" bakes it in, scatters into one buffer
            # ran one kernel each)
            ones = dr.full(mi.Float, 1.0, n_points)  # a last input column: the bias gradient
            a_tab = [dr.ravel(ArrayXf(x + [ones]), order="F") for x in inputs]
            d_tab = [dr.ravel(ArrayXf(d), order="F") for d in deltas]
            dr.eval(a_tab, d_tab, dp)
            grad = dr.zeros(mi.Float, f.cfg.num_mlp_params)
            for (o, fi, _, _), index, a, d in zip(layout, f.weight_and_bias_index, a_tab, d_tab):
                wb = dr.matmul(tensor(d, (n_points, o)), tensor(a, (n_points, fi + 1)), At=True)
                dr.scatter(grad, wb.array, index)
            column = dr.zeros(mi.Float, f.cfg.num_mlp_params * f.n)
            dr.scatter(column, grad, dr.arange(mi.UInt32, f.cfg.num_mlp_params) * f.n
                       + dr.opaque(mi.UInt32, self.k))
            self.set_grad_in("weights", tensor(column, self.weights.shape))
        if want_p:
            # evaluated here (with the weights' tables above, or alone): left lazy, two
            # instances' backward passes of equal width ran as one kernel of both
            dr.eval(dp)
            self.set_grad_in("points", dp)

    def name(self):
        return "FusedResidual"


