#version 330 core
// Residual r = f - A u of the polygrid rows, in the units of the equation (not row-scaled):
// interior (ROW_BOUNDARY = 0), true weights W_j = w_j / s:
//   STENCIL_PAPER = 1: r = f - sum_j W_j (u_i - u_j) - (mu/kappa) u_i            (u = kappa phi)
//   STENCIL_PAPER = 0: r = f - sum_j W_j k_ij (phi_i - phi_j) - mu phi_i
//   (f from T_q when HAS_RHS, else 0);
// boundary (ROW_BOUNDARY = 1), partner j at distance d (T_w1.r), g = T_q:
//   STENCIL_PAPER = 1: r = g - [u_b/k_b + 2 C k_b (u_b/k_b - u_j/k_j) / d]
//   STENCIL_PAPER = 0: r = g - [phi_b + 2 C k_b (phi_b - phi_j) / d]
// Drawn over the same primitives as the sweep (multigrid, glsldiff.solve.multilevel).
#include "common.glsl"
uniform sampler2D u_w1;
uniform sampler2D u_w2;
uniform float u_C;
flat in ivec2 v_off0;
flat in ivec2 v_off1;
flat in ivec2 v_off2;
flat in ivec2 v_off3;
flat in ivec2 v_off4;
flat in ivec2 v_off5;
layout(location = 0) out vec4 f_color;

void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    vec3 x = fetch(u_state, p);
    vec3 kappa = kappa_at(p);
    vec3 rhs = fetch(u_q, p);
    vec4 w1 = texelFetch(u_w1, p, 0);
#if ROW_BOUNDARY
    ivec2 pj = p + v_off0;
    vec3 xj = fetch(u_state, pj);
    float d = w1.r;
#if STENCIL_PAPER
    vec3 kj = kappa_at(pj);
    vec3 r = rhs - (x / kappa + 2.0 * u_C * kappa * (x / kappa - xj / kj) / d);
#else
    vec3 r = rhs - (x + 2.0 * u_C * kappa * (x - xj) / d);
#endif
#else
    ivec2 nb[6] = ivec2[6](p + v_off0, p + v_off1, p + v_off2, p + v_off3, p + v_off4, p + v_off5);
    vec4 w2 = texelFetch(u_w2, p, 0);
    float w[6] = float[6](w1.r, w1.g, w1.b, w2.r, w2.g, w2.b);
    vec3 mu = mu_at(p);
    vec3 flux = vec3(0.0);
    for (int j = 0; j < 6; ++j) {
#if STENCIL_PAPER
        flux += w[j] * (x - fetch(u_state, nb[j]));
#else
        flux += w[j] * face_k(kappa, kappa_at(nb[j])) * (x - fetch(u_state, nb[j]));
#endif
    }
#if STENCIL_PAPER
    vec3 r = -flux / w1.a - mu / kappa * x;
#else
    vec3 r = -flux / w1.a - mu * x;
#endif
#if HAS_RHS
    r += rhs;
#endif
#endif
    f_color = vec4(r, 0.0);
}
