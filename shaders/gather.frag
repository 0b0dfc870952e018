#version 330 core
// One pass of a sparse matrix with RGB channels stored as ELLPACK in textures ("gather";
// glsldiff.solve.gather): per output node i (texel (i % W, i / W) of the render target)
//
//     y_i = sum_k m_ik v_j(k)        (per channel; v = u_src, the gathered vector)
//
// and, by u_mode (the same for every fragment of a pass):
//     0 JACOBI    x_i + omega (b_i - a_ii x_i - y_i) / a_ii    (damped Jacobi sweep; u_src = x)
//     1 RESIDUAL  b_i - a_ii x_i - y_i                          (u_src = x)
//     2 APPLY     y_i                                           (restriction, dense coarse solve)
//     3 ADD       x_i + y_i                                     (prolongation-correction)
//     4 MATVEC    a_ii x_i + y_i                                (A x; u_src = x)
// with x_i = u_self at the node's texel. JACOBI, RESIDUAL and MATVEC store a matrix's
// off-diagonal entries in the slots and a_ii in u_diag; APPLY and ADD store every entry of a
// (rectangular) matrix in the slots.
//
// Slot k of node i is layer k of u_coef at the node's texel: rgb = m_ij of the three channels,
// a = the column j as a float (exact below 2^24), -1 for an empty slot; a row's empty slots come
// last, so the loop stops at the first one (or after u_slots, the layers). A row longer than
// u_slots (a matrix whose few long rows would pad every texel to their length) ends its slots
// with a link, a = -2 - s: the rest of the row, in order, is in layers 0 .. of u_spill at its
// texel s (u_spill_slots layers, width 2^u_spill_shift; 0 layers: no row spills). v_j is at texel
// (j & (2^u_src_shift - 1), j >> u_src_shift) of u_src (the source's width is a power of two:
// llvmpipe has no vector integer division). Padding texels (i >= n) hold a_ii = 1, b = 0 and no
// slots, so they stay 0 in every mode.
// Fetches per node: 2 per used slot (+1 for the first empty slot of a row shorter than u_slots),
// plus x_i, a_ii, b_i (JACOBI, RESIDUAL), x_i, a_ii (MATVEC) or x_i (ADD).
#define JACOBI 0
#define RESIDUAL 1
#define APPLY 2
#define ADD 3
#define MATVEC 4
uniform sampler2D u_src;            // v, the gathered vector (rgb)
uniform sampler2D u_self;           // x at this node (rgb): JACOBI, RESIDUAL, ADD, MATVEC
uniform sampler2D u_diag;           // a_ii (rgb): JACOBI, RESIDUAL, MATVEC
uniform sampler2D u_b;              // b (rgb): JACOBI, RESIDUAL
uniform sampler2DArray u_coef;      // u_slots layers: rgb m_ij, a = j or -1
uniform sampler2DArray u_spill;     // u_spill_slots layers: the rest of the rows that spill
uniform int u_slots;                // layers of u_coef
uniform int u_spill_slots;          // layers of u_spill (0: none)
uniform int u_spill_shift;          // log2 of u_spill's width
uniform int u_src_shift;            // log2 of u_src's width
uniform int u_mode;                 // JACOBI, RESIDUAL, APPLY, ADD, MATVEC
uniform float u_omega;              // damping (JACOBI)
layout(location = 0) out vec4 f_color;

void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    int mask = (1 << u_src_shift) - 1;
    vec3 y = vec3(0.0);
    vec4 c = vec4(0.0);
    for (int k = 0; k < u_slots; ++k) {
        c = texelFetch(u_coef, ivec3(p, k), 0);
        if (c.a < 0.0) break;
        int j = int(c.a);
        y += c.rgb * texelFetch(u_src, ivec2(j & mask, j >> u_src_shift), 0).rgb;
    }
    if (c.a < -1.5) {                   // a link: the row goes on at texel s of u_spill
        int s = int(-c.a) - 2;
        ivec2 q = ivec2(s & ((1 << u_spill_shift) - 1), s >> u_spill_shift);
        for (int k = 0; k < u_spill_slots; ++k) {
            c = texelFetch(u_spill, ivec3(q, k), 0);
            if (c.a < 0.0) break;
            int j = int(c.a);
            y += c.rgb * texelFetch(u_src, ivec2(j & mask, j >> u_src_shift), 0).rgb;
        }
    }
    if (u_mode == APPLY) {
        f_color = vec4(y, 0.0);
        return;
    }
    vec3 x = texelFetch(u_self, p, 0).rgb;
    if (u_mode == ADD) {
        f_color = vec4(x + y, 0.0);
        return;
    }
    vec3 d = texelFetch(u_diag, p, 0).rgb;
    if (u_mode == MATVEC) {
        f_color = vec4(d * x + y, 0.0);
        return;
    }
    vec3 r = texelFetch(u_b, p, 0).rgb - d * x - y;
    f_color = vec4(u_mode == RESIDUAL ? r : x + u_omega * r / d, 0.0);
}
