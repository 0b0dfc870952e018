#version 330 core
// One Jacobi sweep at interior nodes (Wang et al. 2008, eq. 8 first line).
// STENCIL_PAPER = 1: u = kappa*phi,  u_i <- (sum_j u_j + h^2 f_i) / (6 + h^2 mu_i / kappa_i)
// STENCIL_PAPER = 0: phi_i <- (sum_j k_ij phi_j + h^2 f_i) / (sum_j k_ij + h^2 mu_i),
//                    k_ij = FACE_MEAN(kappa_i, kappa_j)  (conservative form)
// f = 0 unless HAS_RHS (a multigrid coarse level); DAMPED mixes with the old value.
#include "common.glsl"
uniform float u_h2;          // h^2, mm^2
flat in ivec2 v_off0;        // texel offset to the node at z-1
flat in ivec2 v_off1;        // texel offset to the node at z+1
layout(location = 0) out vec4 f_color;

void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    ivec2 nb[6] = ivec2[6](p + ivec2(1, 0), p - ivec2(1, 0), p + ivec2(0, 1), p - ivec2(0, 1),
                           p + v_off0, p + v_off1);
    vec3 kappa = kappa_at(p);
    vec3 mu = mu_at(p);
#if STENCIL_PAPER
    vec3 s = vec3(0.0);
    for (int j = 0; j < 6; ++j) s += fetch(u_state, nb[j]);
#if HAS_RHS
    s += u_h2 * fetch(u_q, p);
#endif
    f_color = relaxed(p, s / (6.0 + u_h2 * mu / kappa));
#else
    vec3 num = vec3(0.0);
    vec3 den = u_h2 * mu;
    for (int j = 0; j < 6; ++j) {
        vec3 k = face_k(kappa, kappa_at(nb[j]));
        num += k * fetch(u_state, nb[j]);
        den += k;
    }
#if HAS_RHS
    num += u_h2 * fetch(u_q, p);
#endif
    f_color = relaxed(p, num / den);
#endif
}
