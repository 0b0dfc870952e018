"""The fit objective f_M of one channel and its adjoint gradient (paper section 4.2-4.3).

::

    f(kappa, mu) = sum_m sum_x W_xm (L_m(x) - Y_m(x))^2 / sum W Y^2  +  lambda sum_x |grad kappa(x)|^2
                   +  lambda_mu sum_edges w_axis (ln mu_i - ln mu_j)^2

``L_m`` is the predicted radiance (:mod:`glsldiff.inverse.model`), ``Y_m`` the measurement,
``W`` the mask. Both terms are dimensionless. The data term is normalised by the measured
energy, so the paper's stop criterion ``f_M < 1e-4 sum L_o^2`` reads ``f < 1e-4`` and
``lambda`` does not depend on the camera's exposure scale (the paper leaves the data term
unnormalised, in unstated units). The regulariser is the paper's sum over nodes of
``|grad kappa|^2`` (forward differences, kappa in mm, gradient in mm^-1); with the
normalised data term the paper's lambda = 1e-4 ... 1e-6 spans too smooth ... too noisy
(see the regularisation study in docs/guide/inverse.md). The optional second regulariser
(``lam_mu``, off by default in :class:`Objective`) smooths the absorption: squared differences
of ``ln mu`` over the lattice edges between interior nodes (the nodes that carry mu),
scale-free like the log variables the minimisers use; edges along z weigh ``depth_weight``
times the in-plane ones (surface measurements resolve the absorption in depth worst).

The gradient costs one factorisation (or, with the pyamg solver, one multigrid hierarchy), M
forward and M adjoint solves (all with the same factor or hierarchy) and is exact for this
discrete objective (with pyamg: to its solve tolerance).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from glsldiff.core.checks import real
from glsldiff.core.errors import InputError
from glsldiff.grids.graph import INTERIOR
from glsldiff.inverse.model import ForwardModel, edge_difference_matrix, regularizer_matrix

Array = NDArray[np.float64]


@dataclass
class Evaluation:
    """One evaluation of f: total, its two terms, and (optionally) the gradient."""

    value: float
    data: float
    reg: float  # sum |grad kappa|^2
    grad_kappa: Array | None = None
    grad_mu: Array | None = None
    reg_mu: float = 0.0  # sum w (ln mu_i - ln mu_j)^2


@dataclass
class Objective:
    """f_M of one channel for sources ``Q``, measurements ``Y`` and weights ``W`` (each
    ``(n_boundary, M)`` in the model's boundary order)."""

    model: ForwardModel
    Q: Array
    Y: Array
    W: Array
    lam: float = 1e-5
    lam_mu: float = 0.0          # weight of the ln-mu smoothness term
    depth_weight: float = 1.0    # its z-edges weigh this many times the in-plane ones
    evaluations: int = 0
    gradients: int = 0
    trace: list[tuple[float, float, float]] = field(default_factory=list)  # (seconds, value, data)

    def __post_init__(self) -> None:
        nb = self.model.n_boundary
        for name in ("Q", "Y", "W"):
            a = np.asarray(getattr(self, name), dtype=np.float64)
            if a.ndim != 2 or a.shape[0] != nb:
                raise InputError(f"{name} must be (n_boundary={nb}, M), got {a.shape}")
            setattr(self, name, a)
        if not (self.Q.shape == self.Y.shape == self.W.shape):
            raise InputError(f"Q, Y, W shapes differ: {self.Q.shape}, {self.Y.shape}, {self.W.shape}")
        real(self.lam, "lambda", 0.0)
        real(self.lam_mu, "lambda_mu", 0.0)
        real(self.depth_weight, "depth_weight", 0.0)
        self.norm = float(np.sum(self.W * self.Y**2))
        if self.norm <= 0:
            raise InputError("the used measurements are all zero: nothing to fit")
        self.D = regularizer_matrix(self.model)
        self.D_mu = mu_difference_matrix(self.model, self.depth_weight) if self.lam_mu > 0 else None
        self._t0 = time.perf_counter()

    def regularizer(self, kappa: Array) -> tuple[float, Array]:
        """sum_x |grad kappa|^2 and its gradient."""
        dk = self.D @ kappa
        return float(dk @ dk), 2.0 * (self.D.T @ dk)

    def mu_regularizer(self, mu: Array) -> tuple[float, Array]:
        """sum_edges w (ln mu_i - ln mu_j)^2 and its gradient with respect to mu (0, 0 when
        ``lam_mu`` is 0)."""
        if self.D_mu is None:
            return 0.0, np.zeros_like(mu)
        dm = self.D_mu @ np.log(mu)
        return float(dm @ dm), 2.0 * (self.D_mu.T @ dm) / mu

    def evaluate(self, kappa: Array, mu: Array, gradient: bool = True) -> Evaluation:
        """f (and its gradient over the active nodes) at material ``(kappa, mu)``."""
        fac = self.model.factorize(kappa, mu)
        self.last_material = (fac.kappa, fac.mu)
        X = fac.solve(self.Q)
        E = fac.radiance(X, self.Q) - self.Y
        R = self.W * E
        data = float(np.sum(R * E)) / self.norm
        reg, greg = self.regularizer(fac.kappa)
        reg_mu, greg_mu = self.mu_regularizer(fac.mu)
        ev = Evaluation(data + self.lam * reg + self.lam_mu * reg_mu, data, reg, reg_mu=reg_mu)
        self.evaluations += 1
        if gradient:
            G, dk_explicit = fac.radiance_sensitivity(2.0 * R / self.norm, X)
            Lam = fac.adjoint(G)
            dk, dmu = fac.contract(X, Lam, self.Q)
            ev.grad_kappa = dk_explicit - dk + self.lam * greg
            ev.grad_mu = self.lam_mu * greg_mu - dmu
            self.gradients += 1
        self.trace.append((time.perf_counter() - self._t0, ev.value, ev.data))
        return ev


def mu_difference_matrix(model: ForwardModel, depth_weight: float = 1.0) -> sp.csr_matrix:
    """Difference operator over the lattice edges between interior nodes (those whose mu
    enters the model), rows along z scaled by ``sqrt(depth_weight)``, so that
    ``||D v||^2 = sum_edges w (v_i - v_j)^2`` (dimensionless for ``v = ln mu``)."""
    return edge_difference_matrix(model, keep=model.grid.kind == INTERIOR,
                                  weights=(float(np.sqrt(depth_weight)), 1.0, 1.0))
