// The discrete diffusion operator of glsldiff (Wang et al. 2008, eqs. 8-9), written once.
// stencil.frag builds the Jacobi sweep and the residual from the two row functions below,
// transfer.frag the grid transfers from the unknown <-> phi conversion. The stencil variants
// (STENCIL_PAPER, FACE_HARMONIC) appear in the section "the stencil" only; the CPU twin of
// this file is glsldiff.oracle.assembly (stencil_terms). Textures hold RGB per node; the
// weights follow glsldiff.grids.graph (scaled Laplacian weights w_j, row scale s, mm^2).
uniform sampler2D u_state;   // iterated unknown x: kappa*phi (STENCIL_PAPER) or phi
uniform sampler2D u_kappa;   // diffusion coefficient kappa, mm
uniform sampler2D u_mu;      // absorption mu, mm^-1
uniform sampler2D u_q;       // right-hand side: source q (phi units) at boundary nodes; with
                             // HAS_RHS also f (unknown / mm^2) at interior nodes (multigrid)
uniform sampler2D u_w1;      // interior: (w_x-, w_x+, w_y-, s); boundary: (d, -, -, 0), d in mm
uniform sampler2D u_w2;      // interior: (w_y+, w_z-, w_z+, 0)
uniform float u_C;           // boundary constant (1 + Fdr) / (1 - Fdr)
uniform float u_scale;       // UNIFORM_WEIGHTS: the row scale s of every interior row, mm^2
uniform float u_d;           // UNIFORM_WEIGHTS: the partner distance d of every boundary row, mm
uniform float u_omega;       // Jacobi damping (DAMPED): x <- x + omega (x_jacobi - x)
#ifndef STENCIL_PAPER
#define STENCIL_PAPER 1
#endif
#ifndef FACE_HARMONIC
#define FACE_HARMONIC 0
#endif
#ifndef DAMPED
#define DAMPED 0
#endif
#ifndef HAS_RHS
#define HAS_RHS 0
#endif
#ifndef MATERIAL_8BIT
#define MATERIAL_8BIT 0
#endif
// UNIFORM_WEIGHTS: every scaled weight is 1 and s, d are the same at every node (a regular
// grid): they come from u_scale and u_d instead of T_w1 / T_w2 (two fetches fewer per row).
#ifndef UNIFORM_WEIGHTS
#define UNIFORM_WEIGHTS 0
#endif
// MATERIAL_8BIT: T_kappa / T_mu are RGB8 codes t in [0, 1] (glsldiff.solve.quantize):
// kappa = exp(mix(lo, hi, t)), mu = mix(lo, hi, t), ranges per channel.
uniform vec3 u_kappa_lo;
uniform vec3 u_kappa_hi;
uniform vec3 u_mu_lo;
uniform vec3 u_mu_hi;

vec3 fetch(sampler2D tex, ivec2 p) { return texelFetch(tex, p, 0).rgb; }

vec3 decode_kappa(vec3 t, vec3 lo, vec3 hi) {
#if MATERIAL_8BIT
    return exp(mix(lo, hi, t));
#else
    return t;
#endif
}
vec3 kappa_at(ivec2 p) { return decode_kappa(fetch(u_kappa, p), u_kappa_lo, u_kappa_hi); }
vec3 mu_at(ivec2 p) {
#if MATERIAL_8BIT
    return mix(u_mu_lo, u_mu_hi, fetch(u_mu, p));
#else
    return fetch(u_mu, p);
#endif
}

// ---- the stencil -------------------------------------------------------------------------
// The unknown per unit fluence, x = t phi: t = kappa (paper, after Stam 1995) or 1 (conservative).
vec3 unknown_factor(vec3 kappa) {
#if STENCIL_PAPER
    return kappa;
#else
    return vec3(1.0);
#endif
}
vec3 phi_of(vec3 x, vec3 kappa) { return x / unknown_factor(kappa); }
vec3 unknown_of(vec3 phi, vec3 kappa) { return unknown_factor(kappa) * phi; }
// Coupling a_j of an interior node (kappa_i) to neighbour j (kappa_j, scaled weight w_j) and its
// absorption sigma (row scale s): the paper's stencil discretises Laplacian(kappa phi)
// (a_j = w_j, sigma = s mu / kappa), the conservative one div(kappa grad phi)
// (a_j = w_j k_ij with k_ij the arithmetic or, FACE_HARMONIC, harmonic mean; sigma = s mu).
vec3 coupling(float w, vec3 ki, vec3 kj) {
#if STENCIL_PAPER
    return vec3(w);
#elif FACE_HARMONIC
    return w * (2.0 * ki * kj / (ki + kj));
#else
    return w * (0.5 * (ki + kj));
#endif
}
vec3 absorption(float s, vec3 mu, vec3 kappa) {
#if STENCIL_PAPER
    return s * mu / kappa;
#else
    return s * mu;
#endif
}

// ---- the two rows ------------------------------------------------------------------------
// Interior row of node p, scaled by its row scale s:
//   sum_j a_j (x_p - x_j) + sigma x_p = s f_p        (f = 0 unless HAS_RHS)
struct InteriorRow { vec3 a[6]; vec3 x[6]; vec3 sigma; float s; };

InteriorRow interior_row(ivec2 p, ivec2 nb[6]) {
    InteriorRow row;
#if UNIFORM_WEIGHTS
    float w[6] = float[6](1.0, 1.0, 1.0, 1.0, 1.0, 1.0);
    row.s = u_scale;
#else
    vec4 w1 = texelFetch(u_w1, p, 0);
    vec4 w2 = texelFetch(u_w2, p, 0);
    float w[6] = float[6](w1.r, w1.g, w1.b, w2.r, w2.g, w2.b);
    row.s = w1.a;
#endif
    vec3 kappa = kappa_at(p);
    for (int j = 0; j < 6; ++j) {
        row.a[j] = coupling(w[j], kappa, kappa_at(nb[j]));  // the paper's stencil leaves kappa_j unread
        row.x[j] = fetch(u_state, nb[j]);
    }
    row.sigma = absorption(row.s, mu_at(p), kappa);
    return row;
}

// Boundary row of node p with interior partner pj at distance d (paper eq. 9, second line):
//   phi_p + 2 C kappa_p (phi_p - phi_j) / d = q_p,   phi = x / t
// times d t_p: (d + 2 C kappa_p) x_p - 2 C kappa_p (t_p / t_j) x_j = d t_p q_p.
struct BoundaryRow { vec3 kappa; vec3 t; vec3 x_j; vec3 t_j; float d; };

BoundaryRow boundary_row(ivec2 p, ivec2 pj) {
    BoundaryRow row;
    row.kappa = kappa_at(p);
    row.t = unknown_factor(row.kappa);
    row.x_j = fetch(u_state, pj);
    row.t_j = unknown_factor(kappa_at(pj));
#if UNIFORM_WEIGHTS
    row.d = u_d;
#else
    row.d = texelFetch(u_w1, p, 0).r;
#endif
    return row;
}
