// BSDFs of every material (materials.cl): value, pdfs and sampling, shared by the photon
// passes, the eye pass and the hybrid integrator, so that the pdfs VCM's weights use are
// those its paths were sampled with.
//
// Directions: wo points back along the path that reached the surface, wi the other way;
// both leave the surface. f excludes the cosine; pdfs are per solid angle. Reflection
// lobes turn about the shading normal on wo's geometric side (n); both directions must
// lie on one geometric side for reflection, on opposite sides for transmission.
//
// A BSDF is a sum of parts (PART_*), and a path takes one part, chosen with probability
// part_choice(wo):
//   PART_DIFFUSE  the separable base f_d = g(wo) h(wi) / pi: diffuse g = rho, h = 1;
//                 plastic g = rho (1 - F(wo)) / (eta^2 (1 - R_int)), h = 1 - F(wi), with
//                 R_int the internal diffuse reflectance of the coat (rho R_int in place of
//                 R_int when `nonlinear`); rough_plastic the same with the coat's
//                 transmittance T in place of 1 - F (Mitsuba 3's plastic and roughplastic).
//                 SPPM measures it by photon density: a photon stored on the surface
//                 carries h(wi), the measurement point g(wo) (photon_pass.cl, eye_pass.cl).
//   PART_GLOSSY   a non-delta lobe: the modified Phong lobe (glossy), the microfacet
//                 lobes f = R D G / (4 cos_o cos_i) of rough_conductor (R its Fresnel term)
//                 and rough_plastic's coat (R = specular F(wo.h)), sampled by D(h) cos_h
//                 with pdf D cos_h / (4 wo.h) (Walter et al. 2007).
//                 rough_glass: reflection as rough_plastic's coat (tinted by its albedo),
//                 and refraction through microfacet h (Walter et al. 2007, eq. 21; pbrt-v4's
//                 rough dielectric) f = T (1 - F) D G |wi.h| |wo.h| / (|cos_i| cos_o
//                 (wi.h + wo.h / eta)^2), eta = n(wi's side) / n(wo's side), h the
//                 generalised half vector wo + eta wi; the choice between them is F(wo.h).
//   PART_DELTA    mirror reflection (conductor, plastic's coat) and a smooth dielectric's
//                 reflection and refraction (glass, thin_glass); and the null part of a
//                 masked surface (Mitsuba 3's mask of opacity a): f = a f_lobes + (1 - a)
//                 delta(wi = -wo) / |cos|, the null part taken with probability 1 - a and
//                 passing the path straight on with weight 1, as if the surface were not there.
// Refraction in `radiance` mode (camera and eye paths) divides f by eta^2, the radiance a
// ray gains entering a denser medium; photons and light subpaths carry flux (importance
// mode) and do not. Every path that starts and ends outside an object crosses its surface in
// and out in pairs, whose factors cancel; a path that ends on a surface inside it keeps one.
// Plastics choose between coat and base as Mitsuba 3 does: P_coat proportional to
// w F(wo) (rough: w (1 - T(wo))), P_base to (1 - w)(1 - F(wo)) (rough: (1 - w) T(wo)), w the
// specular sampling weight. A caller may restrict the parts (`mask`): probabilities are
// then renormalised over the parts it allows.

#define PART_DIFFUSE 1
#define PART_GLOSSY 2
#define PART_DELTA 4
#define PART_ALL 7

typedef struct {
    float3 f;       // BSDF value over the allowed non-delta parts, no cosine (0: not scattered)
    float pdf_fwd;  // pdf of sampling wi given wo
    float pdf_rev;  // pdf of sampling wo given wi
} BsdfEval;

typedef struct {
    float3 dir;     // the new direction (leaving the surface)
    float3 weight;  // f cos / pdf, the choice of part included
    float scale;    // the radiance factor 1 / eta^2 of a refraction in `radiance` mode within weight, else 1:
                    // not an absorption, so Russian roulette leaves it out
    float pdf_fwd, pdf_rev;
    bool delta;     // a delta part: pdfs undefined, weights use the delta rules
} BsdfSample;

// The parts of a material's own lobes (the null part aside).
inline int lobe_parts(const Material* m) {
    switch (m->type) {
        case MAT_DIFFUSE: return PART_DIFFUSE;
        case MAT_GLOSSY:
        case MAT_ROUGH_CONDUCTOR:
        case MAT_ROUGH_GLASS: return PART_GLOSSY;
        case MAT_PLASTIC: return PART_DIFFUSE | PART_DELTA;
        case MAT_ROUGH_PLASTIC: return PART_DIFFUSE | PART_GLOSSY;
        default: return PART_DELTA;
    }
}

// The parts a material has.
inline int material_parts(const Material* m) { return lobe_parts(m) | ((m->flags & MF_MASKED) ? PART_DELTA : 0); }

inline bool is_delta(const Material* m) { return material_parts(m) == PART_DELTA; }

// The probability of the null part among the parts in `mask`: 1 - opacity, or 1 where the
// mask allows none of the lobes.
inline float null_choice(const Material* m, int mask) {
    if (!(m->flags & MF_MASKED) || !(mask & PART_DELTA)) return 0.0f;
    return (lobe_parts(m) & mask) ? 1.0f - m->opacity : 1.0f;
}

// The coat's share of what arrives at cos (1 - F for plastic, T for rough_plastic): h above.
inline float coat_in(const Material* m, float c) {
    if (m->type == MAT_DIFFUSE) return 1.0f;
    if (m->type == MAT_ROUGH_PLASTIC) return coat_transmittance(m, c);
    float ct;
    return 1.0f - fresnel_dielectric(clamp(c, 0.0f, 1.0f), m->eta.x, &ct);
}

// g(wo) of the diffuse part (above), at cos_o about n; the opacity included.
inline float3 diffuse_out(const Material* m, float co) {
    if (m->type == MAT_DIFFUSE) return m->opacity * m->base;
    float3 inner = (m->flags & MF_NONLINEAR) ? m->base * m->eta.y : (float3)(m->eta.y);
    return m->base / (1.0f - inner) * (m->opacity * coat_in(m, co) / (m->eta.x * m->eta.x));
}

inline float3 part_on(int parts) {
    return (float3)((parts & PART_DIFFUSE) ? 1.0f : 0.0f, (parts & PART_GLOSSY) ? 1.0f : 0.0f,
                    (parts & PART_DELTA) ? 1.0f : 0.0f);
}

// The probability of each of the lobes' parts for a path arriving from cos_o, over the parts
// in `mask` (diffuse, glossy, delta); all 0 if the mask allows none the lobes have.
inline float3 lobe_choice(const Material* m, float co, int mask) {
    float3 p = (float3)(1.0f);
    if (m->type == MAT_PLASTIC || m->type == MAT_ROUGH_PLASTIC) {
        float base = coat_in(m, co), w = m->eta.z;
        p = (float3)(base * (1.0f - w), (1.0f - base) * w, (1.0f - base) * w);
    }
    p *= part_on(lobe_parts(m) & mask);
    float sum = p.x + p.y + p.z;
    return sum > 0.0f ? p / sum : (float3)(0.0f);
}

// The same over all the material's parts: the null part's share is delta's.
inline float3 part_choice(const Material* m, float co, int mask) {
    float pn = null_choice(m, mask);
    return lobe_choice(m, co, mask) * (1.0f - pn) + (float3)(0.0f, 0.0f, pn);
}

// The glossy part's value and its pdf of wi given wo (n about which both have positive
// cosines co, ci).
inline float3 glossy_eval(const Material* m, float3 n, float3 wo, float3 wi, float co, float ci, float* pdf) {
    *pdf = 0.0f;
    if (m->type == MAT_GLOSSY) {  // modified Phong about the mirror direction
        float ca = dot(wi, reflect_dir(-wo, n));
        if (ca <= 0.0f) return (float3)(0.0f);
        float lobe = pow(ca, m->rough) / (2.0f * PI_F);
        *pdf = (m->rough + 1.0f) * lobe;
        return m->base * ((m->rough + 2.0f) * lobe);
    }
    float3 hv = normalize(wo + wi);
    float ch = dot(hv, n), oh = dot(wo, hv);
    bool beckmann = (m->flags & MF_BECKMANN) != 0;
    float d = mf_d(ch, m->rough, beckmann);
    if (d <= 0.0f || oh <= 0.0f) return (float3)(0.0f);
    *pdf = d * ch / (4.0f * oh);
    float gm = mf_g1(co, oh, m->rough, beckmann) * mf_g1(ci, oh, m->rough, beckmann);
    float3 r;
    if (m->type == MAT_ROUGH_CONDUCTOR) {
        r = conductor_reflectance(m, oh);
    } else {
        float ct;
        r = m->second * fresnel_dielectric(oh, m->eta.x, &ct);
    }
    return r * (d * gm / (4.0f * co * ci));
}

// A dielectric's relative index n(far side) / n(this side) for a direction leaving the side
// where its cosine to ng is g: ior from outside, 1 / ior from inside.
inline float dielectric_eta(const Material* m, float g) { return g > 0.0f ? m->eta.x : 1.0f / m->eta.x; }

// rough_glass: f and both pdfs for wo and wi on either side (go, gi: their cosines to ng).
inline BsdfEval rough_glass_eval(const Material* m, float3 ng, float3 ns, float3 wo, float3 wi, float go, float gi,
                                 bool radiance) {
    BsdfEval e = {(float3)(0.0f), 0.0f, 0.0f};
    float3 n = go > 0.0f ? ns : -ns;
    float co = dot(wo, n), ci = dot(wi, n);
    bool reflect = go * gi > 0.0f;
    if (co <= 0.0f || (reflect ? ci <= 0.0f : ci >= 0.0f)) return e;
    float across = dielectric_eta(m, go);      // n(the other side) / n(wo's side)
    float eta = reflect ? 1.0f : across;      // n(wi's side) / n(wo's side)
    float3 hv = normalize(reflect ? wo + wi : wo + eta * wi);
    if (dot(hv, n) < 0.0f) hv = -hv;
    float oh = dot(wo, hv), ih = dot(wi, hv), ch = dot(hv, n);
    if (oh <= 0.0f || ih * ci <= 0.0f) return e;  // a microfacet seen from its back
    bool beckmann = (m->flags & MF_BECKMANN) != 0;
    float d = mf_d(ch, m->rough, beckmann);
    float gm = mf_g1(co, oh, m->rough, beckmann) * mf_g1(ci, ih, m->rough, beckmann);
    float ct;
    float fr = fresnel_dielectric(oh, across, &ct);
    if (reflect) {
        e.f = m->base * (fr * d * gm / (4.0f * co * ci));
        e.pdf_fwd = e.pdf_rev = fr * d * ch / (4.0f * oh);
        return e;
    }
    float denom = (ih + oh / eta) * (ih + oh / eta);
    float value = (1.0f - fr) * d * gm * fabs(ih) * oh / (denom * fabs(ci) * co);
    e.f = m->second * (radiance ? value / (eta * eta) : value);
    e.pdf_fwd = (1.0f - fr) * d * ch * fabs(ih) / denom;
    e.pdf_rev = (1.0f - fr) * d * ch * oh / (eta * eta * denom);  // the same from wi's side, 1 / eta
    return e;
}

inline BsdfEval bsdf_eval(const Material* m, float3 ng, float3 ns, float3 wo, float3 wi, int mask, bool radiance) {
    BsdfEval e = {(float3)(0.0f), 0.0f, 0.0f};
    if (m->type == MAT_ROUGH_GLASS) {
        float go = dot(wo, ng), gi = dot(wi, ng);
        if (!(mask & PART_GLOSSY) || go * gi == 0.0f) return e;
        e = rough_glass_eval(m, ng, ns, wo, wi, go, gi, radiance);
        float keep = 1.0f - null_choice(m, mask);
        e.f *= m->opacity;
        e.pdf_fwd *= keep;
        e.pdf_rev *= keep;
        return e;
    }
    int parts = material_parts(m) & mask & (PART_DIFFUSE | PART_GLOSSY);
    float go = dot(wo, ng), gi = dot(wi, ng);
    if (go * gi <= 0.0f || parts == 0) return e;  // reflection only, both on one side of the true surface
    float3 n = go > 0.0f ? ns : -ns;
    float co = dot(wo, n), ci = dot(wi, n);
    if (co <= 0.0f || ci <= 0.0f) return e;
    float3 fwd = part_choice(m, co, mask), rev = part_choice(m, ci, mask);
    if (parts & PART_DIFFUSE) {
        e.f = diffuse_out(m, co) * (coat_in(m, ci) / PI_F);
        e.pdf_fwd = fwd.x * ci / PI_F;
        e.pdf_rev = rev.x * co / PI_F;
    }
    if (parts & PART_GLOSSY) {
        float pdf;
        e.f += m->opacity * glossy_eval(m, n, wo, wi, co, ci, &pdf);  // both lobes have pdf(wo | wi) = pdf(wi | wo)
        e.pdf_fwd += fwd.y * pdf;
        e.pdf_rev += rev.y * pdf;
    }
    return e;
}

// A delta part's bounce of a path arriving along d at a surface whose normal n faces it.
inline bool delta_sample(const Material* m, float3 d, float3 n, float3 ng, float co, bool radiance, Rng* rng,
                         float3* nd, float3* weight, float* scale) {
    *scale = 1.0f;
    if (m->type == MAT_CONDUCTOR) {
        *nd = reflect_dir(d, n);
        *weight = conductor_reflectance(m, co);
        return true;
    }
    float ct;
    if (m->type == MAT_PLASTIC) {
        *nd = reflect_dir(d, n);
        *weight = m->second * fresnel_dielectric(co, m->eta.x, &ct);
        return true;
    }
    float eta = m->type == MAT_THIN_GLASS ? m->eta.x : dielectric_eta(m, -dot(d, ng));
    float r = fresnel_dielectric(co, eta, &ct);
    if (m->type == MAT_THIN_GLASS && r < 1.0f) r += (1.0f - r) * (1.0f - r) * r / (1.0f - r * r);
    // Russian roulette between reflection and refraction with the reflectance: the branch
    // weight R/R = T/T = 1 but for the tints.
    if (r >= 1.0f || rng_float(rng) < r) {
        *nd = reflect_dir(d, n);
        *weight = m->base;
    } else {
        *nd = m->type == MAT_THIN_GLASS ? d : normalize(d / eta + (co / eta - ct) * n);
        if (radiance && m->type == MAT_GLASS) *scale = 1.0f / (eta * eta);
        *weight = m->second * *scale;
    }
    return true;
}

// A bounce of a path arriving along d (propagation direction), taking a part among those
// in `mask`; false if the path ends (absorbed, or sampled through the surface).
inline bool bsdf_sample(const Material* m, float3 ng, float3 ns, float3 d, int mask, bool radiance, Rng* rng,
                        BsdfSample* s) {
    float3 wo = -d, n = dot(wo, ng) > 0.0f ? ns : -ns;
    float co = dot(wo, n);
    // The null part: on along d.
    float pn = null_choice(m, mask);
    if (pn > 0.0f && (pn >= 1.0f || rng_float(rng) < pn)) {
        s->dir = d;
        s->weight = (float3)((1.0f - m->opacity) / pn);
        s->scale = s->pdf_fwd = s->pdf_rev = 1.0f;
        s->delta = true;
        return true;
    }
    if (m->type == MAT_DIFFUSE && !(m->flags & MF_MASKED) && (mask & PART_DIFFUSE)) {  // the common case, in closed form: f cos / pdf = rho
        s->dir = sample_cosine(n, rng_float(rng), rng_float(rng));
        float ci = dot(s->dir, n);
        s->delta = false;
        s->weight = m->base;
        s->scale = 1.0f;
        s->pdf_fwd = ci / PI_F;
        s->pdf_rev = co / PI_F;
        return co > 0.0f && ci > 0.0f && dot(s->dir, ng) * dot(wo, ng) > 0.0f;
    }
    float3 p = lobe_choice(m, fmax(co, 0.0f), mask);
    // Choose the part (a random number only where there is a choice).
    int part = p.x > 0.0f ? PART_DIFFUSE : p.y > 0.0f ? PART_GLOSSY : PART_DELTA;
    if (p.x + p.y + p.z == 0.0f) return false;
    if (p.x < 1.0f && p.y < 1.0f && p.z < 1.0f) {
        float u = rng_float(rng);
        part = u < p.x ? PART_DIFFUSE : u < p.x + p.y ? PART_GLOSSY : PART_DELTA;
    }
    s->delta = part == PART_DELTA;
    s->pdf_fwd = s->pdf_rev = 1.0f;
    if (s->delta) {
        if (!delta_sample(m, d, n, ng, co, radiance, rng, &s->dir, &s->weight, &s->scale)) return false;
        s->weight *= m->opacity / ((1.0f - pn) * p.z);
        return true;
    }
    if (part == PART_DIFFUSE) {
        s->dir = sample_cosine(n, rng_float(rng), rng_float(rng));
    } else if (m->type == MAT_GLOSSY) {
        float e = m->rough;
        float cos_a = pow(rng_float(rng), 1.0f / (e + 1.0f));
        float sin_a = sqrt(fmax(0.0f, 1.0f - cos_a * cos_a));
        float phi = 2.0f * PI_F * rng_float(rng);
        s->dir = from_local(reflect_dir(d, n), sin_a * cos(phi), sin_a * sin(phi), cos_a);
    } else {
        float3 hv = mf_sample(n, m->rough, (m->flags & MF_BECKMANN) != 0, rng_float(rng), rng_float(rng));
        s->dir = reflect_dir(d, hv);
        if (m->type == MAT_ROUGH_GLASS) {  // reflect with F(wo.h), else refract through h
            float oh = dot(wo, hv), ct;
            if (oh <= 0.0f) return false;
            float eta = dielectric_eta(m, dot(wo, ng));
            float fr = fresnel_dielectric(oh, eta, &ct);
            bool refract = rng_float(rng) >= fr;
            if (refract) s->dir = normalize(d / eta + (oh / eta - ct) * hv);
            // A steep microfacet can send either branch to the wrong side of the surface: lost.
            if ((dot(s->dir, ng) * dot(wo, ng) < 0.0f) != refract) return false;
        }
    }
    BsdfEval e = bsdf_eval(m, ng, ns, wo, s->dir, mask, radiance);
    if (e.pdf_fwd <= 0.0f) return false;
    s->weight = e.f * (fabs(dot(s->dir, ns)) / e.pdf_fwd);
    s->scale = 1.0f;
    if (radiance && m->type == MAT_ROUGH_GLASS && dot(s->dir, ng) * dot(wo, ng) < 0.0f) {  // refracted
        float eta = dielectric_eta(m, dot(wo, ng));
        s->scale = 1.0f / (eta * eta);
    }
    s->pdf_fwd = e.pdf_fwd;
    s->pdf_rev = e.pdf_rev;
    return true;
}
