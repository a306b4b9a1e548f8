// GLSL ES 3.00 of the viewer's own passes: everything render/ibr.py does after its GL passes
// (normalise, hole filling by push-pull, Eq. 3 composition) and the per_view visibility blend,
// ported from render/blend.py so that the frame stays on the GPU. All full-screen passes share
// FULLSCREEN (one triangle from gl_VertexID).
const HEAD = `#version 300 es
precision highp float;
precision highp int;
precision highp sampler2D;
`;

export const FULLSCREEN = `#version 300 es
void main() {
    vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
    gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0);
}`;

// per_view visibility (IBRModel._render_layer_per_view): one view z-buffered alone (SINGLE pass),
// added with weight w_k x texture alpha where it covers the pixel
export const ACCUM = HEAD + `
uniform sampler2D rgba;   // SINGLE's f_rgba: (rgb, alpha)
uniform sampler2D geo;    // SINGLE's f_geo: (z, cost, beta, covered)
uniform float w_k;
layout(location = 0) out vec4 f_acc;
layout(location = 1) out vec4 f_beta;
void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    vec4 g = texelFetch(geo, p, 0);
    if (g.a <= 0.0) discard;
    vec4 c = texelFetch(rgba, p, 0);
    float w = w_k * c.a;
    f_acc = vec4(w * c.rgb, w);
    f_beta = vec4(w * g.b, 0.0, 0.0, 0.0);
}`;

// the normalised blend (rgb, beta) where covered, 0 elsewhere = push-pull level 0 (colour x
// weight, weight) with weight = covered
export const NORMALIZE = HEAD + `
uniform sampler2D acc;
uniform sampler2D bacc;
layout(location = 0) out vec4 f_cw;
layout(location = 1) out vec4 f_w;
void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    vec4 a = texelFetch(acc, p, 0);
    bool cov = a.a > 0.0;
    float inv = cov ? 1.0 / a.a : 0.0;
    f_cw = cov ? vec4(a.rgb * inv, texelFetch(bacc, p, 0).r * inv) : vec4(0.0);
    f_w = vec4(cov ? 1.0 : 0.0, 0.0, 0.0, 0.0);
}`;

// push: cv2.resize(INTER_AREA) to the next level (size ceil(n / 2)): each texel averages the source
// texels it overlaps, weighted by the overlap (exact for odd sizes too)
export const DOWN = HEAD + `
uniform sampler2D src_cw;
uniform sampler2D src_w;
uniform vec2 ratio;       // source size / destination size, per axis
layout(location = 0) out vec4 f_cw;
layout(location = 1) out vec4 f_w;
void main() {
    ivec2 size = textureSize(src_w, 0);
    vec2 lo = floor(gl_FragCoord.xy) * ratio;
    vec2 hi = lo + ratio;
    vec4 cw = vec4(0.0);
    float w = 0.0;
    for (int y = int(floor(lo.y)); y < int(ceil(hi.y)) && y < size.y; y++) {
        float wy = min(hi.y, float(y + 1)) - max(lo.y, float(y));
        for (int x = int(floor(lo.x)); x < int(ceil(hi.x)) && x < size.x; x++) {
            float a = wy * (min(hi.x, float(x + 1)) - max(lo.x, float(x)));
            cw += a * texelFetch(src_cw, ivec2(x, y), 0);
            w += a * texelFetch(src_w, ivec2(x, y), 0).r;
        }
    }
    float area = ratio.x * ratio.y;
    f_cw = cw / area;
    f_w = vec4(w / area, 0.0, 0.0, 0.0);
}`;

// bilinear sample of a float texture at destination texel centres (cv2 INTER_LINEAR: half-pixel
// centres, coordinates clamped at the border)
const BILINEAR = `
vec4 bilinear(sampler2D t, vec2 dst_px, vec2 ratio) {
    ivec2 size = textureSize(t, 0);
    vec2 s = clamp((dst_px + 0.5) * ratio - 0.5, vec2(0.0), vec2(size - 1));
    ivec2 i0 = ivec2(floor(s));
    ivec2 i1 = min(i0 + 1, size - 1);
    vec2 f = s - vec2(i0);
    vec4 a = mix(texelFetch(t, i0, 0), texelFetch(t, ivec2(i1.x, i0.y), 0), f.x);
    vec4 b = mix(texelFetch(t, ivec2(i0.x, i1.y), 0), texelFetch(t, i1, 0), f.x);
    return mix(a, b, f.y);
}`;

// pull: blend._pyramid_fill's upward pass; `coarse_ok` false at the top level (no coarser one)
export const UP = HEAD + BILINEAR + `
uniform sampler2D cw;
uniform sampler2D w;
uniform sampler2D coarse;
uniform bool has_coarse;
uniform vec2 ratio;       // coarse size / this size
out vec4 f_out;
void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    float ww = texelFetch(w, p, 0).r;
    vec4 own = texelFetch(cw, p, 0) / max(ww, 1e-12);
    if (!has_coarse) { f_out = own; return; }
    float a = min(ww * 4.0, 1.0);   // well-covered cells keep their own colour
    f_out = a * own + (1.0 - a) * bilinear(coarse, floor(gl_FragCoord.xy), ratio);
}`;

// blend.fill_holes: the warped colour where covered, decaying to the push-pull fill within
// decay_px of a hole (OpenCV's 3x3 chamfer L2 distance: 0.955 per step, 1.3693 per diagonal)
export const FILL = HEAD + BILINEAR + `
uniform sampler2D color;   // level-0 colour (0 where uncovered)
uniform sampler2D covered; // level-0 weight (1 covered, 0 hole)
uniform sampler2D fill;    // pull result at level 1
uniform vec2 ratio;        // level-1 size / full size
uniform float decay_px;
uniform int radius;
uniform bool enabled;
out vec4 f_out;
void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    ivec2 size = textureSize(covered, 0);
    vec4 c = texelFetch(color, p, 0);
    if (!enabled) { f_out = c; return; }
    bool cov = texelFetch(covered, p, 0).r > 0.5;
    float d = 1e9;
    if (cov) {
        for (int dy = -radius; dy <= radius; dy++) {
            for (int dx = -radius; dx <= radius; dx++) {
                ivec2 q = p + ivec2(dx, dy);
                if (any(lessThan(q, ivec2(0))) || any(greaterThanEqual(q, size))) continue;
                if (texelFetch(covered, q, 0).r > 0.5) continue;
                float lo = float(min(abs(dx), abs(dy))), hi = float(max(abs(dx), abs(dy)));
                d = min(d, 1.3693 * lo + 0.955 * (hi - lo));
            }
        }
    } else {
        d = 0.0;
    }
    float a = min(d / max(decay_px, 1e-9), 1.0);
    f_out = a >= 1.0 ? c : a * c + (1.0 - a) * bilinear(fill, floor(gl_FragCoord.xy), ratio);
}`;

// Eq. 3 composition (layers blended as stored sRGB values are decoded first: post_nb.finish),
// clamp, and display: linear -> sRGB for the canvas, rows flipped (image row 0
// is GL row 0 in the offline convention, the top of the canvas here)
export const COMPOSE = HEAD + `
uniform sampler2D layer0;  // filled (I0 rgb, beta)
uniform sampler2D layer1;  // filled I1
uniform int mode;          // 0 I0 + beta I1, 1 I0, 2 beta I1, 3 layer0 as it is (single layer)
uniform bool has_layer1;
uniform bool decode_srgb;  // the layers hold sRGB values (RenderSettings.blend_space stored)
out vec4 f_color;
vec3 to_linear(vec3 x) {
    x = clamp(x, 0.0, 1.0);
    return mix(x / 12.92, pow((x + 0.055) / 1.055, vec3(2.4)), step(vec3(0.04045), x));
}
vec3 to_srgb(vec3 x) {
    x = clamp(x, 0.0, 1.0);
    return mix(12.92 * x, 1.055 * pow(x, vec3(1.0 / 2.4)) - 0.055, step(vec3(0.0031308), x));
}
void main() {
    ivec2 size = textureSize(layer0, 0);
    ivec2 p = ivec2(int(gl_FragCoord.x), size.y - 1 - int(gl_FragCoord.y));
    vec4 l0 = texelFetch(layer0, p, 0);
    float beta = clamp(l0.a, 0.0, 1.0);
    vec3 i1 = has_layer1 ? texelFetch(layer1, p, 0).rgb : vec3(0.0);
    if (decode_srgb) {
        l0.rgb = to_linear(l0.rgb);
        i1 = to_linear(i1);
    }
    vec3 c = mode == 1 ? l0.rgb : mode == 2 ? beta * i1 : mode == 3 ? l0.rgb : l0.rgb + beta * i1;
    f_color = vec4(to_srgb(max(c, vec3(0.0))), 1.0);
}`;

// camera frusta and path: world-space lines in the current camera, flipped like COMPOSE
export const LINES_VS = `#version 300 es
uniform mat4 P_n;
in vec3 in_pos;
in vec3 in_color;
out vec3 v_color;
void main() {
    vec4 p = P_n * vec4(in_pos, 1.0);
    gl_Position = vec4(p.x, -p.y, p.z, p.w);
    v_color = in_color;
}`;
export const LINES_FS = `#version 300 es
precision highp float;
in vec3 v_color;
out vec4 f_color;
void main() { f_color = vec4(v_color, 1.0); }`;
