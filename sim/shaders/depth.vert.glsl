#version 330
// Depth pre-pass: the same projection as scene.vert.glsl, positions only.
uniform mat4 T_cam_cad;
uniform vec4 proj;
uniform vec2 nearfar;
in vec3 in_pos;
void main() {
    vec4 pc = T_cam_cad * vec4(in_pos, 1.0);
    float n = nearfar.x, f = nearfar.y;
    gl_Position = vec4(proj.x * pc.x + proj.z * pc.z, proj.y * pc.y + proj.w * pc.z,
                       pc.z * (f + n) / (f - n) - 2.0 * f * n / (f - n), pc.z);
}
