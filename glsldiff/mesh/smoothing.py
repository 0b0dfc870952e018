"""Screened smoothing of vertex values along a triangle surface.

:func:`screened_smoothing` solves ``u - lambda^2 Lap_s u = q`` on the surface (``Lap_s`` the
Laplace-Beltrami operator, lambda a length in mm that may vary per vertex and per column):
the response to a point source is ``K0(r / lambda) / (2 pi lambda^2)``, so a step in ``q`` becomes
``1 - exp(-x / lambda) / 2`` across it (on a plane). Discretised with lumped vertex areas ``A``
and cotangent weights clipped at 0, ``(A + K_lambda) u = A q``: an M-matrix, so ``u`` is
non-negative where ``q`` is, a constant ``q`` is kept exactly and the area-weighted total
``sum A q`` is conserved. It follows the triangulation, so values never cross a thin gap
between two sheets of the surface (unlike a Euclidean kernel).
"""
from __future__ import annotations

from typing import Callable

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.sparse.linalg import factorized

from glsldiff.core.errors import InputError
from glsldiff.mesh.types import vertex_areas

__all__ = ["cotangent_edges", "screened_smoothing"]


def cotangent_edges(v: NDArray[np.float64], f: NDArray[np.int64]) -> tuple[NDArray, NDArray, NDArray]:
    """Interior-angle edge weights of the cotangent Laplacian: ``(i, j, w)`` with one row per
    triangle edge (an edge shared by two triangles appears twice; sum them), ``w = cot(angle
    opposite) / 2`` clipped at 0 (obtuse angles would give negative weights)."""
    v, f = np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64)
    I, J, W = [], [], []
    for o in range(3):
        i, j, m = f[:, (o + 1) % 3], f[:, (o + 2) % 3], f[:, o]
        a, b = v[i] - v[m], v[j] - v[m]
        cross = np.linalg.norm(np.cross(a, b), axis=1)
        cot = np.einsum("ij,ij->i", a, b) / np.maximum(cross, 1e-300)
        I.append(i)
        J.append(j)
        W.append(np.where(cross > 0.0, np.maximum(0.5 * cot, 0.0), 0.0))
    return np.concatenate(I), np.concatenate(J), np.concatenate(W)


def screened_smoothing(v: NDArray[np.float64], f: NDArray[np.int64],
                       length_mm: NDArray[np.float64]) -> Callable[[NDArray[np.float64]], NDArray[np.float64]]:
    """The map ``q (V, k) -> u (V, k)`` solving ``(A + K_lambda) u = A q`` column by column
    (module docstring), factorised once. ``length_mm``: lambda per vertex, ``(V,)`` or ``(V, k)``
    (one per column), mm, >= 0; an edge takes the mean of its ends' lambda^2. Vertices of no
    triangle keep their value."""
    v, f = np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64)
    lam = np.asarray(length_mm, dtype=np.float64)
    lam = lam[:, None] if lam.ndim == 1 else lam
    if lam.shape[0] != len(v) or not np.all(np.isfinite(lam)) or lam.min(initial=0.0) < 0.0:
        raise InputError(f"smoothing lengths: need {len(v)} finite values >= 0 per column, got shape "
                         f"{lam.shape}, min {np.nanmin(lam) if lam.size else 'none'}")
    area = vertex_areas(v, f)
    area = np.where(area > 0.0, area, 1.0)          # isolated vertices: u = q
    i, j, w = cotangent_edges(v, f)
    n = len(v)
    solves = []
    for c in range(lam.shape[1]):
        l2 = lam[:, c] ** 2
        we = w * 0.5 * (l2[i] + l2[j])
        W = sp.coo_matrix((we, (i, j)), shape=(n, n)).tocsr()
        W = W + W.T
        K = sp.diags(np.asarray(W.sum(axis=1)).ravel()) - W
        solves.append(factorized(sp.csc_matrix(sp.diags(area) + K)))

    def apply(q: NDArray[np.float64]) -> NDArray[np.float64]:
        q = np.asarray(q, dtype=np.float64)
        cols = q[:, None] if q.ndim == 1 else q
        if cols.shape[0] != n or (len(solves) > 1 and cols.shape[1] != len(solves)):
            raise InputError(f"smoothing: values of shape {q.shape} for {n} vertices and {len(solves)} lengths")
        out = np.column_stack([solves[min(c, len(solves) - 1)](area * cols[:, c]) for c in range(cols.shape[1])])
        return out.reshape(q.shape)
    return apply
