// Shared by the diffusion shaders. Textures hold RGB per node (alpha unused).
uniform sampler2D u_state;   // iterated unknown: kappa*phi (STENCIL_PAPER) or phi
uniform sampler2D u_kappa;   // diffusion coefficient kappa, mm
uniform sampler2D u_mu;      // absorption mu, mm^-1
uniform sampler2D u_q;       // right-hand side: boundary source q (phi units) at boundary nodes;
                             // with HAS_RHS also f (unknown / mm^2) at interior nodes (multigrid)
uniform float u_omega;       // Jacobi damping (DAMPED): x <- x + omega (x_jacobi - x)
#ifndef DAMPED
#define DAMPED 0
#endif
#ifndef HAS_RHS
#define HAS_RHS 0
#endif
#ifndef MATERIAL_8BIT
#define MATERIAL_8BIT 0
#endif
// MATERIAL_8BIT: T_kappa / T_mu are RGB8 codes t in [0, 1] (glsldiff.solve.quantize):
// kappa = exp(mix(lo, hi, t)), mu = mix(lo, hi, t), ranges per channel.
uniform vec3 u_kappa_lo;
uniform vec3 u_kappa_hi;
uniform vec3 u_mu_lo;
uniform vec3 u_mu_hi;

vec3 fetch(sampler2D tex, ivec2 p) { return texelFetch(tex, p, 0).rgb; }

vec3 kappa_at(ivec2 p) {
#if MATERIAL_8BIT
    return exp(mix(u_kappa_lo, u_kappa_hi, fetch(u_kappa, p)));
#else
    return fetch(u_kappa, p);
#endif
}

vec3 mu_at(ivec2 p) {
#if MATERIAL_8BIT
    return mix(u_mu_lo, u_mu_hi, fetch(u_mu, p));
#else
    return fetch(u_mu, p);
#endif
}

// Face coefficient k_ij of the conservative stencil (FACE_HARMONIC: harmonic mean).
vec3 face_k(vec3 a, vec3 b) {
#if FACE_HARMONIC
    return 2.0 * a * b / (a + b);
#else
    return 0.5 * (a + b);
#endif
}

// The new value of the node at p from its plain Jacobi value (damped when DAMPED).
vec4 relaxed(ivec2 p, vec3 jacobi) {
#if DAMPED
    return vec4(mix(texelFetch(u_state, p, 0).rgb, jacobi, u_omega), 0.0);
#else
    return vec4(jacobi, 0.0);
#endif
}
