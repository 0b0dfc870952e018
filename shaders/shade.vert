#version 330 core
// Pass 3 (glsldiff.render.shading): the render mesh in world space (mm) with per-vertex
// normal, multiple-scattering radiance factor (the exitant bracket), shadow visibility per
// shader light and the view-dependent extras (single scattering, surface diffuse).
uniform mat4 u_mvp;
in vec3 in_pos;
in vec3 in_normal;
in vec3 in_ms;
in vec4 in_vis;
in vec3 in_ss;
out vec3 v_pos;
out vec3 v_normal;
out vec3 v_ms;
out vec4 v_vis;
out vec3 v_ss;
void main() {
    v_pos = in_pos; v_normal = in_normal; v_ms = in_ms; v_vis = in_vis; v_ss = in_ss;
    gl_Position = u_mvp * vec4(in_pos, 1.0);
}
