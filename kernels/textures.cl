// Textures: colours and roughnesses that vary over a surface, looked up at a hit's texture
// coordinates (u, v). Every texture of a scene lives in two buffers (worker/surfaces.py,
// texture_table): TEX_ROWS float4 rows a texture in tex_info,
//   row 0: flags (kind TEX_* | wrap mode WRAP_* << 2 | TEX_NEAREST | TEX_GREY | TEX_BYTES),
//          byte offset of its data in tex_texels, width, height (int bits)
//   row 1, 2: to_uv, the affine map to the texture's own coordinates: u' = row1.xyz . (u, v, 1),
//             v' = row2.xyz . (u, v, 1)
// and its data in tex_texels, from a multiple of 16 bytes: the values, linear and in [0, 1],
// with TEX_BYTES an 8-bit image's bytes after a table of 256 floats, each byte's linear value
// (half the bytes of half floats: fewer cache misses), else half floats; a texel 4 values (rgb
// and a pad: one aligned load) or 1 (TEX_GREY); a bitmap's rows from the image's top row
// (v' = 0) down, a checkerboard's two colours as two texels.
// Lookups follow Mitsuba 3's bitmap and checkerboard textures: bilinear between the texel
// centres at (u' width - 1/2, v' height - 1/2), nearest the texel at floor(u' width, v' height),
// the wrap mode applied to the texel indices; and a checkerboard of unit cells, colour 0 where
// floor(u') + floor(v') is even.
//
// Surface coordinates (the shapes' own parameterisations): a triangle's from its corners'
// (tex_uv: a mesh's own, a quad's (s, t), else (0, 0), (1, 0), (0, 1)) by its barycentrics at
// the point; a sphere's (phi / 2 pi, theta / pi) about its centre, phi in [0, 2 pi) from +x
// towards +y, theta from +z (Mitsuba 3's sphere).

// A surface point's primitive as one int: the triangle's index, or -2 - the sphere's.
inline int hit_prim(const Hit* h) { return h->tri >= 0 ? h->tri : -2 - h->sphere; }

inline float2 prim_uv(const SceneGeom* g, int prim, float3 p) {
    if (prim < 0) {
        float4 s = g->spheres[-2 - prim];
        float3 l = (p - s.xyz) / s.w;
        float phi = atan2(l.y, l.x);
        if (phi < 0.0f) phi += 2.0f * PI_F;
        return (float2)(phi / (2.0f * PI_F), acos(clamp(l.z, -1.0f, 1.0f)) / PI_F);
    }
    // Barycentrics of p in the triangle's plane (the normal equations of p - v0 = b1 e1 + b2 e2).
    float3 e1 = g->tri_e1[prim].xyz, e2 = g->tri_e2[prim].xyz, w = p - g->tri_v0[prim].xyz;
    float d11 = dot3(e1, e1), d12 = dot3(e1, e2), d22 = dot3(e2, e2), w1 = dot3(w, e1), w2 = dot3(w, e2);
    float inv = 1.0f / (d11 * d22 - d12 * d12);
    float b1 = (d22 * w1 - d12 * w2) * inv, b2 = (d11 * w2 - d12 * w1) * inv;
    __global const float2* c = g->tex_uv + 3 * prim;
    return (1.0f - b1 - b2) * c[0] + b1 * c[1] + b2 * c[2];
}

// A texture coordinate reduced to one period of its wrap mode, in [0, 1] (repeat: [0, 1)):
// the texel indices it then gives, each clamped to [0, n - 1], are the wrap mode's indices
// of the unreduced one (a mirrored period is the texels in reverse order, so the fold at an
// integer coordinate meets the index fold between texels n - 1 and n).
inline float wrap_coordinate(float x, int mode) {
    if (mode == WRAP_CLAMP) return clamp(x, 0.0f, 1.0f);
    if (mode == WRAP_MIRROR) {
        float t = x - 2.0f * floor(0.5f * x);  // [0, 2)
        return t > 1.0f ? 2.0f - t : t;
    }
    return x - floor(x);
}

// Texel k of the texture whose data starts at byte `at` of `texels`.
inline float3 texel(__global const uchar* texels, int at, int k, int flags) {
    if (flags & TEX_BYTES) {
        __global const float* decode = (__global const float*)(texels + at);
        __global const uchar* bytes = texels + at + 256 * sizeof(float);
        if (flags & TEX_GREY) return (float3)(decode[bytes[k]]);
        uchar4 b = ((__global const uchar4*)bytes)[k];
        return (float3)(decode[b.x], decode[b.y], decode[b.z]);
    }
    __global const half* values = (__global const half*)(texels + at);
    if (flags & TEX_GREY) return (float3)(vload_half(k, values));
    return vload_half4(k, values).xyz;
}

inline float3 texture_eval(const SceneGeom* g, int tex, float2 uv) {
    __global const float4* r = g->tex_info + TEX_ROWS * tex;
    int4 head = as_int4(r[0]);
    float4 ru = r[1], rv = r[2];
    float u = ru.x * uv.x + ru.y * uv.y + ru.z, v = rv.x * uv.x + rv.y * uv.y + rv.z;
    int flags = head.x, at = head.y, w = head.z, h = head.w;
    __global const uchar* texels = g->tex_texels;
    if ((flags & 3) == TEX_CHECKERBOARD) {
        int parity = ((int)floor(u - 2.0f * floor(0.5f * u)) + (int)floor(v - 2.0f * floor(0.5f * v))) & 1;
        return texel(texels, at, parity, flags);
    }
    int mode = (flags >> 2) & 3;
    float x = wrap_coordinate(u, mode) * (float)w, y = wrap_coordinate(v, mode) * (float)h;
    if (flags & TEX_NEAREST) return texel(texels, at, min((int)y, h - 1) * w + min((int)x, w - 1), flags);
    x -= 0.5f;
    y -= 0.5f;
    float fx = floor(x), fy = floor(y), ax = x - fx, ay = y - fy;
    int x0 = (int)fx, y0 = (int)fy, x1 = x0 + 1, y1 = y0 + 1;
    if (mode == WRAP_REPEAT) {  // indices -1 and n are the far ends' texels
        x0 = x0 < 0 ? w - 1 : x0;
        y0 = y0 < 0 ? h - 1 : y0;
        x1 = x1 == w ? 0 : x1;
        y1 = y1 == h ? 0 : y1;
    } else {
        x0 = max(x0, 0);
        y0 = max(y0, 0);
        x1 = min(x1, w - 1);
        y1 = min(y1, h - 1);
    }
    int row0 = y0 * w, row1 = y1 * w;
    float3 top = mix(texel(texels, at, row0 + x0, flags), texel(texels, at, row0 + x1, flags), ax);
    float3 bottom = mix(texel(texels, at, row1 + x0, flags), texel(texels, at, row1 + x1, flags), ax);
    return mix(top, bottom, ay);
}

// A texture's value where one number is asked for (a roughness, an opacity), as Mitsuba 3's
// eval_1: a bitmap's luminance, a checkerboard's colour's mean over its channels.
inline float texture_scalar(const SceneGeom* g, int tex, float2 uv) {
    float3 c = texture_eval(g, tex, uv);
    bool checks = (as_int(g->tex_info[TEX_ROWS * tex].x) & 3) == TEX_CHECKERBOARD;
    return checks ? (c.x + c.y + c.z) / 3.0f : dot(c, (float3)(LUM_R, LUM_G, LUM_B));
}

// Surface `surf`'s material at point p of primitive `prim` (hit_prim): its record, with the
// textured values looked up there. A record without textures is loaded as it is.
inline Material surface_material(const SceneGeom* g, __global const float4* surfaces, int surf, int prim, float3 p) {
    Material m = load_material(surfaces, surf);
    if (!(m.flags & MF_TEXTURED)) return m;
    int4 t = as_int4(surfaces[SURF_ROWS * surf + 4]);
    float2 uv = prim_uv(g, prim, p);
    if (t.x >= 0) m.base = texture_eval(g, t.x, uv);
    if (t.y >= 0) m.second = texture_eval(g, t.y, uv);
    if (t.z >= 0) m.rough = clamp(texture_scalar(g, t.z, uv), 0.001f, 1.0f);  // Roughness's range (worker/scene.py)
    if (t.w >= 0) m.opacity = clamp(texture_scalar(g, t.w, uv), 0.0f, 1.0f);
    return m;
}

inline Material hit_material(const SceneGeom* g, __global const float4* surfaces, const Hit* h, float3 p) {
    return surface_material(g, surfaces, h->surf, hit_prim(h), p);
}

// A light vertex's textured values, kept where it is stored (vcm_light_pass.cl; lv_tex, two
// float4 a vertex, written for textured materials only): the fields surface_material fills
// in, so that the camera pass's connections to it (vcm_camera_pass.cl) look none up again.
inline void store_textured(__global float4* lv_tex, uint slot, const Material* m) {
    lv_tex[2 * slot] = (float4)(m->base, m->rough);
    lv_tex[2 * slot + 1] = (float4)(m->second, m->opacity);
}

inline Material stored_material(__global const float4* surfaces, int surf, __global const float4* lv_tex, uint slot) {
    Material m = load_material(surfaces, surf);
    if (!(m.flags & MF_TEXTURED)) return m;
    float4 a = lv_tex[2 * slot], b = lv_tex[2 * slot + 1];
    m.base = a.xyz;
    m.rough = a.w;
    m.second = b.xyz;
    m.opacity = b.w;
    return m;
}
