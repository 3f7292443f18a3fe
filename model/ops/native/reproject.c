/* The fused step's reprojection at 1x in one pass per pixel: the bicubic, bilinear and nearest backward warps of
 * model.ops.warp (border padding) and the geometry test of model.ops.reproject, with grid_sample's arithmetic
 * (align_corners=False, cubic convolution A = -0.75). Planes are single-image (H, W) float32 arrays. */
#include <math.h>
#include <stdint.h>

#define CUBIC_A (-0.75f)

static inline float clampf(float v, float lo, float hi) { return v < lo ? lo : (v > hi ? hi : v); }

/* grid_sample's unnormalisation of the grid model.ops.warp builds from a position p: g = (2p - S) / S, then
 * (g + 1) * (S / 2) - 0.5 */
static inline float source_coordinate(float p, float size) {
    float g = (2.0f * p - size) / size;
    return (g + 1.0f) * (size * 0.5f) - 0.5f;
}

static inline void cubic_coefficients(float t, float c[4]) {
    float x1 = t + 1.0f, x2 = 1.0f - t, x3 = 2.0f - t;
    c[0] = ((CUBIC_A * x1 - 5.0f * CUBIC_A) * x1 + 8.0f * CUBIC_A) * x1 - 4.0f * CUBIC_A;
    c[1] = ((CUBIC_A + 2.0f) * t - (CUBIC_A + 3.0f)) * t * t + 1.0f;
    c[2] = ((CUBIC_A + 2.0f) * x2 - (CUBIC_A + 3.0f)) * x2 * x2 + 1.0f;
    c[3] = ((CUBIC_A * x3 - 5.0f * CUBIC_A) * x3 + 8.0f * CUBIC_A) * x3 - 4.0f * CUBIC_A;
}

void reproject_x1(int64_t h, int64_t w, const float *motion,
                  const float **cubic_src, float **cubic_dst, int64_t n_cubic, double cubic_low, double cubic_high,
                  const float **linear_src, float **linear_dst, int64_t n_linear,
                  const float **nearest_src, float **nearest_dst, int64_t n_nearest,
                  const float *depth, const float *normal, const float *prev_depth, const float *prev_normal,
                  double jitter_x, double jitter_y, double depth_tol, double cos_tol, uint8_t *valid,
                  int64_t threads) {
    const int64_t plane = h * w;
    const float fw = (float)w, fh = (float)h, low = (float)cubic_low, high = (float)cubic_high;
    const float jx = (float)jitter_x, jy = (float)jitter_y, dtol = (float)depth_tol, ctol = (float)cos_tol;
#pragma omp parallel for num_threads(threads) schedule(static)
    for (int64_t y = 0; y < h; y++) {
        for (int64_t x = 0; x < w; x++) {
            const int64_t i = y * w + x;
            const float px = ((float)x + 0.5f) + motion[i], py = ((float)y + 0.5f) + motion[plane + i];
            const int inside = px >= 0.0f && px < fw && py >= 0.0f && py < fh;
            if (n_cubic) {
                const float ix = source_coordinate(px, fw), iy = source_coordinate(py, fh);
                const float fx = floorf(ix), fy = floorf(iy);
                float cx[4], cy[4];
                cubic_coefficients(ix - fx, cx);
                cubic_coefficients(iy - fy, cy);
                int64_t cols[4], rows[4];
                for (int k = 0; k < 4; k++) {
                    cols[k] = (int64_t)clampf(fx - 1.0f + (float)k, 0.0f, fw - 1.0f);
                    rows[k] = (int64_t)clampf(fy - 1.0f + (float)k, 0.0f, fh - 1.0f) * w;
                }
                for (int64_t c = 0; c < n_cubic; c++) {
                    const float *src = cubic_src[c];
                    float r[4];
                    for (int k = 0; k < 4; k++) {
                        const float *row = src + rows[k];
                        r[k] = row[cols[0]] * cx[0] + row[cols[1]] * cx[1] + row[cols[2]] * cx[2] + row[cols[3]] * cx[3];
                    }
                    float v = r[0] * cy[0] + r[1] * cy[1] + r[2] * cy[2] + r[3] * cy[3];
                    cubic_dst[c][i] = clampf(v, low, high);
                }
            }
            if (n_linear) {
                const float ix = clampf(source_coordinate(px, fw), 0.0f, fw - 1.0f);
                const float iy = clampf(source_coordinate(py, fh), 0.0f, fh - 1.0f);
                const float x0 = floorf(ix), y0 = floorf(iy);
                const float tx = ix - x0, ty = iy - y0, ex = 1.0f - tx, ey = 1.0f - ty;
                const int64_t c0 = (int64_t)x0, r0 = (int64_t)y0 * w;
                /* the far taps lie outside only where their weight is 0 (a read on the last column or row) */
                const int64_t c1 = c0 + 1 < w ? c0 + 1 : c0, r1 = (int64_t)y0 + 1 < h ? r0 + w : r0;
                const float wnw = ey * ex, wne = ey * tx, wsw = ty * ex, wse = ty * tx;
                for (int64_t c = 0; c < n_linear; c++) {
                    const float *src = linear_src[c];
                    linear_dst[c][i] = src[r0 + c0] * wnw + src[r0 + c1] * wne + src[r1 + c0] * wsw + src[r1 + c1] * wse;
                }
            }
            {
                const int64_t nx = (int64_t)clampf(floorf(px), 0.0f, fw - 1.0f);
                const int64_t ny = (int64_t)clampf(floorf(py), 0.0f, fh - 1.0f);
                for (int64_t c = 0; c < n_nearest; c++) nearest_dst[c][i] = nearest_src[c][ny * w + nx];
            }
            if (valid) {
                const float qx = px + jx, qy = py + jy;
                const int in_prev = qx >= 0.0f && qx < fw && qy >= 0.0f && qy < fh;
                const int64_t j = (int64_t)clampf(floorf(qy), 0.0f, fh - 1.0f) * w
                                + (int64_t)clampf(floorf(qx), 0.0f, fw - 1.0f);
                const float d = depth[i], pd = prev_depth[j];
                const float n0 = normal[i], n1 = normal[plane + i], n2 = normal[2 * plane + i];
                const float p0 = prev_normal[j], p1 = prev_normal[plane + j], p2 = prev_normal[2 * plane + j];
                const float lengths = sqrtf((n0 * n0 + n1 * n1 + n2 * n2) * (p0 * p0 + p1 * p1 + p2 * p2));
                const float cosine = (n0 * p0 + n1 * p1 + n2 * p2) / (lengths > 1e-12f ? lengths : 1e-12f);
                valid[i] = in_prev && d > 0.0f && pd > 0.0f && fabsf(d - pd) <= dtol * d && cosine >= ctol;
            }
        }
    }
}
