/* The fused network's joints between its convolutions in bfloat16 channels-last (model.methods.fused.FusionNet):
 * the 2x2 mean pooling (avg_pool2d, ceil_mode: a window cut by the border divides by the pixels it holds) and the
 * bilinear upsampling of the coarse level (interpolate, align_corners=False) written next to the fine level's
 * channels (the concatenation the decoder reads), each in float and rounded once to bfloat16, as torch's kernels
 * do. torch's own kernels for these in bfloat16 took a third of the network's time on the CPU. Images are single
 * (H, W, C) arrays of bfloat16 bit patterns. */
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "scratch.h"

#define NOINLINE __attribute__((noinline))

static inline float from_bf16(uint16_t v) {
    const uint32_t u = (uint32_t)v << 16;
    float f;
    memcpy(&f, &u, sizeof f);
    return f;
}

/* rounding to nearest even, as torch's conversion (the values are finite) */
static inline uint16_t to_bf16(float f) {
    uint32_t u;
    memcpy(&u, &f, sizeof u);
    return (uint16_t)((u + 0x7FFFu + ((u >> 16) & 1u)) >> 16);
}

int mean_pool2_bf16(int64_t h, int64_t w, int64_t c, const uint16_t *src, uint16_t *dst, int64_t threads) {
    const int64_t ho = (h + 1) / 2, wo = (w + 1) / 2;
    int failed = 0;
#pragma omp parallel num_threads(threads)
    {
        float *sum = scratch_alloc(sizeof(float) * c, &failed);
#pragma omp barrier
        const int64_t rows = failed ? 0 : ho;
#pragma omp for schedule(static)
        for (int64_t oy = 0; oy < rows; oy++) {
            const int64_t y0 = 2 * oy, y1 = y0 + 2 < h ? y0 + 2 : h;
            for (int64_t ox = 0; ox < wo; ox++) {
                const int64_t x0 = 2 * ox, x1 = x0 + 2 < w ? x0 + 2 : w;
                const float count = (float)((y1 - y0) * (x1 - x0));
                for (int64_t k = 0; k < c; k++) sum[k] = 0.0f;
                for (int64_t y = y0; y < y1; y++)
                    for (int64_t x = x0; x < x1; x++) {
                        const uint16_t *p = src + (y * w + x) * c;
                        for (int64_t k = 0; k < c; k++) sum[k] += from_bf16(p[k]);
                    }
                uint16_t *o = dst + (oy * wo + ox) * c;
                for (int64_t k = 0; k < c; k++) o[k] = to_bf16(sum[k] / count);
            }
        }
        free(sum);
    }
    return failed;
}

/* interpolate's source index along one axis (area_pixel_compute_source_index, align_corners=False) */
static void axis_taps(int64_t out, int64_t in, int64_t *i0, int64_t *i1, float *l0, float *l1) {
    const float scale = (float)in / (float)out;
    for (int64_t d = 0; d < out; d++) {
        float s = scale * ((float)d + 0.5f) - 0.5f;
        s = s < 0.0f ? 0.0f : s;
        const int64_t a = (int64_t)s;
        i0[d] = a;
        i1[d] = a < in - 1 ? a + 1 : a;
        l1[d] = s - (float)a;
        l0[d] = 1.0f - l1[d];
    }
}

static NOINLINE void up_row(int64_t c, const uint16_t *restrict p00, const uint16_t *restrict p01,
                            const uint16_t *restrict p10, const uint16_t *restrict p11, float w00, float w01,
                            float w10, float w11, uint16_t *restrict o) {
    for (int64_t k = 0; k < c; k++)
        o[k] = to_bf16(from_bf16(p00[k]) * w00 + from_bf16(p01[k]) * w01 + from_bf16(p10[k]) * w10
                       + from_bf16(p11[k]) * w11);
}

int upsample_cat_bf16(int64_t h, int64_t w, int64_t c_fine, const uint16_t *fine, int64_t hc, int64_t wc,
                       int64_t c_coarse, const uint16_t *coarse, uint16_t *dst, int64_t threads) {
    int failed = 0;
    int64_t *taps = scratch_alloc(sizeof(int64_t) * 2 * (h + w), &failed);
    float *weights = scratch_alloc(sizeof(float) * 2 * (h + w), &failed);
    if (failed) {
        free(taps), free(weights);
        return failed;
    }
    int64_t *ys0 = taps, *ys1 = taps + h, *xs0 = taps + 2 * h, *xs1 = taps + 2 * h + w;
    float *ly0 = weights, *ly1 = weights + h, *lx0 = weights + 2 * h, *lx1 = weights + 2 * h + w;
    axis_taps(h, hc, ys0, ys1, ly0, ly1);
    axis_taps(w, wc, xs0, xs1, lx0, lx1);
    const int64_t c = c_fine + c_coarse;
#pragma omp parallel for num_threads(threads) schedule(static)
    for (int64_t y = 0; y < h; y++) {
        const uint16_t *r0 = coarse + ys0[y] * wc * c_coarse, *r1 = coarse + ys1[y] * wc * c_coarse;
        for (int64_t x = 0; x < w; x++) {
            uint16_t *o = dst + (y * w + x) * c;
            memcpy(o, fine + (y * w + x) * c_fine, c_fine * sizeof(uint16_t));
            up_row(c_coarse, r0 + xs0[x] * c_coarse, r0 + xs1[x] * c_coarse, r1 + xs0[x] * c_coarse,
                   r1 + xs1[x] * c_coarse, ly0[y] * lx0[x], ly0[y] * lx1[x], ly1[y] * lx0[x], ly1[y] * lx1[x],
                   o + c_fine);
        }
    }
    free(taps), free(weights);
    return failed;
}
