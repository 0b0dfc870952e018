#version 330 core
// Quads (two triangles), lines and points over texel runs of a packed grid (Wang et al. 2008,
// section 5.2, figure 7; glsldiff.solve.stencil.pass_primitives). Each primitive carries the
// texel offsets to the six neighbours of its nodes (interior pass, order x-, x+, y-, y+, z-, z+)
// or to the interior partner (boundary pass, in_off0) as flat integer attributes.
layout(location = 0) in vec2 in_pos;     // texel-space vertex (x, y)
layout(location = 1) in ivec2 in_off0;
layout(location = 2) in ivec2 in_off1;
layout(location = 3) in ivec2 in_off2;
layout(location = 4) in ivec2 in_off3;
layout(location = 5) in ivec2 in_off4;
layout(location = 6) in ivec2 in_off5;
uniform vec2 u_size;                     // texture size in texels
flat out ivec2 v_off0;
flat out ivec2 v_off1;
flat out ivec2 v_off2;
flat out ivec2 v_off3;
flat out ivec2 v_off4;
flat out ivec2 v_off5;
void main() {
    v_off0 = in_off0; v_off1 = in_off1; v_off2 = in_off2;
    v_off3 = in_off3; v_off4 = in_off4; v_off5 = in_off5;
    gl_Position = vec4(in_pos / u_size * 2.0 - 1.0, 0.0, 1.0);
}
