"""A per-instance table of the residual field on a box-local lattice, read back by tricubic interpolation."""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

def catmull_rom_weights(f: mi.Float) -> list[mi.Float]:
    """Weights of the four grid values ``v[i-1..i+2]`` of the Catmull-Rom spline at fraction
    ``f`` of cell ``[i, i+1]`` (C1; exact for quadratics)."""
    f2 = f * f
    f3 = f2 * f
    return [0.5 * (2.0 * f2 - f3 - f), dr.fma(1.5, f3, dr.fma(-2.5, f2, 1.0)),
            0.5 * (dr.fma(-3.0, f3, 4.0 * f2) + f), 0.5 * (f3 - f2)]


#: A lookup of :class:`ResidualLattice` (64 gathers) costs about this many fused residual MLP
#: evaluations: in the integrator's chord grids 20 ns a lookup against 83-92 ns a point for the
#: MLP, and 78-82 ns a lattice node (6 and 12 boxes, 16k rays, 2 cores).
LATTICE_LOOKUP_COST = 0.25


@dataclass(frozen=True)
class ResidualLattice:
    """Every instance's residual ``R_k`` tabulated on a regular grid over its box-local box
    enlarged by a margin, read back by tricubic Catmull-Rom interpolation
    (:meth:`ResidualField.lattice`; detached).

    ``R`` is a function of the box-local point alone, so one table per instance serves every
    ray of every frame: where many rays cross a box (large ray batches, full-image renders)
    tabulating it costs fewer MLP evaluations than evaluating it along each ray. The x axis
    holds ``|x|`` (the field's mirror symmetry) from 0; in the cell at ``|x| = 0`` the node at
    ``-h`` is replaced by the quadratic extrapolation of the three beyond it, so the kink of
    ``R(|x|)`` at the mirror plane stays exact. Per axis the nodes sit one spacing below the
    covered range and two above it (the spline's stencil).
    """

    values: mi.Float  #: the residual at every node, instance-major, then x, y, z (z fastest)
    base: mi.UInt32  #: per instance the index of its first node
    counts: tuple  #: per axis (x, y, z) a UInt32 of per-instance node counts
    low: tuple  #: per axis a Float of per-instance coordinates of node 1 (x: 0)
    inv_step: mi.Float  #: 1 / spacing (opaque)
    num_instances: int

    @staticmethod
    def node_counts(extents: np.ndarray, spacing: float) -> np.ndarray:
        """``(N, 3)`` node counts for boxes of half sizes ``extents`` (``(N, 3)``, margin
        included) at ``spacing``."""
        span = np.asarray(extents, dtype=np.float64) * np.array([1.0, 2.0, 2.0])
        return np.ceil(span / spacing).astype(np.int64) + 3

    def residual(self, inst: mi.UInt32, p_local: mi.Vector3f, active: mi.Bool | bool = True) -> mi.Float:
        """Interpolated ``R_inst(p_local)`` (0 on inactive lanes; points beyond the covered box
        read its border)."""
        active = mi.Bool(active) & (inst < self.num_instances)
        k = dr.select(active, inst, 0)
        axes = []
        for axis, coord in enumerate((dr.abs(p_local.x), p_local.y, p_local.z)):
            n = dr.gather(mi.UInt32, self.counts[axis], k)
            u = dr.clip(dr.fma(coord - dr.gather(mi.Float, self.low[axis], k), self.inv_step, 1.0),
                        1.0, mi.Float(n - 2))
            i = dr.minimum(mi.UInt32(u), n - 3)
            axes.append((i - 1, n, catmull_rom_weights(u - mi.Float(i))))
        (ix, _, wx), (iy, ny, wy), (iz, nz, wz) = axes
        # the cell at the mirror plane: quadratic extrapolation in place of the node at -h
        mirror = ix == 0
        w0 = wx[0]
        wx = [dr.select(mirror, 0.0, w0), dr.select(mirror, dr.fma(3.0, w0, wx[1]), wx[1]),
              dr.select(mirror, dr.fma(-3.0, w0, wx[2]), wx[2]), dr.select(mirror, wx[3] + w0, wx[3])]
        base = dr.gather(mi.UInt32, self.base, k)
        out = mi.Float(0.0)
        for a in range(4):
            for b in range(4):
                row = base + ((ix + a) * ny + iy + b) * nz + iz
                line = mi.Float(0.0)
                for c in range(4):
                    line = dr.fma(wz[c], dr.gather(mi.Float, self.values, row + c, active), line)
                out = dr.fma(wx[a] * wy[b], line, out)
        return out


# ----------------------------------------------------------------------------------------------
# The instance field: boxes (+ velocity) (+ residual)
# ----------------------------------------------------------------------------------------------


