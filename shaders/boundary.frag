#version 330 core
// One Jacobi sweep at boundary nodes (Wang et al. 2008, eq. 8/9 second line):
//   phi_b + 2 C kappa_b (phi_b - phi_j) / d = q_b,  j = interior partner,
//   d = h on a regular grid (PER_NODE_D = 0), d_b from T_w1.r on a polygrid (PER_NODE_D = 1).
// Texture fetches: q, kappa_b, kappa_j, state_j (+ d_b): five on a polygrid.
// STENCIL_PAPER = 1 (u = kappa*phi):
//   u_b <- [q kappa_b kappa_j d + 2 C kappa_b^2 u_j] / [kappa_j d + 2 C kappa_b kappa_j]
// STENCIL_PAPER = 0: phi_b <- [q d + 2 C kappa_b phi_j] / [d + 2 C kappa_b]
// (q: the source, or the restricted residual on a multigrid coarse level; DAMPED mixes.)
#include "common.glsl"
uniform float u_C;           // boundary constant (1 + Fdr) / (1 - Fdr)
uniform float u_d;           // boundary-to-interior distance d = h, mm (regular grid)
uniform sampler2D u_w1;      // polygrid: .r = d_b, mm, at boundary texels
flat in ivec2 v_off0;        // texel offset to the linked interior node
flat in ivec2 v_off1;
layout(location = 0) out vec4 f_color;

void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    ivec2 pj = p + v_off0;
    vec3 kb = kappa_at(p);
    vec3 q = fetch(u_q, p);
    vec3 xj = fetch(u_state, pj);
#if PER_NODE_D
    float d = texelFetch(u_w1, p, 0).r;
#else
    float d = u_d;
#endif
#if STENCIL_PAPER
    vec3 kj = kappa_at(pj);
    f_color = relaxed(p, (q * kb * kj * d + 2.0 * u_C * kb * kb * xj) / (kj * d + 2.0 * u_C * kb * kj));
#else
    f_color = relaxed(p, (q * d + 2.0 * u_C * kb * xj) / (d + 2.0 * u_C * kb));
#endif
}
