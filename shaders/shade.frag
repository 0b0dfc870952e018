#version 330 core
// Pass 3 (glsldiff.render.shading), per fragment: L = F_t(eta, n.w_o) v_ms + v_ss
// + sum over lights of the Ward isotropic specular lobe
//   rho_s exp(-tan^2(theta_h) / alpha^2) / (4 pi alpha^2 sqrt(cos_i cos_o)) cos_i E vis.
// F_t: glsldiff.physics.optics.fresnel_transmittance; spot cone: lighting.spot_factor.
#ifndef MAX_LIGHTS
#define MAX_LIGHTS 4
#endif
uniform vec3 u_eye;
uniform float u_eta;
uniform float u_rho_s;
uniform float u_alpha;
uniform int u_nlights;
uniform int u_type[MAX_LIGHTS];       // 0 directional, 1 point (or projector), 2 spot
uniform vec3 u_lvec[MAX_LIGHTS];      // directional: towards the light; point/spot: position (mm)
uniform vec3 u_axis[MAX_LIGHTS];      // spot axis (from the light into the scene)
uniform vec3 u_power[MAX_LIGHTS];     // directional: irradiance; point/spot: intensity
uniform vec2 u_cone[MAX_LIGHTS];      // spot: cos(cone), cos(falloff)
in vec3 v_pos;
in vec3 v_normal;
in vec3 v_ms;
in vec4 v_vis;
in vec3 v_ss;
layout(location = 0) out vec4 f_color;

float fresnel_t(float eta, float c) {   // unpolarised dielectric transmittance, outside -> inside
    c = clamp(c, 0.0, 1.0);
    float s2 = (1.0 - c * c) / (eta * eta);
    if (s2 >= 1.0) return 0.0;
    float ct = sqrt(1.0 - s2);
    float rs = (c - eta * ct) / (c + eta * ct);
    float rp = (eta * c - ct) / (eta * c + ct);
    return 1.0 - 0.5 * (rs * rs + rp * rp);
}

void main() {
    vec3 n = normalize(v_normal);
    vec3 wo = normalize(u_eye - v_pos);
    float co = dot(n, wo);
    if (co <= 0.0) { n = -n; co = -co; }   // silhouette vertices interpolate past 90 degrees
    vec3 L = fresnel_t(u_eta, co) * v_ms + v_ss;
    for (int i = 0; i < u_nlights; ++i) {
        vec3 wi; vec3 E;
        if (u_type[i] == 0) { wi = normalize(u_lvec[i]); E = u_power[i]; }
        else {
            vec3 d = u_lvec[i] - v_pos; float r2 = dot(d, d); wi = d * inversesqrt(r2);
            E = u_power[i] / r2;
            if (u_type[i] == 2) {  // lighting.spot_factor; a hard edge where falloff = cone
                float c = dot(-wi, normalize(u_axis[i]));
                E *= u_cone[i].y - u_cone[i].x > 1e-6 ? smoothstep(u_cone[i].x, u_cone[i].y, c)
                                                      : step(u_cone[i].x, c);
            }
        }
        float ci = dot(n, wi);
        if (ci <= 0.0) continue;
        vec3 h = normalize(wi + wo);
        float ch = max(dot(n, h), 1e-4);
        float t2 = (1.0 - ch * ch) / (ch * ch);
        float f = u_rho_s * exp(-t2 / (u_alpha * u_alpha)) / (4.0 * 3.14159265 * u_alpha * u_alpha * sqrt(ci * co));
        L += f * ci * E * v_vis[i];
    }
    f_color = vec4(max(L, vec3(0.0)), 1.0);   // non-negative vertex values; interpolation round-off (-1e-14) is not light
}
