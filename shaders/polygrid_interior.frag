#version 330 core
// One Jacobi sweep at polygrid interior nodes (Wang et al. 2008, eq. 9 first line and
// section 5.2), with scaled appendix-B weights w_j (T_w1.rgb = x-, x+, y-; T_w2.rgb = y+, z-, z+)
// and the row scale s (T_w1.a, mm^2; true weights are w_j / s):
// STENCIL_PAPER = 1: u = kappa*phi,  u_i <- (sum_j w_j u_j + s f_i) / (sum_j w_j + s mu_i / kappa_i)
// STENCIL_PAPER = 0: phi_i <- (sum_j w_j k_ij phi_j + s f_i) / (sum_j w_j k_ij + s mu_i)
// f = 0 unless HAS_RHS (a multigrid coarse level: f from T_q); DAMPED mixes with the old value.
// Texture fetches (paper stencil): six neighbours, T_w1, T_w2, kappa, mu = ten.
#include "common.glsl"
uniform sampler2D u_w1;
uniform sampler2D u_w2;
flat in ivec2 v_off0;
flat in ivec2 v_off1;
flat in ivec2 v_off2;
flat in ivec2 v_off3;
flat in ivec2 v_off4;
flat in ivec2 v_off5;
layout(location = 0) out vec4 f_color;

void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    ivec2 nb[6] = ivec2[6](p + v_off0, p + v_off1, p + v_off2, p + v_off3, p + v_off4, p + v_off5);
    vec4 w1 = texelFetch(u_w1, p, 0);
    vec4 w2 = texelFetch(u_w2, p, 0);
    float w[6] = float[6](w1.r, w1.g, w1.b, w2.r, w2.g, w2.b);
    vec3 kappa = kappa_at(p);
    vec3 mu = mu_at(p);
#if STENCIL_PAPER
    vec3 num = vec3(0.0);
    float den = 0.0;
    for (int j = 0; j < 6; ++j) {
        num += w[j] * fetch(u_state, nb[j]);
        den += w[j];
    }
#if HAS_RHS
    num += w1.a * fetch(u_q, p);
#endif
    f_color = relaxed(p, num / (den + w1.a * mu / kappa));
#else
    vec3 num = vec3(0.0);
    vec3 den = w1.a * mu;
    for (int j = 0; j < 6; ++j) {
        vec3 k = w[j] * face_k(kappa, kappa_at(nb[j]));
        num += k * fetch(u_state, nb[j]);
        den += k;
    }
#if HAS_RHS
    num += w1.a * fetch(u_q, p);
#endif
    f_color = relaxed(p, num / den);
#endif
}
