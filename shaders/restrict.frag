#version 330 core
// Restriction to a coarser polygrid level (glsldiff.grids.hierarchy.Transfer.restrict_kind): each
// coarse node takes the mean of the fine values at its children of its own kind (interior
// from interior, boundary from boundary; removed coarse nodes 0). Children are found by index
// arithmetic on the packing of figure 6: blocks of n x n texels (one x-y slice of a cube),
// tiles_x blocks per texture row, cube-major then z.
uniform sampler2D u_fine;   // fine values (residual)
uniform sampler2D u_w1f;    // fine T_w1: .a > 0 interior (row scale), .r > 0 boundary (d)
uniform sampler2D u_w1c;    // coarse T_w1
uniform int u_nc;           // coarse nodes per cube edge (fine: 2 u_nc)
uniform int u_txc;          // coarse blocks per texture row
uniform int u_txf;          // fine blocks per texture row
layout(location = 0) out vec4 f_color;

int kind(vec4 w1) { return w1.a > 0.0 ? 1 : (w1.r > 0.0 ? 2 : 0); }

void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    int kc = kind(texelFetch(u_w1c, p, 0));
    vec3 sum = vec3(0.0);
    float count = 0.0;
    if (kc != 0) {
        ivec2 tile = p / u_nc;
        ivec2 loc = p - tile * u_nc;
        int block = tile.y * u_txc + tile.x;
        int cube = block / u_nc;
        int z = block - cube * u_nc;
        int nf = 2 * u_nc;
        for (int dz = 0; dz < 2; ++dz) {
            int bf = cube * nf + 2 * z + dz;
            ivec2 origin = ivec2(bf % u_txf, bf / u_txf) * nf + 2 * loc;
            for (int dy = 0; dy < 2; ++dy) {
                for (int dx = 0; dx < 2; ++dx) {
                    ivec2 t = origin + ivec2(dx, dy);
                    if (kind(texelFetch(u_w1f, t, 0)) == kc) {
                        sum += texelFetch(u_fine, t, 0).rgb;
                        count += 1.0;
                    }
                }
            }
        }
    }
    f_color = vec4(count > 0.0 ? sum / count : vec3(0.0), 0.0);
}
