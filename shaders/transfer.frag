#version 330 core
// A grid transfer (glsldiff.grids.hierarchy.Transfer) applied as a sparse gather: target node
// p gets sum_k w_k v(s_k) over the slots k of its row (T_slots layer k = (s_k.x, s_k.y, w_k, 0),
// w = 0 for an empty slot; glsldiff.solve.stencil.transfer_slots), v = T_src.
// Prolongation acts on phi (PHI = 1: the source unknown is divided by the source kappa and
// the sum multiplied by the target's, diffusion.glsl's unknown <-> phi); restriction of a
// residual acts on the values as they are (PHI = 0).
// ADD = 0: the target gets the sum (an initial guess, a restricted right-hand side); ADD = 1:
// u_alpha times the sum is added to the target's state (multigrid's coarse-grid correction).
#include "diffusion.glsl"
uniform sampler2DArray u_slots;
uniform sampler2D u_src;           // source values (coarse unknown, or fine residual)
uniform sampler2D u_kappa_src;     // PHI: source kappa
uniform vec3 u_kappa_src_lo;       // PHI and MATERIAL_8BIT: the source level's decode range
uniform vec3 u_kappa_src_hi;
uniform float u_alpha;             // ADD: correction factor
layout(location = 0) out vec4 f_color;
void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    vec3 v = vec3(0.0);
    for (int k = 0; k < SLOTS; ++k) {
        vec4 s = texelFetch(u_slots, ivec3(p, k), 0);
        if (s.z != 0.0) {
            ivec2 c = ivec2(s.xy);
            vec3 x = fetch(u_src, c);
#if PHI
            x = phi_of(x, decode_kappa(fetch(u_kappa_src, c), u_kappa_src_lo, u_kappa_src_hi));
#endif
            v += s.z * x;
        }
    }
#if PHI
    v = unknown_of(v, kappa_at(p));
#endif
#if ADD
    v = u_alpha * v + fetch(u_state, p);
#endif
    f_color = vec4(v, 0.0);
}
