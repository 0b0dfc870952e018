// Shared by the diffusion shaders. Textures hold RGB per node (alpha unused).
uniform sampler2D u_state;   // iterated unknown: kappa*phi (STENCIL_PAPER) or phi
uniform sampler2D u_kappa;   // diffusion coefficient kappa, mm
uniform sampler2D u_mu;      // absorption mu, mm^-1

vec3 fetch(sampler2D tex, ivec2 p) { return texelFetch(tex, p, 0).rgb; }
