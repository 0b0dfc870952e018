#version 330 core
// out = a + s b per node and channel, s = u_scale num / den with num, den the rgb of the
// one-texel textures u_num, u_den (dot products of glsldiff.solve.gather_multigrid's
// conjugate gradients, computed on the GPU: no read-back); s = 0 in a channel whose den is 0
// (a channel with a zero residual: converged, or a zero source).
uniform sampler2D u_a;
uniform sampler2D u_b;
uniform sampler2D u_num;
uniform sampler2D u_den;
uniform float u_scale;
layout(location = 0) out vec4 f_color;

void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    vec3 den = texelFetch(u_den, ivec2(0), 0).rgb;
    bvec3 ok = notEqual(den, vec3(0.0));
    vec3 s = u_scale * texelFetch(u_num, ivec2(0), 0).rgb / mix(vec3(1.0), den, ok);
    s = mix(vec3(0.0), s, ok);
    f_color = vec4(texelFetch(u_a, p, 0).rgb + s * texelFetch(u_b, p, 0).rgb, 0.0);
}
