#version 330 core
// One pass over the rows of one kind (ROW_BOUNDARY = 0: interior rows, 1: boundary rows), built
// from the row functions of diffusion.glsl:
//   RESIDUAL = 0: a Jacobi sweep, the row solved for its own node
//     interior: x_p <- (sum_j a_j x_j + s f_p) / (sum_j a_j + sigma)
//     boundary: x_p <- (d t_p q_p + 2 C kappa_p (t_p / t_j) x_j) / (d + 2 C kappa_p)
//     (DAMPED mixes with the old value);
//   RESIDUAL = 1: the residual r = rhs - row(x) in the units of the equation (not row-scaled)
//     interior: r = f_p - (sum_j a_j (x_p - x_j) + sigma x_p) / s   (f = 0 unless HAS_RHS)
//     boundary: r = q_p - (phi_p + 2 C kappa_p (phi_p - phi_j) / d)
// Texture fetches of an interior sweep, paper stencil: six neighbours, T_w1, T_w2, kappa, mu.
#include "diffusion.glsl"
// TEXEL_OFFSETS = 0: the primitives of stencil.vert carry the offsets (flat varyings), one
// program per row kind. TEXEL_OFFSETS = 1 (the "texels" packing, glsldiff.solve.stencil.offset_textures):
// one quad over the level, every texel reads its row kind and offsets from T_offA / T_offB
// (each uint packs (dx + 32768) << 16 | (dy + 32768); T_offA.w = kind: 0 not updated, 1
// interior, 2 boundary) and runs the same row code; two fetches more per interior texel,
// one quad instead of thousands of primitives. A sweep copies the texels it does not update
// (the schedules keep both ping-pong buffers equal there, so this is what the primitives'
// untouched texels hold too); the residual variant leaves them untouched.
#ifndef TEXEL_OFFSETS
#define TEXEL_OFFSETS 0
#endif
layout(location = 0) out vec4 f_color;

// The new value of the node at p from its plain Jacobi value (damped when DAMPED).
vec3 relaxed(ivec2 p, vec3 jacobi) {
#if DAMPED
    return mix(fetch(u_state, p), jacobi, u_omega);
#else
    return jacobi;
#endif
}

vec4 boundary_value(ivec2 p, ivec2 pj) {
    BoundaryRow row = boundary_row(p, pj);
    vec3 q = fetch(u_q, p);
    vec3 c = 2.0 * u_C * row.kappa;
#if RESIDUAL
    vec3 phi = fetch(u_state, p) / row.t;
    return vec4(q - (phi + c * (phi - row.x_j / row.t_j) / row.d), 0.0);
#else
    return vec4(relaxed(p, (row.d * row.t * q + c * (row.t / row.t_j) * row.x_j) / (row.d + c)), 0.0);
#endif
}

vec4 interior_value(ivec2 p, ivec2 nb[6]) {
    InteriorRow row = interior_row(p, nb);
#if RESIDUAL
    vec3 x = fetch(u_state, p);
    vec3 flux = vec3(0.0);
    for (int j = 0; j < 6; ++j) flux += row.a[j] * (x - row.x[j]);
    vec3 r = -(flux + row.sigma * x) / row.s;
#if HAS_RHS
    r += fetch(u_q, p);
#endif
    return vec4(r, 0.0);
#else
    vec3 num = vec3(0.0);
    vec3 den = vec3(0.0);
    for (int j = 0; j < 6; ++j) {
        num += row.a[j] * row.x[j];
        den += row.a[j];
    }
#if HAS_RHS
    num += row.s * fetch(u_q, p);
#endif
    return vec4(relaxed(p, num / (den + row.sigma)), 0.0);
#endif
}

#if TEXEL_OFFSETS
uniform usampler2D u_offa;
uniform usampler2D u_offb;

ivec2 unpack_offset(uint v) { return ivec2(int(v >> 16u), int(v & 0xFFFFu)) - 32768; }

void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    uvec4 a = texelFetch(u_offa, p, 0);
#if RESIDUAL
    if (a.w == 0u) discard;                // the residual leaves other texels untouched
#else
    if (a.w == 0u) {                       // not updated: keeps its value, which the schedules hold in
        f_color = vec4(fetch(u_state, p), 0.0);  // both buffers (on llvmpipe a discard made the sweep 2x slower)
        return;
    }
#endif
    if (a.w == 2u) {
        f_color = boundary_value(p, p + unpack_offset(a.x));
        return;
    }
    uvec4 b = texelFetch(u_offb, p, 0);
    ivec2 nb[6] = ivec2[6](p + unpack_offset(a.x), p + unpack_offset(a.y), p + unpack_offset(a.z),
                           p + unpack_offset(b.x), p + unpack_offset(b.y), p + unpack_offset(b.z));
    f_color = interior_value(p, nb);
}
#else
flat in ivec2 v_off0;
flat in ivec2 v_off1;
flat in ivec2 v_off2;
flat in ivec2 v_off3;
flat in ivec2 v_off4;
flat in ivec2 v_off5;

void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
#if ROW_BOUNDARY
    f_color = boundary_value(p, p + v_off0);
#else
    ivec2 nb[6] = ivec2[6](p + v_off0, p + v_off1, p + v_off2, p + v_off3, p + v_off4, p + v_off5);
    f_color = interior_value(p, nb);
#endif
}
#endif
