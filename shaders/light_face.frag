#version 330 core
// Face buffer of glsldiff.render.shadows: which face of the mesh is the nearest surface facing
// the light in each texel. Drawn with light_depth.vert and the same index buffer (so
// gl_PrimitiveID is the face's index) into an RG32F target cleared to 0, with the depth test
// '<' on the depth metric of light_depth.frag divided by the view's far distance (linear, so
// as fine as the depth buffer allows everywhere, not only near the light); fragments of faces
// turned away from the light are discarded, so the kept face is the surface of channel r of
// light_depth.frag. Stored: k = face + 1 (0: no surface) as two exactly representable floats,
// r = k mod 2^20 and g = floor(k / 2^20).
in vec3 v_pos;
uniform vec3 u_origin;   // light position (or the eye of the orthographic view), mm
uniform vec3 u_axis;     // unit propagation direction of a directional light
uniform int u_mode;      // 0: dot(p - origin, axis), 1: length(p - origin)
uniform float u_far;     // the view's far distance, mm: depth 1
layout(location = 0) out vec4 f_face;

void main() {
    if (!gl_FrontFacing) {
        discard;
    }
    vec3 d = v_pos - u_origin;
    float z = (u_mode == 0) ? dot(d, u_axis) : length(d);
    gl_FragDepth = clamp(z / u_far, 0.0, 1.0);
    int k = gl_PrimitiveID + 1;
    f_face = vec4(float(k & 0xFFFFF), float(k >> 20), 0.0, 0.0);
}
