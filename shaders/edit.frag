#version 330 core
// Material edit (Wang et al. 2008, section 5.4) as a GPU pass over the packed T_kappa / T_mu
// of one polygrid level: every texel reads its node's position from T_p, projects it into the
// edit view, weighs the edit by brush, mask and depth window, and writes the edited kappa and
// mu into T'_kappa / T'_mu (two render targets). The CPU twin (the oracle) is
// glsldiff.physics.editing: every formula here is written out there.
uniform sampler2D u_kappa;     // mm (rgb)
uniform sampler2D u_mu;        // mm^-1 (rgb)
uniform sampler2D u_pos;       // node position, mm (xyz); w = 1 at active nodes
uniform sampler2D u_mask;      // pattern mask (r), row 0 = the image's top row
uniform sampler2D u_surface;   // distance of the visible surface per view pixel, mm (r), row 0 = top
uniform mat4 u_mvp;            // world -> clip of the edit view
uniform vec2 u_view;           // W, H (pixels)
uniform vec3 u_eye;            // mm
uniform vec3 u_axis;           // orthographic view direction (u_ortho = 1)
uniform int u_ortho;
uniform int u_prop;            // 0: kappa, 1: mu
uniform int u_op;              // 0: set, 1: multiply, 2: add
uniform vec3 u_value;
uniform float u_strength;
uniform int u_restricted;      // a brush, mask or depth window is given
uniform int u_brush;
uniform vec2 u_centre;         // brush centre (pixels)
uniform float u_radius;        // brush radius (pixels)
uniform float u_inner;         // radius of full weight (pixels)
uniform int u_has_mask;
uniform vec2 u_mask_size;      // mask width, height (pixels)
uniform int u_has_depth;
uniform int u_has_surface;
uniform vec2 u_depth;          // depth window d0, d1 (mm below the visible surface)
uniform float u_kappa_min;
uniform float u_no_surface;
layout(location = 0) out vec4 f_kappa;
layout(location = 1) out vec4 f_mu;

float mask_at(vec2 uv) {
    vec2 m = uv * (u_mask_size / u_view) - 0.5;
    vec2 f0 = floor(m);
    vec2 f = m - f0;
    ivec2 hi = ivec2(u_mask_size) - 1;
    ivec2 a = clamp(ivec2(f0), ivec2(0), hi);
    ivec2 b = clamp(ivec2(f0) + 1, ivec2(0), hi);
    float m00 = texelFetch(u_mask, ivec2(a.x, a.y), 0).r, m10 = texelFetch(u_mask, ivec2(b.x, a.y), 0).r;
    float m01 = texelFetch(u_mask, ivec2(a.x, b.y), 0).r, m11 = texelFetch(u_mask, ivec2(b.x, b.y), 0).r;
    return (m00 * (1.0 - f.x) + m10 * f.x) * (1.0 - f.y) + (m01 * (1.0 - f.x) + m11 * f.x) * f.y;
}

float weight(vec3 p) {
    float w = u_strength;
    if (u_restricted == 0) return w;
    vec4 clip = u_mvp * vec4(p, 1.0);
    if (!(clip.w > 0.0)) return 0.0;
    vec2 ndc = clip.xy / clip.w;
    vec2 uv = vec2((ndc.x + 1.0) * 0.5 * u_view.x, (1.0 - ndc.y) * 0.5 * u_view.y);
    if (uv.x < 0.0 || uv.x > u_view.x || uv.y < 0.0 || uv.y > u_view.y) return 0.0;
    if (u_brush == 1) {
        float r = length(uv - u_centre);
        if (u_inner >= u_radius) {
            w *= (r <= u_radius) ? 1.0 : 0.0;
        } else {
            float t = clamp((u_radius - r) / (u_radius - u_inner), 0.0, 1.0);
            w *= t * t * (3.0 - 2.0 * t);
        }
    }
    if (u_has_mask == 1) w *= mask_at(uv);
    if (u_has_depth == 1) {
        float dist = (u_ortho == 1) ? dot(p - u_eye, u_axis) : length(p - u_eye);
        if (u_has_surface == 1) {
            ivec2 px = ivec2(floor(uv));
            if (px.x >= int(u_view.x) || px.y >= int(u_view.y)) return 0.0;
            float s = texelFetch(u_surface, px, 0).r;
            if (s >= u_no_surface) return 0.0;
            dist -= s;
        }
        if (!(dist >= u_depth.x && dist <= u_depth.y)) return 0.0;
    }
    return w;
}

vec3 edited(vec3 x, float w, float lo) {
    vec3 target = (u_op == 0) ? u_value : ((u_op == 1) ? x * u_value : x + u_value);
    return max(x + w * (target - x), vec3(lo));
}

void main() {
    ivec2 t = ivec2(gl_FragCoord.xy);
    vec4 k = texelFetch(u_kappa, t, 0);
    vec4 m = texelFetch(u_mu, t, 0);
    vec4 p = texelFetch(u_pos, t, 0);
    f_kappa = k;
    f_mu = m;
    if (p.w < 0.5) return;
    float w = weight(p.xyz);
    if (w <= 0.0) return;
    if (u_prop == 0) f_kappa.rgb = edited(k.rgb, w, u_kappa_min);
    else f_mu.rgb = edited(m.rgb, w, 0.0);
}
