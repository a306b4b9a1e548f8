"""GLSL 330 shaders of the IBR renderer (Xu et al. 2021, §5.1.3–5.1.4), as strings.

One vertex shader for every pass: world-space positions of a per-view mesh are projected into the
novel camera (`P_n`, OpenCV intrinsics → clip space, image row v at GL row v) and into the mesh's
own source camera (`S_k` = K_k [R_k | t_k], homogeneous pixel coordinates, interpolated
perspective-correctly, divided per fragment = exact projective texturing).

Passes (ibr.py runs them per layer over the selected views):
  COST   min-blend the per-fragment IBR cost (§5.1.3, Hedman et al. 2016) → smallest cost per pixel
  FRONT  min-blend the z-depth of fragments whose cost ≤ smallest + margin → front-most depth map
  BLEND  additive blend of w_k · alpha · (rgb, 1) and w_k · alpha · beta for fragments within
         depth_tol of the front-most depth (fuzzy depth test); Eq. 15 weights w_k per view.
"""

VERTEX = """
#version 330
uniform mat4 P_n;        // novel camera: world -> clip
uniform mat4 S_k;        // source camera: world -> (u z, v z, z, 1)
uniform mat4 V_n;        // novel camera: world -> camera (for z-depth)
in vec3 in_pos;
out vec3 v_world;
out vec3 v_src;
out float v_z;
void main() {
    vec4 p = vec4(in_pos, 1.0);
    gl_Position = P_n * p;
    v_world = in_pos;
    v_src = (S_k * p).xyz;
    v_z = (V_n * p).z;
}
"""

_COMMON = """
#version 330
uniform vec3 t_k;        // optical centre of the source view
uniform vec3 t_n;        // optical centre of the novel view
uniform vec2 src_size;   // source image (width, height)
in vec3 v_world;
in vec3 v_src;
in float v_z;
// §5.1.3: c = angle(t_k - x, t_n - x) * pi/180 + max(0, 1 - |t_n - x| / |t_k - x|)  (radians)
float ibr_cost(vec3 x) {
    vec3 a = t_k - x;
    vec3 b = t_n - x;
    float la = max(length(a), 1e-9);
    float lb = max(length(b), 1e-9);
    float c = clamp(dot(a, b) / (la * lb), -1.0, 1.0);
    return acos(c) + max(0.0, 1.0 - lb / la);
}
bool src_uv(out vec2 uv) {
    if (v_src.z <= 1e-6) return false;
    vec2 px = v_src.xy / v_src.z;                    // pixel centre (0, 0) convention
    uv = (px + 0.5) / src_size;
    return all(greaterThanEqual(uv, vec2(0.0))) && all(lessThanEqual(uv, vec2(1.0)));
}
"""

COST = _COMMON + """
out vec4 f_cost;
void main() {
    vec2 uv;
    if (v_z <= 0.0 || !src_uv(uv)) discard;
    f_cost = vec4(ibr_cost(v_world));
}
"""

FRONT = _COMMON + """
uniform sampler2D cost_min;
uniform float cost_margin;   // §5.1.3: 0.17
out vec4 f_depth;
void main() {
    vec2 uv;
    if (v_z <= 0.0 || !src_uv(uv)) discard;
    float cmin = texelFetch(cost_min, ivec2(gl_FragCoord.xy), 0).r;
    if (ibr_cost(v_world) > cmin + cost_margin) discard;
    f_depth = vec4(v_z);
}
"""

BLEND = _COMMON + """
uniform sampler2D front;      // front-most depth map of this layer
uniform sampler2D tex_rgba;   // source layer image, alpha = feathering x edge decay (§5.1.4)
uniform sampler2D tex_beta;   // source beta (layer 0 only)
uniform float depth_tol;      // §5.1.3: 0.03 m
uniform float w_k;            // Eq. 15: exp(-d_k / delta)
uniform bool has_beta;        // false: beta = 0 everywhere in this view (skip the fetch)
layout(location = 0) out vec4 f_acc;
layout(location = 1) out vec4 f_beta;
void main() {
    vec2 uv;
    if (v_z <= 0.0 || !src_uv(uv)) discard;
    float zf = texelFetch(front, ivec2(gl_FragCoord.xy), 0).r;
    if (abs(v_z - zf) >= depth_tol) discard;
    vec4 c = texture(tex_rgba, uv);
    float w = w_k * c.a;
    f_acc = vec4(w * c.rgb, w);
    f_beta = vec4(has_beta ? w * texture(tex_beta, uv).r : 0.0, 0.0, 0.0, 0.0);
}
"""

# Debug / reference pass: one view alone, ordinary depth test, every quantity the blend uses.
SINGLE = _COMMON + """
uniform sampler2D tex_rgba;
uniform sampler2D tex_beta;
layout(location = 0) out vec4 f_rgba;
layout(location = 1) out vec4 f_geo;     // (z, cost, beta, 1)
void main() {
    vec2 uv;
    if (v_z <= 0.0 || !src_uv(uv)) discard;
    f_rgba = texture(tex_rgba, uv);
    f_geo = vec4(v_z, ibr_cost(v_world), texture(tex_beta, uv).r, 1.0);
}
"""
