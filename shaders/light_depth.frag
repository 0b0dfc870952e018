#version 330 core
// Front- and back-face depth of a closed mesh seen from a light (glsldiff.render.shadows).
// Channel r: nearest light-facing surface, channel g: nearest surface facing away; written
// with glBlendEquation(GL_MIN) into an RG32F target cleared to LIGHT_FAR, so no depth buffer
// is needed. The caller compares against the midpoint (r + g) / 2 (Woo's midpoint shadow map).
// Depth is the world distance in mm: along u_axis from u_origin (u_mode 0, orthographic
// views of directional lights) or the Euclidean distance from u_origin (u_mode 1, point and
// spot lights), evaluated per fragment from the interpolated position, so it is exact.
#ifndef LIGHT_FAR
#define LIGHT_FAR 1.0e30
#endif
in vec3 v_pos;
uniform vec3 u_origin;   // light position (or the eye of the orthographic view), mm
uniform vec3 u_axis;     // unit propagation direction of a directional light
uniform int u_mode;      // 0: dot(p - origin, axis), 1: length(p - origin)
layout(location = 0) out vec4 f_depth;

void main() {
    vec3 d = v_pos - u_origin;
    float z = (u_mode == 0) ? dot(d, u_axis) : length(d);
    f_depth = gl_FrontFacing ? vec4(z, LIGHT_FAR, 0.0, 0.0) : vec4(LIGHT_FAR, z, 0.0, 0.0);
}
