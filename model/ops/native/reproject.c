/* The fused step's reprojection at 1x in one pass per row: the bicubic, bilinear and nearest backward warps of
 * model.ops.warp (border padding) and the geometry test of model.ops.reproject, with grid_sample's arithmetic
 * (align_corners=False, cubic convolution A = -0.75). Planes are single-image (H, W) float32 arrays. Each row first
 * computes every pixel's taps and weights into row buffers (simple loops over x in functions of their own, restrict
 * arguments, which the compiler vectorizes), then reads the images interleaved, one vector load a tap. */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#include "scratch.h"

#define CUBIC_A (-0.75f)
#define NOINLINE __attribute__((noinline))

static inline float clampf(float v, float lo, float hi) { return v < lo ? lo : (v > hi ? hi : v); }

/* grid_sample's unnormalisation of the grid model.ops.warp builds from a position p: g = (2p - S) / S, then
 * (g + 1) * (S / 2) - 0.5 */
static inline float source_coordinate(float p, float size) {
    float g = (2.0f * p - size) / size;
    return (g + 1.0f) * (size * 0.5f) - 0.5f;
}

static inline float cubic_near(float d) { return ((CUBIC_A + 2.0f) * d - (CUBIC_A + 3.0f)) * d * d + 1.0f; }
static inline float cubic_far(float d) {
    return ((CUBIC_A * d - 5.0f * CUBIC_A) * d + 8.0f * CUBIC_A) * d - 4.0f * CUBIC_A;
}

/* positions centre + motion of one row */
static NOINLINE void positions(int64_t w, float y, const float *restrict mx, const float *restrict my,
                               float *restrict px, float *restrict py) {
    for (int64_t x = 0; x < w; x++) {
        px[x] = ((float)x + 0.5f) + mx[x];
        py[x] = (y + 0.5f) + my[x];
    }
}

/* along one axis: the 4 cubic weights and the 4 clamped tap indices (times stride) of each position */
static NOINLINE void cubic_axis(int64_t w, const float *restrict p, float size, int32_t stride,
                                float *restrict k0, float *restrict k1, float *restrict k2, float *restrict k3,
                                int32_t *restrict i0, int32_t *restrict i1, int32_t *restrict i2,
                                int32_t *restrict i3) {
    for (int64_t x = 0; x < w; x++) {
        const float ix = source_coordinate(p[x], size), f = floorf(ix), t = ix - f;
        k0[x] = cubic_far(t + 1.0f);
        k1[x] = cubic_near(t);
        k2[x] = cubic_near(1.0f - t);
        k3[x] = cubic_far(2.0f - t);
        i0[x] = (int32_t)clampf(f - 1.0f, 0.0f, size - 1.0f) * stride;
        i1[x] = (int32_t)clampf(f, 0.0f, size - 1.0f) * stride;
        i2[x] = (int32_t)clampf(f + 1.0f, 0.0f, size - 1.0f) * stride;
        i3[x] = (int32_t)clampf(f + 2.0f, 0.0f, size - 1.0f) * stride;
    }
}

/* along one axis: the bilinear position clamped to the border, its fraction and its two taps (times stride); a far
 * tap past the edge has weight 0 and reads the near one */
static NOINLINE void linear_axis(int64_t w, const float *restrict p, float size, int32_t stride,
                                 float *restrict frac, int32_t *restrict i0, int32_t *restrict i1) {
    for (int64_t x = 0; x < w; x++) {
        const float l = clampf(source_coordinate(p[x], size), 0.0f, size - 1.0f), f = floorf(l);
        frac[x] = l - f;
        i0[x] = (int32_t)f * stride;
        i1[x] = (int32_t)(f + 1.0f < size ? f + 1.0f : f) * stride;
    }
}

/* the pixel whose footprint holds each position, clamped to the image */
static NOINLINE void nearest_index(int64_t w, const float *restrict px, const float *restrict py, float jx, float jy,
                                   float fw, float fh, int32_t iw, int32_t *restrict index) {
    for (int64_t x = 0; x < w; x++)
        index[x] = (int32_t)clampf(floorf(py[x] + jy), 0.0f, fh - 1.0f) * iw
                 + (int32_t)clampf(floorf(px[x] + jx), 0.0f, fw - 1.0f);
}

static NOINLINE void gather_row(int64_t w, const float *restrict src, const int32_t *restrict index,
                                float *restrict dst) {
    for (int64_t x = 0; x < w; x++) dst[x] = src[index[x]];
}

static NOINLINE void geometry_row(int64_t w, int64_t plane, const float *restrict px, const float *restrict py,
                                  float jx, float jy, float fw, float fh, const int32_t *restrict j,
                                  const float *restrict d, const float *restrict n0, const float *restrict n1,
                                  const float *restrict n2, const float *restrict pd, const float *restrict pn,
                                  float dtol, float ctol, uint8_t *restrict out) {
    for (int64_t x = 0; x < w; x++) {
        const float qx = px[x] + jx, qy = py[x] + jy;
        const int in_prev = (qx >= 0.0f) & (qx < fw) & (qy >= 0.0f) & (qy < fh);
        const float p = pd[j[x]], p0 = pn[j[x]], p1 = pn[plane + j[x]], p2 = pn[2 * plane + j[x]];
        const float lengths = sqrtf((n0[x] * n0[x] + n1[x] * n1[x] + n2[x] * n2[x]) * (p0 * p0 + p1 * p1 + p2 * p2));
        const float cosine = (n0[x] * p0 + n1[x] * p1 + n2[x] * p2) / (lengths > 1e-12f ? lengths : 1e-12f);
        out[x] = (uint8_t)(in_prev & (d[x] > 0.0f) & (p > 0.0f) & (fabsf(d[x] - p) <= dtol * d[x]) & (cosine >= ctol));
    }
}

/* Channels read together are first interleaved, CUBIC_STRIDE / LINEAR_STRIDE floats per pixel (the rest 0), so a tap
 * reads all of a pixel's channels with one vector load instead of one gather per channel. */
#define CUBIC_STRIDE 8
#define LINEAR_STRIDE 16

static NOINLINE void interleave_row(int64_t w, const float **src, int64_t n, int64_t offset, int64_t stride,
                                    float *restrict dst) {
    for (int64_t c = 0; c < stride; c++) {
        const float *restrict in = c < n ? src[c] + offset : NULL;
        for (int64_t x = 0; x < w; x++) dst[x * stride + c] = in ? in[x] : 0.0f;
    }
}

/* whole pixels as vectors (GCC's vector extensions; unaligned loads) */
typedef float v8 __attribute__((vector_size(CUBIC_STRIDE * sizeof(float)), aligned(4)));
typedef float v16 __attribute__((vector_size(LINEAR_STRIDE * sizeof(float)), aligned(4)));

/* one row of the cubic read from interleaved pixels, each channel summed in grid_sample's order */
static NOINLINE void cubic_row_interleaved(int64_t w, const float *restrict src, const int32_t *const rows[4],
                                           const int32_t *const cols[4], const float *const kx[4],
                                           const float *const ky[4], float low, float high, float *restrict out) {
    for (int64_t x = 0; x < w; x++) {
        const float a = kx[0][x], b = kx[1][x], c = kx[2][x], d = kx[3][x];
        v8 acc;
        for (int r = 0; r < 4; r++) {
            const float *row = src + (int64_t)rows[r][x] * CUBIC_STRIDE;
            const v8 t = ((*(const v8 *)(row + (int64_t)cols[0][x] * CUBIC_STRIDE) * a
                           + *(const v8 *)(row + (int64_t)cols[1][x] * CUBIC_STRIDE) * b)
                          + *(const v8 *)(row + (int64_t)cols[2][x] * CUBIC_STRIDE) * c)
                         + *(const v8 *)(row + (int64_t)cols[3][x] * CUBIC_STRIDE) * d;
            acc = r == 0 ? t * ky[0][x] : acc + t * ky[r][x];
        }
        float *o = out + x * CUBIC_STRIDE;
        *(v8 *)o = acc;
        for (int k = 0; k < CUBIC_STRIDE; k++) o[k] = clampf(o[k], low, high);
    }
}

/* one row of the bilinear read from interleaved pixels */
static NOINLINE void linear_row_interleaved(int64_t w, const float *restrict src, const int32_t *restrict r0,
                                            const int32_t *restrict r1, const int32_t *restrict c0,
                                            const int32_t *restrict c1, const float *restrict ux,
                                            const float *restrict uy, float *restrict out) {
    for (int64_t x = 0; x < w; x++) {
        const float tx = ux[x], ty = uy[x], ex = 1.0f - tx, ey = 1.0f - ty;
        const v16 p0 = *(const v16 *)(src + (int64_t)(r0[x] + c0[x]) * LINEAR_STRIDE);
        const v16 p1 = *(const v16 *)(src + (int64_t)(r0[x] + c1[x]) * LINEAR_STRIDE);
        const v16 p2 = *(const v16 *)(src + (int64_t)(r1[x] + c0[x]) * LINEAR_STRIDE);
        const v16 p3 = *(const v16 *)(src + (int64_t)(r1[x] + c1[x]) * LINEAR_STRIDE);
        *(v16 *)(out + x * LINEAR_STRIDE) = ((p0 * (ey * ex) + p1 * (ey * tx)) + p2 * (ty * ex)) + p3 * (ty * tx);
    }
}

/* a row of interleaved pixels back into one plane per channel */
static NOINLINE void deinterleave_row(int64_t w, const float *restrict src, int64_t n, int64_t stride, float **dst,
                                      int64_t base) {
    for (int64_t k = 0; k < n; k++) {
        float *restrict out = dst[k] + base;
        const float *restrict in = src + k;
        if (stride == CUBIC_STRIDE)
            for (int64_t x = 0; x < w; x++) out[x] = in[x * CUBIC_STRIDE];
        else
            for (int64_t x = 0; x < w; x++) out[x] = in[x * LINEAR_STRIDE];
    }
}

int reproject_x1(int64_t h, int64_t w, const float *motion,
                  const float **cubic_src, float **cubic_dst, int64_t n_cubic, double cubic_low, double cubic_high,
                  const float **linear_src, float **linear_dst, int64_t n_linear,
                  const float **nearest_src, float **nearest_dst, int64_t n_nearest,
                  const float *depth, const float *normal, const float *prev_depth, const float *prev_normal,
                  double jitter_x, double jitter_y, double depth_tol, double cos_tol, uint8_t *valid,
                  float *scratch, int64_t threads) {
    const int64_t plane = h * w;
    const float fw = (float)w, fh = (float)h, low = (float)cubic_low, high = (float)cubic_high;
    const float jx = (float)jitter_x, jy = (float)jitter_y, dtol = (float)depth_tol, ctol = (float)cos_tol;
    const int32_t iw = (int32_t)w;
    /* interleaved copies of the images, in scratch (h * w * (CUBIC_STRIDE + LINEAR_STRIDE) floats); the caller
     * passes at most CUBIC_STRIDE and LINEAR_STRIDE channels */
    float *cubic_pixels = scratch, *linear_pixels = scratch + plane * CUBIC_STRIDE;
#pragma omp parallel for num_threads(threads) schedule(static)
    for (int64_t y = 0; y < h; y++) {
        if (n_cubic) interleave_row(w, cubic_src, n_cubic, y * w, CUBIC_STRIDE, cubic_pixels + y * w * CUBIC_STRIDE);
        if (n_linear)
            interleave_row(w, linear_src, n_linear, y * w, LINEAR_STRIDE, linear_pixels + y * w * LINEAR_STRIDE);
    }
    int failed = 0;
#pragma omp parallel num_threads(threads)
    {
        /* row buffers: cubic 4 + 4 weights, 4 columns, 4 row offsets; bilinear 2 fractions, 2 columns, 2 row
         * offsets; positions 2; nearest 2 indices */
        float *fl = scratch_alloc((size_t)w * 12 * sizeof(float), &failed);
        int32_t *in = scratch_alloc((size_t)w * 14 * sizeof(int32_t), &failed);
        float *kx[4] = {fl, fl + w, fl + 2 * w, fl + 3 * w}, *ky[4] = {fl + 4 * w, fl + 5 * w, fl + 6 * w, fl + 7 * w};
        float *ux = fl + 8 * w, *uy = fl + 9 * w, *px = fl + 10 * w, *py = fl + 11 * w;
        int32_t *cols[4] = {in, in + w, in + 2 * w, in + 3 * w};
        int32_t *rows[4] = {in + 4 * w, in + 5 * w, in + 6 * w, in + 7 * w};
        int32_t *lc0 = in + 8 * w, *lc1 = in + 9 * w, *lr0 = in + 10 * w, *lr1 = in + 11 * w;
        int32_t *near = in + 12 * w, *moved = in + 13 * w;
        float *pixels = scratch_alloc(sizeof(float) * w * LINEAR_STRIDE, &failed);  /* a row of interleaved results */
#pragma omp barrier
        const int64_t rows_to_do = failed ? 0 : h;
#pragma omp for schedule(static)
        for (int64_t y = 0; y < rows_to_do; y++) {
            const int64_t base = y * w;
            positions(w, (float)y, motion + base, motion + plane + base, px, py);
            if (n_cubic) {
                cubic_axis(w, px, fw, 1, kx[0], kx[1], kx[2], kx[3], cols[0], cols[1], cols[2], cols[3]);
                cubic_axis(w, py, fh, iw, ky[0], ky[1], ky[2], ky[3], rows[0], rows[1], rows[2], rows[3]);
                cubic_row_interleaved(w, cubic_pixels, (const int32_t *const *)rows, (const int32_t *const *)cols,
                                      (const float *const *)kx, (const float *const *)ky, low, high, pixels);
                deinterleave_row(w, pixels, n_cubic, CUBIC_STRIDE, cubic_dst, base);
            }
            if (n_linear) {
                linear_axis(w, px, fw, 1, ux, lc0, lc1);
                linear_axis(w, py, fh, iw, uy, lr0, lr1);
                linear_row_interleaved(w, linear_pixels, lr0, lr1, lc0, lc1, ux, uy, pixels);
                deinterleave_row(w, pixels, n_linear, LINEAR_STRIDE, linear_dst, base);
            }
            if (n_nearest) {
                nearest_index(w, px, py, 0.0f, 0.0f, fw, fh, iw, near);
                for (int64_t c = 0; c < n_nearest; c++) gather_row(w, nearest_src[c], near, nearest_dst[c] + base);
            }
            if (valid) {
                nearest_index(w, px, py, jx, jy, fw, fh, iw, moved);
                geometry_row(w, plane, px, py, jx, jy, fw, fh, moved, depth + base, normal + base,
                             normal + plane + base, normal + 2 * plane + base, prev_depth, prev_normal, dtol, ctol,
                             valid + base);
            }
        }
        free(fl);
        free(in);
        free(pixels);
    }
    return failed;
}
