#version 330 core
// Shadow map of glsldiff.render.shadows: mesh vertices (mm, relative to the mesh's bounding-sphere
// centre) seen from a light.
layout(location = 0) in vec3 in_pos;
uniform mat4 u_mvp;      // projection * view of one light view (one cube face or the whole map)
out vec3 v_pos;

void main() {
    v_pos = in_pos;
    gl_Position = u_mvp * vec4(in_pos, 1.0);
}
