"""Material onto polygrid nodes, and boundary-node values onto mesh vertices (section 5.2).

Materials come as a constant, a regular volume in object space (:class:`VolumeField`,
trilinear interpolation) or a function of position; each is evaluated at the polygrid's
node positions. Radiance computed at boundary nodes goes to the mesh vertices by
Shepard (inverse-distance) interpolation over the nearest boundary nodes.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Union

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import map_coordinates
from scipy.spatial import cKDTree

from glsldiff.core.errors import InputError
from glsldiff.grids.polygrid import Polygrid


@dataclass(frozen=True)
class VolumeField:
    """Values on a regular grid in object space.

    Attributes
    ----------
    values
        ``(nz, ny, nx)`` or ``(nz, ny, nx, 3)`` samples (e.g. kappa in mm, mu in mm^-1).
    origin
        Position of sample ``[0, 0, 0]``, mm (x, y, z).
    spacing
        Sample spacing, mm (scalar or per axis x, y, z).
    """

    values: NDArray[np.float64]
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    spacing: float | tuple[float, float, float] = 1.0

    def __call__(self, positions: NDArray[np.float64]) -> NDArray[np.float64]:
        """Trilinear interpolation at ``(N, 3)`` positions (clamped at the volume's faces)."""
        vals = np.asarray(self.values, dtype=np.float64)
        if vals.ndim == 3:
            vals = vals[..., None]
        if vals.ndim != 4 or vals.shape[3] not in (1, 3) or min(vals.shape[:3]) < 1:
            raise InputError(f"VolumeField values have shape {np.shape(self.values)}; expected (nz, ny, nx)[, 3]")
        idx = (positions - np.asarray(self.origin, dtype=np.float64)) / np.asarray(self.spacing, dtype=np.float64)
        coords = idx[:, ::-1].T  # (z, y, x)
        return np.stack([map_coordinates(vals[..., c], coords, order=1, mode="nearest")
                         for c in range(vals.shape[3])], axis=1)


Field = Union[float, ArrayLike, VolumeField, Callable[[NDArray[np.float64]], ArrayLike]]


def sample_field(pg: Polygrid, field: Field, name: str = "field") -> NDArray[np.float64]:
    """``field`` at every active node, as a ``shape + (3,)`` node array (removed nodes: 0)."""
    out = np.zeros((pg.size, 3))
    act = np.flatnonzero(pg.active.ravel())
    if callable(field):
        vals = np.asarray(field(pg.positions[act]), dtype=np.float64)
        if vals.shape == (act.size,):
            vals = vals[:, None]
        if vals.shape not in ((act.size, 1), (act.size, 3)):
            raise InputError(f"{name}(positions) returned shape {vals.shape}; expected ({act.size},) or ({act.size}, 3)")
        out[act] = vals
    else:
        arr = np.asarray(field, dtype=np.float64)
        if arr.shape not in ((), (3,)):
            raise InputError(f"{name} must be a scalar, an RGB triple, a VolumeField or a function of "
                             f"position; got an array of shape {arr.shape}")
        out[act] = arr
    if not np.all(np.isfinite(out[act])):
        raise InputError(f"{name} is not finite at {int((~np.isfinite(out[act])).any(axis=1).sum())} nodes")
    return out.reshape(pg.shape + (3,))


def sample_material(pg: Polygrid, kappa: Field, mu: Field) -> tuple[NDArray, NDArray]:
    """kappa (mm) and mu (mm^-1) node arrays for :class:`glsldiff.system.problem.DiffusionProblem`."""
    return sample_field(pg, kappa, "kappa"), sample_field(pg, mu, "mu")


def to_vertices(pg: Polygrid, values: ArrayLike, vertices: ArrayLike, k: int = 8,
                power: float = 2.0) -> NDArray[np.float64]:
    """Interpolate ``(n_boundary, c)`` boundary-node values to ``(V, 3)`` mesh vertices.

    Shepard interpolation over the ``k`` nearest boundary nodes with weights
    ``1 / distance^power``; a vertex on a node takes its value.
    """
    vals = np.asarray(values, dtype=np.float64)
    if vals.shape[0] != pg.n_boundary:
        raise InputError(f"values have {vals.shape[0]} rows; the polygrid has {pg.n_boundary} boundary nodes")
    verts = np.asarray(vertices, dtype=np.float64)
    if verts.ndim != 2 or verts.shape[1] != 3:
        raise InputError(f"vertices must be (V, 3), got {verts.shape}")
    k = min(k, pg.n_boundary)
    dist, idx = cKDTree(pg.boundary_positions).query(verts, k=k)
    if k == 1:
        dist, idx = dist[:, None], idx[:, None]
    w = 1.0 / np.maximum(dist, 1e-12 * max(pg.lattice.h, 1e-300)) ** power
    w /= w.sum(axis=1, keepdims=True)
    flat = vals.reshape(pg.n_boundary, -1)
    out = np.einsum("vk,vkc->vc", w, flat[idx])
    return out.reshape((len(verts),) + vals.shape[1:])
