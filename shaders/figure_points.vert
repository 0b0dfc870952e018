#version 330 core
// Opaque node dots (GL_POINTS, gl_PointSize) or, with LINES defined, thin line segments
// widened to screen-space quads of u_width pixels (glLineWidth > 1 is not core).
// Positions are pulled u_bias mm towards the camera so dots on the surface win the depth
// test against the surface they sit on; clipping uses the unbiased position.
#ifndef MAX_CLIP_PLANES
#define MAX_CLIP_PLANES 4
#endif
layout(location = 0) in vec3 in_pos;     // world position, mm
layout(location = 1) in vec3 in_color;   // linear rgb 0..1
layout(location = 2) in float in_clip;   // 1: subject to the clip planes
#ifdef LINES
layout(location = 3) in vec3 in_other;   // the segment's other end
layout(location = 4) in float in_side;   // -1 / +1: which edge of the quad
uniform vec2 u_viewport;                 // render-target size, pixels
uniform float u_width;                   // line width, pixels
out vec3 v_world;
flat out float v_clip;
#else
uniform float u_size;                    // dot diameter, pixels
uniform int u_nplanes;
uniform vec4 u_planes[MAX_CLIP_PLANES];  // keep n.x <= d, stored as (n, d)
#endif
uniform mat4 u_mvp;
uniform vec3 u_eye;
uniform float u_bias;
out vec3 v_color;

vec4 project(vec3 p) {
    vec3 to_eye = u_eye - p;
    float len = length(to_eye);
    return u_mvp * vec4(len > 0.0 ? p + to_eye * (u_bias / len) : p, 1.0);
}

void main() {
    v_color = in_color;
#ifdef LINES
    v_world = in_pos;
    v_clip = in_clip;
    vec4 p0 = project(in_pos);
    vec4 p1 = project(in_other);
    vec2 half_vp = 0.5 * u_viewport;
    vec2 s0 = p0.xy / max(p0.w, 1e-6) * half_vp;
    vec2 s1 = p1.xy / max(p1.w, 1e-6) * half_vp;
    vec2 d = s1 - s0;
    float len = length(d);
    vec2 n = len > 1e-6 ? vec2(-d.y, d.x) / len : vec2(0.0, 1.0);
    vec2 offset = n * (in_side * 0.5 * u_width) / half_vp;
    gl_Position = p0 + vec4(offset * p0.w, 0.0, 0.0);
#else
    gl_PointSize = u_size;
    gl_Position = project(in_pos);
    if (in_clip > 0.5) {
        for (int i = 0; i < u_nplanes; ++i) {
            if (dot(u_planes[i].xyz, in_pos) > u_planes[i].w) {
                gl_Position = vec4(2.0, 2.0, 2.0, 1.0);  // outside the view volume: dropped
            }
        }
    }
#endif
}
