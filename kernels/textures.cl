// Textures: colours and roughnesses that vary over a surface, looked up at a hit's texture
// coordinates (u, v). Every texture of a scene lives in two buffers (worker/surfaces.py,
// texture_table): TEX_ROWS float4 rows a texture in tex_info,
//   row 0: kind TEX_*, offset of its first value in tex_texels, width, height (int bits)
//   row 1, 2: to_uv, the affine map to the texture's own coordinates: u' = row1.xyz . (u, v, 1),
//             v' = row2.xyz . (u, v, 1)
//   row 3: wrap mode WRAP_*, 1 for nearest filtering (0: bilinear), channels (1 or 3) (int bits)
// and the values, linear and in [0, 1], in tex_texels: a bitmap's rows from the image's top
// row (v' = 0) down, `channels` values a texel; a checkerboard's two colours as two rgb texels.
// Lookups follow Mitsuba 3's bitmap and checkerboard textures: bilinear between the texel
// centres at (u' width - 1/2, v' height - 1/2), nearest the texel at floor(u' width, v' height),
// and a checkerboard of unit cells, colour 0 where floor(u') + floor(v') is even.
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
    float d11 = dot(e1, e1), d12 = dot(e1, e2), d22 = dot(e2, e2), w1 = dot(w, e1), w2 = dot(w, e2);
    float inv = 1.0f / (d11 * d22 - d12 * d12);
    float b1 = (d22 * w1 - d12 * w2) * inv, b2 = (d11 * w2 - d12 * w1) * inv;
    __global const float2* c = g->tex_uv + 3 * prim;
    return (1.0f - b1 - b2) * c[0] + b1 * c[1] + b2 * c[2];
}

// Texel index i of a row or column of n under a wrap mode.
inline int wrap_index(int i, int n, int mode) {
    if (mode == WRAP_CLAMP) return clamp(i, 0, n - 1);
    if (mode == WRAP_MIRROR) {
        int m = i % (2 * n);
        m = m < 0 ? m + 2 * n : m;
        return m < n ? m : 2 * n - 1 - m;
    }
    int m = i % n;
    return m < 0 ? m + n : m;
}

// floor(x) as an int, x kept within int range (far texture coordinates repeat all the same).
inline int floor_int(float x) { return (int)floor(clamp(x, -1.0e9f, 1.0e9f)); }

inline float3 texel(__global const float* texels, int4 head, int channels, int x, int y) {
    __global const float* t = texels + head.y + (y * head.z + x) * channels;
    return channels == 1 ? (float3)(t[0]) : (float3)(t[0], t[1], t[2]);
}

inline float3 texture_eval(const SceneGeom* g, int tex, float2 uv) {
    __global const float4* r = g->tex_info + TEX_ROWS * tex;
    int4 head = as_int4(r[0]), mode = as_int4(r[3]);
    float3 h = (float3)(uv, 1.0f);
    float u = dot(r[1].xyz, h), v = dot(r[2].xyz, h);
    if (head.x == TEX_CHECKERBOARD) return texel(g->tex_texels, head, 3, (floor_int(u) + floor_int(v)) & 1, 0);
    int w = head.z, ht = head.w;
    if (mode.y) return texel(g->tex_texels, head, mode.z, wrap_index(floor_int(u * w), w, mode.x),
                             wrap_index(floor_int(v * ht), ht, mode.x));
    float x = u * w - 0.5f, y = v * ht - 0.5f;
    int x0 = floor_int(x), y0 = floor_int(y);
    float fx = x - floor(x), fy = y - floor(y);
    int xa = wrap_index(x0, w, mode.x), xb = wrap_index(x0 + 1, w, mode.x);
    int ya = wrap_index(y0, ht, mode.x), yb = wrap_index(y0 + 1, ht, mode.x);
    float3 top = mix(texel(g->tex_texels, head, mode.z, xa, ya), texel(g->tex_texels, head, mode.z, xb, ya), fx);
    float3 bottom = mix(texel(g->tex_texels, head, mode.z, xa, yb), texel(g->tex_texels, head, mode.z, xb, yb), fx);
    return mix(top, bottom, fy);
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
    if (t.z >= 0) {
        float3 a = texture_eval(g, t.z, uv);
        m.rough = clamp((a.x + a.y + a.z) / 3.0f, 0.001f, 1.0f);  // Roughness's range (worker/scene.py)
    }
    return m;
}

inline Material hit_material(const SceneGeom* g, __global const float4* surfaces, const Hit* h, float3 p) {
    return surface_material(g, surfaces, h->surf, hit_prim(h), p);
}
