"""``glsldiff polygrid``'s studies: the hierarchy's node counts per level and the GLSL polygrid
solve against the scipy direct solve of the same discrete system (a marble-like material lit
on the -x half)."""
from __future__ import annotations

import numpy as np

from glsldiff.grids.lattice import Lattice
from glsldiff.grids.polygrid import Polygrid
from glsldiff.bench.peers import reference_solve, relax_label
from glsldiff.physics.material import coefficients, preset
from glsldiff.solve.jacobi import solve_glsl
from glsldiff.system.problem import DiffusionProblem, relative_l2


def level_counts(pg: Polygrid) -> list[tuple[int, int]]:
    """Active nodes of the lattice at n, n/2, n/4, ... per cube (the hierarchy's levels)."""
    out, n = [], pg.lattice.n
    while n >= 3:
        lat = Lattice(pg.lattice.cubes, n, pg.lattice.size, pg.lattice.origin)
        out.append((n, lat.n_interior + lat.n_boundary))
        n //= 2
    return out


def check_solve(pg: Polygrid, tol: float) -> list[dict[str, object]]:
    """Marble-like material lit on the -x half: GLSL polygrid (Jacobi to the Jacobi-scaled residual
    ``tol``) vs the converged CPU solve (:func:`glsldiff.bench.peers.reference_solve`: SuperLU up
    to 20k nodes, pyamg SA + GMRES above: SuperLU took 17 minutes and 3.8 GB on the 6^3-per-cube
    bunny). ``solver`` names what ran and its tolerance; ``seconds``: one run each, the
    reference's with its assembly and factorisation / AMG set-up, the GLSL one without the
    solver's construction (texture upload, shader compilation)."""
    m = preset("marble")
    kappa, mu = coefficients(m.sigma_a, m.sigma_s_prime)
    x = pg.boundary_positions[:, 0]
    q = (x < np.median(x))[:, None] * np.ones(3)
    p = DiffusionProblem(pg, kappa, mu, q, eta=m.eta)
    phi_d, rep_d, label_d, rtol_d = reference_solve(p)   # SuperLU on small grids, pyamg above 20k nodes
    phi_g, rep_g = solve_glsl(p, tol=tol)
    act = pg.active
    return [{"solver": label, "nodes": r.nodes, "sweeps": r.sweeps, "tol": t, "residual": r.residual,
             "seconds": r.seconds, "error_phi": relative_l2(ph[act], phi_d[act]),
             "error_radiance": relative_l2(r.radiance, rep_d.radiance), "status": r.status}
            for r, ph, label, t in ((rep_d, phi_d, label_d, rtol_d),
                                    (rep_g, phi_g, relax_label(f"GLSL Jacobi {rep_g.method.rsplit('-', 1)[-1]}", tol), tol))]
