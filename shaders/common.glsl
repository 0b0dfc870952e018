// Shared by the diffusion shaders. Textures hold RGB per node (alpha unused).
uniform sampler2D u_state;   // iterated unknown: kappa*phi (STENCIL_PAPER) or phi
uniform sampler2D u_kappa;   // diffusion coefficient kappa, mm
uniform sampler2D u_mu;      // absorption mu, mm^-1

vec3 fetch(sampler2D tex, ivec2 p) { return texelFetch(tex, p, 0).rgb; }

// Face coefficient k_ij of the conservative stencil (FACE_HARMONIC: harmonic mean).
vec3 face_k(vec3 a, vec3 b) {
#if FACE_HARMONIC
    return 2.0 * a * b / (a + b);
#else
    return 0.5 * (a + b);
#endif
}
