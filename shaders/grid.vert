#version 330 core
// Rectangles over texel ranges of the packed grid (one per slice block, face or
// block edge strip). Per-primitive texel offsets to the neighbours that are not
// adjacent in the texture travel as flat integer attributes (Wang et al. 2008, sec. 5.2).
layout(location = 0) in vec2 in_pos;     // texel-space corner (x, y)
layout(location = 1) in ivec2 in_off0;   // interior: offset to slice z-1; boundary: to linked interior node
layout(location = 2) in ivec2 in_off1;   // interior: offset to slice z+1; boundary: unused
uniform vec2 u_size;                     // texture size in texels
flat out ivec2 v_off0;
flat out ivec2 v_off1;

void main() {
    v_off0 = in_off0;
    v_off1 = in_off1;
    gl_Position = vec4(in_pos / u_size * 2.0 - 1.0, 0.0, 1.0);
}
