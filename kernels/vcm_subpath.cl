// A subpath of the hybrid integrator (light or camera side) as it walks: its ray, its
// throughput and VCM's recursive MIS quantities (Georgiev 2012 tech report, sec. 4):
//   at a hit, to the area measure there: dVCM *= d^2 (not on the first hit from a
//   directional light), then dVCM, dVC, dVM /= |cos| of the arrival;
//   through a specular bounce: dVCM = 0, dVC *= cos, dVM *= cos (delta pdfs cancel);
//   through any other, with the bounce's forward and reverse solid-angle pdfs:
//       dVC  = cos / p_fwd (dVC p_rev + dVCM + eta_vm)
//       dVM  = cos / p_fwd (dVM p_rev + dVCM eta_vc + 1)
//       dVCM = 1 / p_fwd
// with eta_vm = eta_vcm = pi r^2 N_L where merging is on (else 0) and eta_vc = 1 / eta_vcm
// where connecting is on (else 0). Paths end by Russian roulette on the bounce's largest
// throughput factor (photon_pass.cl).

typedef struct {
    float3 o, d;     // the ray
    float3 thr;      // throughput
    float dVCM, dVC, dVM;
} SubPath;

typedef struct { float vm, vc; } MisEtas;  // eta_vm and eta_vc above

inline MisEtas mis_etas(int connect, int merge, float eta_vcm) {
    MisEtas e = {merge ? eta_vcm : 0.0f, connect ? 1.0f / eta_vcm : 0.0f};
    return e;
}

// `dist`: from the previous vertex to the hit (0: no distance factor). It differs from the
// ray's length only on a camera ray started at the near-clip plane.
inline void subpath_arrive(SubPath* s, const Hit* h, float dist) {
    float cos_in = fabs(dot(s->d, h->ng));
    if (dist > 0.0f) s->dVCM *= dist * dist;
    s->dVCM /= cos_in;
    s->dVC /= cos_in;
    s->dVM /= cos_in;
}

// Sample the bounce at hit point p through the BSDF parts `parts` (bsdf.cl) and continue;
// false if the path ends. `light`: the adjoint shading-normal factor of light paths
// (materials.cl, shading_bounce).
inline bool subpath_bounce(const SceneGeom* g, SubPath* s, const Hit* h, float3 p, const Material* m, int parts,
                           bool light, MisEtas eta, Rng* rng) {
    BsdfSample b;
    if (!bsdf_sample(m, h->ng, h->ns, s->d, parts, !light, rng, &b)) return false;
    float3 w = b.weight;
    if (h->smooth) w *= shading_bounce(s->d, b.dir, h->ng, h->ns, light);
    float survive = fmin(1.0f, fmax(w.x, fmax(w.y, w.z)) / b.scale);
    if (rng_float(rng) >= survive) return false;
    s->thr *= w / survive;
    float cos_out = fabs(dot(b.dir, h->ng));
    if (b.delta) {
        s->dVCM = 0.0f;
        s->dVC *= cos_out;
        s->dVM *= cos_out;
    } else {
        s->dVC = cos_out / b.pdf_fwd * (s->dVC * b.pdf_rev + s->dVCM + eta.vm);
        s->dVM = cos_out / b.pdf_fwd * (s->dVM * b.pdf_rev + s->dVCM * eta.vc + 1.0f);
        s->dVCM = 1.0f / b.pdf_fwd;
    }
    s->d = b.dir;
    s->o = p + (dot(b.dir, h->ng) > 0.0f ? h->ng : -h->ng) * ray_eps(g, p);
    return true;
}
