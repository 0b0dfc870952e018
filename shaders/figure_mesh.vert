#version 330 core
// Translucent surface of a node figure (glsldiff.figures): unshared triangle vertices
// with their face normal, in world space (mm).
layout(location = 0) in vec3 in_pos;
layout(location = 1) in vec3 in_normal;
uniform mat4 u_mvp;      // projection * view
out vec3 v_world;
out vec3 v_normal;

void main() {
    v_world = in_pos;
    v_normal = in_normal;
    gl_Position = u_mvp * vec4(in_pos, 1.0);
}
