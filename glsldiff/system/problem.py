"""A validated forward-diffusion problem on a grid (regular or polygrid), shared by every solver.

The continuous problem (Wang et al. 2008, eqs. 1-2), with outward normal n::

    div(kappa grad phi) - mu phi = 0          in V
    phi + 2 C kappa dphi/dn      = q          on A

is discretised on a :class:`~glsldiff.grids.regular.RegularGrid` (eq. 8) in one of two forms:

``stencil="paper"`` (faithful to eq. 8, after Stam 1995)
    unknown ``u = kappa phi``; interior row ``sum_j u_j - (6 + h^2 mu_i/kappa_i) u_i = 0``.
    This discretises ``Laplacian(kappa phi)``, which equals ``div(kappa grad phi)``
    only where kappa is constant.
``stencil="conservative"``
    unknown ``phi``; interior row ``sum_j k_ij (phi_j - phi_i) - h^2 mu_i phi_i = 0``
    with the face coefficient ``k_ij`` the arithmetic (default) or harmonic mean of
    ``kappa_i`` and ``kappa_j``: a flux-conservative discretisation of ``div(kappa grad phi)``.

Both use the boundary row ``phi_b + 2 C kappa_b (phi_b - phi_j) / d = q_b`` with
``d = h`` and ``j`` the interior partner of boundary node ``b``.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal, Mapping

import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff.core.checks import choice
from glsldiff.core.errors import InputError
from glsldiff.grids.graph import NodeGraph
from glsldiff.grids.hierarchy import Hierarchy
from glsldiff.grids.polygrid import Polygrid
from glsldiff.grids.regular import RegularGrid
from glsldiff.physics.exitance import EXITANT, exitant_bracket, source_from_irradiance
from glsldiff.physics.material import validate_coefficients
from glsldiff.physics.optics import boundary_constant, fresnel_transmittance


Stencil = Literal["paper", "conservative"]
FaceMean = Literal["arithmetic", "harmonic"]
STENCILS = ("paper", "conservative")
FACE_MEANS = ("arithmetic", "harmonic")


def _as_volume(name: str, values: ArrayLike, shape: tuple[int, ...]) -> NDArray[np.float64]:
    """A scalar, an RGB triple or a per-node array as a ``shape + (3,)`` volume."""
    arr = np.asarray(values, dtype=np.float64)
    if arr.ndim == 0 or arr.shape == (3,):
        return np.broadcast_to(arr, shape + (3,))
    if arr.shape == shape:
        return np.broadcast_to(arr[..., None], shape + (3,))
    if arr.shape == shape + (3,):
        return arr
    raise InputError(f"{name} has shape {arr.shape}; the grid needs a scalar, (3,), {shape} or {shape + (3,)}")


@dataclass
class DiffusionProblem:
    """Grid, material, boundary source and discretisation choices, validated.

    Parameters
    ----------
    grid
        The regular grid (spacing ``grid.h`` in mm).
    kappa, mu
        Diffusion coefficient (mm) and absorption (mm^-1) per node: shape
        ``(nz, ny, nx)`` or ``(nz, ny, nx, 3)``, or scalars / ``(3,)`` for homogeneous.
    q
        Boundary source (see ``grid.source_volume``: face arrays on a regular grid,
        per-boundary-node values on a polygrid); defaults to zero.
    eta
        Relative refractive index (used for ``F_t`` in the exitant radiance and, when
        ``C`` is not given, ``C = boundary_constant(eta)``).
    C
        Boundary constant ``(1 + Fdr)/(1 - Fdr)``; pass ``glsldiff.physics.optics.PAPER_C``
        to reproduce the paper's 2.1489.
    stencil, face_mean
        Interior discretisation (module docstring).
    exitant
        Source and exitance convention of :meth:`exitant_radiance` (and the solve reports'
        ``radiance``): ``"p1"`` (default; ``q`` is then the Marshak source ``4 E_t / (1 - Fdr)``
        of transmitted irradiance ``E_t``, and the radiance matches Monte Carlo on slabs to
        0.97-1.02x), ``"arbree"``, or ``"paper"`` (``q = E_t``, the paper's net flux).
        :meth:`from_irradiance` builds ``q`` from ``E_t`` for the chosen convention.
    """

    grid: "RegularGrid | Polygrid"
    kappa: ArrayLike
    mu: ArrayLike
    q: ArrayLike | Mapping[str, ArrayLike] | None = None
    eta: float = 1.3
    C: float | None = None
    stencil: Stencil = "paper"
    face_mean: FaceMean = "arithmetic"
    exitant: str = "p1"

    @classmethod
    def from_irradiance(cls, grid: "RegularGrid | Polygrid", kappa: ArrayLike, mu: ArrayLike,
                        irradiance: ArrayLike | Mapping[str, ArrayLike], eta: float = 1.3,
                        exitant: str = "p1", **options: object) -> "DiffusionProblem":
        """The problem lit by transmitted irradiance ``E_t`` (same layout as ``q``: face arrays
        or per boundary node), with ``q = source_from_irradiance(E_t, eta, exitant)``."""
        return cls(grid, kappa, mu, q=_source_of(irradiance, eta, exitant), eta=eta, exitant=exitant,
                   **options)  # type: ignore[arg-type]

    def with_irradiance(self, irradiance: ArrayLike | Mapping[str, ArrayLike]) -> "DiffusionProblem":
        """Same grid, material and options, lit by transmitted irradiance ``E_t``."""
        return replace(self, q=_source_of(irradiance, self.eta, self.exitant))

    def __post_init__(self) -> None:
        if not hasattr(self.grid, "source_volume"):
            raise InputError(f"grid must be a RegularGrid or a Polygrid, got {type(self.grid).__name__}")
        shape = self.grid.shape
        kappa = _as_volume("kappa", self.kappa, shape)
        mu = _as_volume("mu", self.mu, shape)
        if not isinstance(self.grid, RegularGrid):
            # removed polygrid nodes hold placeholders so that packed textures stay finite
            dead = ~self.grid.active
            kappa, mu = kappa.copy(), mu.copy()
            kappa[dead], mu[dead] = 1.0, 0.0
        self.kappa, self.mu = validate_coefficients(kappa, mu)
        self.q = self.grid.source_volume(self.q)
        self.C = boundary_C(self.eta, self.C)
        choice(self.stencil, "stencil", STENCILS)
        choice(self.face_mean, "face_mean", FACE_MEANS)
        choice(self.exitant, "exitant", EXITANT)

    # ---- derived quantities ------------------------------------------------------
    @property
    def graph(self) -> "NodeGraph":
        """Node connectivity of the discretisation (:mod:`glsldiff.grids.graph`)."""
        return self.grid.graph

    @property
    def node_shape(self) -> tuple[int, ...]:
        """Shape of the node arrays (``(nz, ny, nx)`` or a polygrid's ``(cubes, n, n, n)``)."""
        return tuple(self.grid.shape)

    @property
    def unknown(self) -> str:
        """What a solver iterates on: ``"kappa*phi"`` (paper) or ``"phi"``."""
        return "kappa*phi" if self.stencil == "paper" else "phi"

    def to_phi(self, x: NDArray) -> NDArray:
        """Convert the iterated unknown (volume) to fluence phi."""
        return x / self.kappa if self.stencil == "paper" else x

    def from_phi(self, phi: NDArray) -> NDArray:
        """Convert fluence phi (volume) to the iterated unknown."""
        return phi * self.kappa if self.stencil == "paper" else phi

    def with_q(self, q: ArrayLike | Mapping[str, ArrayLike]) -> "DiffusionProblem":
        """Same grid, material and options, new boundary source."""
        return replace(self, q=q)

    def exitant_radiance(self, phi: NDArray, cos_o: float = 1.0) -> dict[str, NDArray] | NDArray:
        """Multiple-scattering radiance leaving each face (regular grid: dict of face
        arrays) or each boundary node (polygrid: ``(n_boundary, 3)``), per channel:
        ``L = F_t(eta, cos_o) B`` with the bracket ``B = a phi - b q`` of :attr:`exitant`
        (:mod:`glsldiff.physics.exitance`, with this problem's ``C``); ``cos_o`` is the
        cosine of the viewing direction (1 = along the normal).

        ``"p1"`` is the P1 radiance refracted out, the form calibrated against Monte Carlo.
        ``"paper"`` is paper eq. 3 with the boundary condition, ``(phi - q) / (2 pi)`` =
        ``-(C/pi) kappa dphi/dn``: the *net* flux, negative where light enters (phi < q), so
        meaningful on unlit faces only (the paper's setup).
        """
        ft = float(fresnel_transmittance(self.eta, cos_o))
        L = ft * exitant_bracket(phi, self.q, self.eta, self.exitant, self.C)
        return self.grid.boundary_values(L)


def _source_of(irradiance: ArrayLike | Mapping[str, ArrayLike], eta: float,
               exitant: str) -> NDArray[np.float64] | dict[str, NDArray[np.float64]]:
    """``source_from_irradiance`` of an array or of each face array of a mapping."""
    if isinstance(irradiance, Mapping):
        return {k: source_from_irradiance(v, eta, exitant) for k, v in irradiance.items()}
    return source_from_irradiance(irradiance, eta, exitant)


def boundary_C(eta: float, C: float | None) -> float:
    """The boundary constant of a problem: ``C``, or ``boundary_constant(eta)`` when ``None``;
    InputError unless ``eta`` and the result are finite and > 0."""
    if not np.isfinite(eta) or eta <= 0:
        raise InputError(f"eta={eta!r} must be a finite relative index > 0")
    C = float(boundary_constant(eta)) if C is None else C
    if not np.isfinite(C) or C <= 0:
        raise InputError(f"C={C!r} must be finite and > 0")
    return float(C)


def relative_l2(x: ArrayLike, ref: ArrayLike, mask: NDArray[np.bool_] | None = None) -> float:
    """``||x - ref||_2 / ||ref||_2`` over all (masked) nodes and channels; 0 if both vanish."""
    x, ref = np.asarray(x, dtype=np.float64), np.asarray(ref, dtype=np.float64)
    if mask is not None:
        x, ref = x[mask], ref[mask]
    den = float(np.linalg.norm(ref))
    num = float(np.linalg.norm(x - ref))
    if den == 0.0:
        return 0.0 if num == 0.0 else float("inf")
    return num / den


def level_problems(hierarchy: Hierarchy, problem: DiffusionProblem) -> list[DiffusionProblem]:
    """``problem`` (on the hierarchy's finest grid) and its restriction to every coarser level:
    kappa and mu by the transfers' ``restrict_all``, q by ``restrict_kind`` (boundary from
    boundary nodes), see :class:`glsldiff.grids.hierarchy.Transfer`."""
    if problem.grid is not hierarchy.grids[0]:
        raise InputError("the problem is not on this hierarchy's finest grid")
    out = [problem]
    for t, g in zip(hierarchy.transfers, hierarchy.grids[1:]):
        p = out[-1]
        kappa = (t.restrict_all @ p.kappa.reshape(-1, 3)).reshape(g.shape + (3,))
        mu = (t.restrict_all @ p.mu.reshape(-1, 3)).reshape(g.shape + (3,))
        q = (t.restrict_kind @ p.q.reshape(-1, 3)).reshape(g.shape + (3,))
        out.append(DiffusionProblem(g, kappa, mu, q, eta=p.eta, C=p.C, stencil=p.stencil,
                                    face_mean=p.face_mean))
    return out
