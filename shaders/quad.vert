#version 330 core
// Rectangles over texel ranges (grid-transfer passes of the multiresolution polygrid).
layout(location = 0) in vec2 in_pos;     // texel-space corner (x, y)
uniform vec2 u_size;                     // render-target region in texels

void main() {
    gl_Position = vec4(in_pos / u_size * 2.0 - 1.0, 0.0, 1.0);
}
