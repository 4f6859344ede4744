#version 330
// CAD-frame triangles -> OpenCV pinhole camera (x right, y down, z forward). Rows come out top row first
// because v = 0 maps to NDC y = -1 (the first row read back).
uniform mat4 T_cam_cad;
uniform vec4 proj;     // 2fx/W, 2fy/H, 2(cx+0.5)/W-1, 2(cy+0.5)/H-1
uniform vec2 nearfar;  // metres
in vec3 in_pos;
in vec3 in_normal;
in vec3 in_tint;
in float in_layer;
in float in_inst;
in vec2 in_fuv;
in float in_kind;
in float in_style;
out vec3 v_pos;
flat out vec3 v_normal;  // per-triangle (face normals, one tint per element): flat is cheaper
flat out vec3 v_tint;
out vec2 v_fuv;
flat out float v_layer;
flat out float v_inst;
flat out float v_kind;
flat out float v_style;
void main() {
    vec4 pc = T_cam_cad * vec4(in_pos, 1.0);
    float n = nearfar.x, f = nearfar.y;
    gl_Position = vec4(proj.x * pc.x + proj.z * pc.z, proj.y * pc.y + proj.w * pc.z,
                       pc.z * (f + n) / (f - n) - 2.0 * f * n / (f - n), pc.z);
    v_pos = in_pos;
    v_normal = in_normal;
    v_tint = in_tint;
    v_fuv = in_fuv;
    v_layer = in_layer;
    v_inst = in_inst;
    v_kind = in_kind;
    v_style = in_style;
}
