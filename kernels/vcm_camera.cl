// The camera of the hybrid integrator, pinhole or thin lens, both ways: a camera ray through
// a jittered point of a pixel (as eye_pass.cl), and the projection of a light vertex onto the
// image with the camera's importance (light tracing).
//
// Camera rows (worker/scene_arrays.py): (position, near clip), (unit view axis, lens
// radius), (right * tan(fov_x/2), focus), (up * tan(fov/2)). The image plane at unit
// distance along the axis spans A_img = 4 |right| |up|, a pixel A_pix = A_img / (w h). A
// uniform point of a pixel gives the direction at angle theta to the axis the solid-angle
// pdf 1 / (A_pix cos^3 theta), which is also the importance of that pixel's measurement
// per unit solid angle. A point y seen at distance d with surface cosine cos_y then has
// the area pdf 1 / (A_pix cos^3 theta) cos_y / d^2 of being hit by that pixel's camera ray.
//
// A thin lens (radius > 0) starts the ray at a uniform point of the lens disc and aims it
// at the pixel's point on the plane of focus. The pixel spans A_pix f^2 of that plane, f
// the focus distance, so the direction's pdf from the lens point is again
// 1 / (A_pix cos^3 theta), theta the ray's own angle to the axis; the lens point's pdf
// 1 / (pi r^2) is the same for a camera path and for light tracing, which samples the lens
// the same way, and leaves the MIS ratios (pbrt-v4's PerspectiveCamera: We and its pdfs).

typedef struct {
    float3 pos, fwd, right, up;
    float near, pixel_area, lens, focus;
    int width, height;
} Pinhole;

// A uniform point of the lens disc (the camera's position for a pinhole).
inline float3 lens_point(const Pinhole* c, Rng* rng) {
    if (c->lens <= 0.0f) return c->pos;
    float r = c->lens * sqrt(rng_float(rng)), phi = 2.0f * PI_F * rng_float(rng);
    return c->pos + r * cos(phi) * normalize(c->right) + r * sin(phi) * normalize(c->up);
}

typedef struct {
    int pixel;         // index of the pixel the point projects to
    float3 to_camera;  // unit direction from the point to the camera
    float dist;        // to the camera
    float visible;     // shadow-ray length: up to the near-clip plane
    float importance;  // 1 / (A_pix cos^3 theta): pdf of the pixel's ray direction
} Projection;

inline Pinhole pinhole(__global const float4* cam, int width, int height) {
    Pinhole c;
    c.pos = cam[0].xyz;
    c.near = cam[0].w;
    c.fwd = cam[1].xyz;
    c.right = cam[2].xyz;
    c.up = cam[3].xyz;
    c.lens = cam[1].w;
    c.focus = cam[2].w;
    c.width = width;
    c.height = height;
    c.pixel_area = 4.0f * length(c.right) * length(c.up) / ((float)width * (float)height);
    return c;
}

// A jittered ray through pixel `gid`: origin on the near-clip plane (`skipped` from the
// lens), unit direction, and the solid-angle pdf of the direction (the importance above).
inline float camera_ray(const Pinhole* c, int gid, Rng* rng, float3* o, float3* d, float* skipped) {
    int x = gid % c->width, y = gid / c->width;
    float sx = 2.0f * ((float)x + rng_float(rng)) / (float)c->width - 1.0f;
    float sy = 1.0f - 2.0f * ((float)y + rng_float(rng)) / (float)c->height;
    float3 dir = c->fwd + sx * c->right + sy * c->up;  // unit length along the axis
    float3 lens = lens_point(c, rng);
    if (c->lens > 0.0f) dir = (c->pos + c->focus * dir - lens) / c->focus;  // to the focus point, still unit along the axis
    *o = lens + c->near * dir;
    *d = normalize(dir);
    *skipped = c->near * length(dir);
    float cos_t = dot(*d, c->fwd);
    return 1.0f / (c->pixel_area * cos_t * cos_t * cos_t);
}

// Where point p lands on the image, seen from a uniform point of the lens; false if behind
// the camera, outside the image or nearer than the near-clip plane.
inline bool project(const Pinhole* c, float3 p, Rng* rng, Projection* out) {
    float3 lens = lens_point(c, rng);
    float3 v = lens - p;
    out->dist = length(v);
    out->to_camera = v / out->dist;
    float cos_t = -dot(out->to_camera, c->fwd);
    if (cos_t <= 0.0f || out->dist * cos_t <= c->near) return false;
    float3 q = -out->to_camera / cos_t;  // the ray's point on the plane at unit distance from the lens
    if (c->lens > 0.0f) q = (lens - c->pos) / c->focus + q;  // where it meets the plane of focus, over f
    float sx = dot(q, c->right) / dot(c->right, c->right), sy = dot(q, c->up) / dot(c->up, c->up);
    int x = (int)floor((sx + 1.0f) * 0.5f * (float)c->width), y = (int)floor((1.0f - sy) * 0.5f * (float)c->height);
    if (x < 0 || x >= c->width || y < 0 || y >= c->height) return false;
    out->pixel = y * c->width + x;
    out->visible = out->dist - c->near / cos_t;
    out->importance = 1.0f / (c->pixel_area * cos_t * cos_t * cos_t);
    return true;
}
