#version 330 core
// Two-sided Lambert + ambient shading of the translucent surface; the opacity is
// u_alpha seen head-on and rises toward silhouettes (up to 2 u_alpha) so the shape reads.
// Fragments on the positive side of any active clip plane are discarded when u_clip != 0.
#ifndef MAX_CLIP_PLANES
#define MAX_CLIP_PLANES 4
#endif
in vec3 v_world;
in vec3 v_normal;
uniform vec3 u_color;       // surface albedo (linear 0..1)
uniform float u_alpha;      // head-on opacity
uniform float u_ambient;    // ambient fraction
uniform vec3 u_light;       // unit direction towards the light (world)
uniform vec3 u_eye;         // camera position (world, mm)
uniform int u_clip;         // clip the surface too
uniform int u_nplanes;      // active clip planes
uniform vec4 u_planes[MAX_CLIP_PLANES];  // keep n.x <= d, stored as (n, d)
layout(location = 0) out vec4 f_color;

void main() {
    if (u_clip != 0) {
        for (int i = 0; i < u_nplanes; ++i) {
            if (dot(u_planes[i].xyz, v_world) > u_planes[i].w) discard;
        }
    }
    vec3 n = normalize(v_normal);
    vec3 v = normalize(u_eye - v_world);
    float ndv = dot(n, v);
    if (ndv < 0.0) {  // back face seen through the front: light its visible side
        n = -n;
        ndv = -ndv;
    }
    float diffuse = max(dot(n, u_light), 0.0);
    vec3 c = u_color * (u_ambient + (1.0 - u_ambient) * diffuse);
    float rim = 1.0 - ndv;
    float a = clamp(u_alpha * (1.0 + rim * rim), 0.0, 1.0);
    f_color = vec4(c, a);
}
