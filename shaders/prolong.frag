#version 330 core
// Prolongation to a finer polygrid level (glsldiff.grids.hierarchy.Transfer.prolong): each fine node
// copies the coarse node in T_source (its parent, or the nearest active coarse node where the
// parent was removed; x < 0 at removed fine nodes). The unknown kappa*phi (STENCIL_PAPER) is
// rescaled by kappa_fine / kappa_coarse so that phi is what is copied.
// ADD = 0: initial guess (coarse-to-fine solve); ADD = 1: correction, times u_alpha, added to the
// fine state (multigrid's damped coarse-grid correction; u_alpha = 1 for a full-multigrid start).
#include "common.glsl"
uniform sampler2D u_coarse;    // coarse unknown
uniform sampler2D u_source;    // .xy coarse texel of the source node
uniform sampler2D u_kappa_c;   // coarse kappa
uniform vec3 u_kappa_c_lo;     // MATERIAL_8BIT: the coarse level's decode range
uniform vec3 u_kappa_c_hi;
uniform float u_alpha;         // ADD: correction factor
layout(location = 0) out vec4 f_color;

void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    vec2 s = texelFetch(u_source, p, 0).xy;
    vec3 v = vec3(0.0);
    if (s.x >= 0.0) {
        ivec2 c = ivec2(s);
        v = fetch(u_coarse, c);
#if STENCIL_PAPER
#if MATERIAL_8BIT
        vec3 kc = exp(mix(u_kappa_c_lo, u_kappa_c_hi, fetch(u_kappa_c, c)));
#else
        vec3 kc = fetch(u_kappa_c, c);
#endif
        v *= kappa_at(p) / kc;
#endif
    }
#if ADD
    v = u_alpha * v + fetch(u_state, p);
#endif
    f_color = vec4(v, 0.0);
}
