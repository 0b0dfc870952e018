#version 330 core
// Flat-coloured round dots (gl_PointCoord) or, with LINES defined, line quads whose
// fragments on the positive side of an active clip plane are discarded.
#ifndef MAX_CLIP_PLANES
#define MAX_CLIP_PLANES 4
#endif
in vec3 v_color;
#ifdef LINES
in vec3 v_world;
flat in float v_clip;
uniform int u_nplanes;
uniform vec4 u_planes[MAX_CLIP_PLANES];
#endif
layout(location = 0) out vec4 f_color;

void main() {
#ifdef LINES
    if (v_clip > 0.5) {
        for (int i = 0; i < u_nplanes; ++i) {
            if (dot(u_planes[i].xyz, v_world) > u_planes[i].w) discard;
        }
    }
#else
    vec2 d = gl_PointCoord * 2.0 - 1.0;
    if (dot(d, d) > 1.0) discard;
#endif
    f_color = vec4(v_color, 1.0);
}
