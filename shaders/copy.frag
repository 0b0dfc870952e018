#version 330 core
// Texel-exact copy of one buffer into the other of a ping-pong pair.
uniform sampler2D u_src;
layout(location = 0) out vec4 f_color;

void main() {
    f_color = texelFetch(u_src, ivec2(gl_FragCoord.xy), 0);
}
