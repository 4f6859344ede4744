#version 330
// Textured, lit surfaces; doors get a frame, panels and a handle from their opening's (u, v) in [0, 1];
// glass (second pass) is blended over what lies behind it. Outputs BGR colour and (depth_m, instance).
uniform sampler2DArray tex;
uniform vec3 light_pos[4];
uniform vec3 light_col[4];
uniform int n_lights;
uniform vec3 ambient;
uniform float exposure;
uniform float noise_sigma;
uniform float frame_seed;
uniform vec3 cam_pos;
uniform vec3 sky_rgb;
uniform int glass_pass;
in vec3 v_pos;
flat in vec3 v_normal;
flat in vec3 v_tint;
in vec2 v_fuv;
flat in float v_layer;
flat in float v_inst;
flat in float v_kind;
flat in float v_style;
layout(location = 0) out vec4 out_colour;
layout(location = 1) out vec4 out_aux;

float hash(vec2 p) {  // integer hash of the pixel and the frame: cheaper than sin() on llvmpipe
    uvec2 q = uvec2(p);
    uint h = q.x * 1973u + q.y * 9277u + uint(frame_seed * 64.0) * 26699u;
    h = (h ^ (h >> 13u)) * 1274126177u;
    h ^= h >> 16u;
    return float(h & 65535u) / 65535.0;
}

float box(vec2 uv, vec4 r) { return float(uv.x > r.x && uv.x < r.z && uv.y > r.y && uv.y < r.w); }

float bevel(vec2 uv, vec4 r, float w) {  // -1 lower-left edge, +1 upper-right edge of a raised panel
    if (box(uv, r) < 0.5) return 0.0;
    float d = min(min(uv.x - r.x, r.z - uv.x), min(uv.y - r.y, r.w - uv.y));
    if (d > w) return 0.0;
    return (uv.x - r.x < w || uv.y - r.y < w) ? -1.0 : 1.0;
}

// A door's look from its style (materials.py): single leaves 0-9 (pattern = style mod 5, handle on the right
// below 5), double leaves 10-14 (pattern = style - 10, handles where the leaves meet). Patterns: two raised
// panels, four panels, a vision panel, a kick plate, two narrow vision slits (flush institutional doors).
vec3 leaf_pattern(vec3 base, vec3 frame, vec2 uv, float s, out float shine) {
    shine = 0.0;
    vec3 c = base;
    if (s < 1.0) {          // two raised panels
        float b = bevel(uv, vec4(0.2, 0.1, 0.8, 0.45), 0.012) + bevel(uv, vec4(0.2, 0.55, 0.8, 0.9), 0.012);
        c *= 1.0 + 0.25 * b;
    } else if (s < 2.0) {   // four panels
        float b = bevel(uv, vec4(0.15, 0.08, 0.46, 0.45), 0.012) + bevel(uv, vec4(0.54, 0.08, 0.85, 0.45), 0.012)
                + bevel(uv, vec4(0.15, 0.55, 0.46, 0.92), 0.012) + bevel(uv, vec4(0.54, 0.55, 0.85, 0.92), 0.012);
        c *= 1.0 + 0.25 * b;
    } else if (s < 3.0) {   // flush door with a vision panel
        if (box(uv, vec4(0.3, 0.58, 0.7, 0.88)) > 0.5) { c = vec3(0.18, 0.22, 0.25); shine = 0.5; }
        if (box(uv, vec4(0.28, 0.56, 0.72, 0.9)) > 0.5 && box(uv, vec4(0.3, 0.58, 0.7, 0.88)) < 0.5) c = frame;
    } else if (s < 4.0) {   // flush door with a metal kick plate
        if (uv.y < 0.1) { c = vec3(0.7, 0.72, 0.75); shine = 0.3; }
    } else {                // flush door with two narrow vision slits, one above the other
        float slit = box(uv, vec4(0.45, 0.56, 0.55, 0.86)) + box(uv, vec4(0.45, 0.14, 0.55, 0.44));
        float trim = box(uv, vec4(0.43, 0.54, 0.57, 0.88)) + box(uv, vec4(0.43, 0.12, 0.57, 0.46));
        if (trim > 0.5) c = frame;
        if (slit > 0.5) { c = vec3(0.12, 0.14, 0.16); shine = 0.5; }
    }
    return c;
}

vec3 door_pattern(vec3 base, vec2 uv, float style, out float shine) {
    shine = 0.0;
    float st = floor(style + 0.5);
    bool two = st > 9.5;
    vec3 frame = base * 0.55 + vec3(0.08);
    float fw = two ? 0.03 : 0.055;  // the frame's width, a fraction of the opening
    if (uv.x < fw || uv.x > 1.0 - fw || uv.y > 0.965) return frame;
    if (two && abs(uv.x - 0.5) < 0.006) return base * 0.35;  // the gap where the leaves meet
    // a leaf's own (u, v) in [0, 1]: a double door's leaves mirror each other, u = 1 where they meet
    vec2 luv = two ? vec2(uv.x < 0.5 ? 2.0 * uv.x : 2.0 * (1.0 - uv.x), uv.y) : uv;
    vec3 c = leaf_pattern(base, frame, luv, two ? st - 10.0 : mod(st, 5.0), shine);
    float hu = (two || st < 4.5) ? 0.86 : 0.14;  // handle side
    float hs = (hu > 0.5) ? -1.0 : 1.0;
    vec2 d = (luv - vec2(hu, 0.47)) * vec2(0.9, 2.1);  // metric-ish: a leaf is about 0.9 x 2.1 m
    if (length(d) < 0.035) { c = vec3(0.75, 0.74, 0.7); shine = 0.8; }
    if (abs(d.y) < 0.012 && d.x * hs > -0.01 && d.x * hs < 0.13) { c = vec3(0.82, 0.8, 0.75); shine = 0.8; }
    return c;
}

void main() {
    vec3 n = normalize(v_normal);
    vec3 view = normalize(cam_pos - v_pos);
    if (dot(n, view) < 0.0) n = -n;
    vec3 an = abs(n);
    vec2 uv = an.z > max(an.x, an.y) ? v_pos.xy : (an.x > an.y ? v_pos.yz : v_pos.xz);
    // style >= 16: a photo of a real door/window stretched across the opening (row 0 of the photo at the top)
    bool photo = v_style > 15.5 && v_fuv.x > -0.5;
    vec2 st = photo ? vec2(clamp(v_fuv.x, 0.0, 1.0), 1.0 - clamp(v_fuv.y, 0.0, 1.0)) : uv;
    vec3 base = texture(tex, vec3(st, v_layer)).rgb * v_tint;
    float shine = 0.0;
    float alpha = 1.0;
    if (v_kind > 0.5 && v_kind < 1.5 && v_fuv.x > -0.5 && !photo) {
        base = door_pattern(base, clamp(v_fuv, 0.0, 1.0), v_style, shine);
    }
    if (glass_pass == 1 && photo) {
        alpha = 0.92;
    } else if (glass_pass == 1) {
        float fres = pow(1.0 - max(dot(n, view), 0.0), 3.0);
        vec3 reflection = mix(vec3(0.55, 0.58, 0.6), sky_rgb, 0.5) * (0.8 + 0.2 * sin(v_pos.x * 3.0 + v_pos.z * 2.0));
        base = mix(v_tint * 0.6 + vec3(0.05, 0.08, 0.1), reflection, 0.4 + 0.5 * fres);
        alpha = clamp(0.22 + 0.6 * fres, 0.0, 0.85);
        float s = mod(v_style, 3.0);   // muntins across the pane
        if (v_fuv.x > -0.5 && ((s > 0.5 && abs(v_fuv.x - 0.5) < 0.012) || (s > 1.5 && abs(v_fuv.y - 0.5) < 0.01))) {
            base = v_tint;
            alpha = 1.0;
        }
    }
    vec3 light = ambient;
    for (int i = 0; i < n_lights; i++) {
        vec3 d = light_pos[i] - v_pos;
        float r2 = dot(d, d);
        vec3 l = d * inversesqrt(r2);
        float att = 1.0 / (1.0 + 0.08 * r2);
        light += light_col[i] * (att * max(dot(n, l), 0.0));
    }
    // highlight of the nearest light (lights come nearest first) on shiny parts: outside the loop, because
    // llvmpipe runs both sides of a branch for every pixel
    if (n_lights > 0) {
        vec3 d = light_pos[0] - v_pos;
        vec3 l = normalize(d);
        light += light_col[0] * (shine / (1.0 + 0.08 * dot(d, d)) * pow(max(dot(reflect(-l, n), view), 0.0), 20.0));
    }
    vec3 c = (glass_pass == 1) ? base * (0.6 + 0.4 * light) : base * light;
    c *= exposure * 1.4;
    c = c * (1.0 + 0.25 * c) / (1.0 + c);  // tone curve: ~linear in the shadows, saturates softly
    float nz = 2.0 * hash(gl_FragCoord.xy) - 1.0;  // uniform in [-1, 1]
    c += noise_sigma * 1.7 * nz;
    out_colour = vec4(c.bgr, alpha);
    out_aux = vec4(1.0 / gl_FragCoord.w, v_inst, 0.0, 1.0);  // 1/w = z along the optical axis
}
