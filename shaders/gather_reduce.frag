#version 330 core
// Chunked sums for the dot products of glsldiff.solve.gather_multigrid's conjugate gradients:
// output texel (i, 0) of a one-row target gets, per channel,
//
//     sum_{j = i c}^{min(u_count, (i + 1) c) - 1} a_j b_j     (u_product = 1)
//     sum_{j = i c}^{min(u_count, (i + 1) c) - 1} a_j         (u_product = 0)
//
// with c = u_chunk and v_j at texel (j & (2^u_src_shift - 1), j >> u_src_shift) of u_a, u_b
// (node layout of glsldiff.solve.gather). Two passes (chunks of ~sqrt(n), then one chunk of the
// partial sums) reduce n values to one texel. Fetches per output texel: c (x2 with u_product).
uniform sampler2D u_a;
uniform sampler2D u_b;
uniform int u_product;
uniform int u_count;
uniform int u_chunk;
uniform int u_src_shift;
layout(location = 0) out vec4 f_color;

void main() {
    int j0 = int(gl_FragCoord.x) * u_chunk;
    int j1 = min(u_count, j0 + u_chunk);
    int mask = (1 << u_src_shift) - 1;
    vec3 s = vec3(0.0);
    if (u_product != 0) {
        for (int j = j0; j < j1; ++j) {
            ivec2 t = ivec2(j & mask, j >> u_src_shift);
            s += texelFetch(u_a, t, 0).rgb * texelFetch(u_b, t, 0).rgb;
        }
    } else {
        for (int j = j0; j < j1; ++j)
            s += texelFetch(u_a, ivec2(j & mask, j >> u_src_shift), 0).rgb;
    }
    f_color = vec4(s, 0.0);
}
