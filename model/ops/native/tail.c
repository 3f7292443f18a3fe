/* The fused step's work after the network at 1x, one pass per row (model.methods.fused, Fused.step, where no output
 * kernel runs): the softmax of the 4 fusion logits, the sample mean's count kept in proportion to the history's
 * share (Fused._history_share), the history's and the clipped mean's weights moved to OIDN's estimate where the
 * stale-history test distrusts them (Fused._distrust_stale), the blend of the 4 candidates and the output in linear
 * radiance (reinhard_inverse). Planes are single-image (H, W) float32 arrays. */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#include "exp_negative.h"
#include "scratch.h"

#define NOINLINE __attribute__((noinline))

static NOINLINE void weights_row(int64_t w, const float *restrict l0, const float *restrict l1,
                                 const float *restrict l2, const float *restrict l3, const float *restrict trust,
                                 const float *restrict valid, int distrust, float *restrict w0, float *restrict w1,
                                 float *restrict w2, float *restrict w3, float *restrict share) {
    for (int64_t x = 0; x < w; x++) {
        const float a = l0[x], b = l1[x], c = l2[x], d = l3[x];
        const float m01 = a > b ? a : b, m23 = c > d ? c : d, m = m01 > m23 ? m01 : m23;
        const float ea = exp_negative(m - a), eb = exp_negative(m - b), ec = exp_negative(m - c),
                    ed = exp_negative(m - d);
        const float sum = ((ea + eb) + ec) + ed;
        const float p0 = ea / sum, p1 = eb / sum, p2 = ec / sum, p3 = ed / sum;
        /* the history's share of the trust, before the stale test moves any weight */
        const float trusted = p1 + p3, total = trusted + p0;
        share[x] = trusted / (total > 1e-6f ? total : 1e-6f);
        /* where the history is not valid there is nothing to distrust */
        const float t = valid[x] != 0.0f ? trust[x] : 1.0f;
        const float h = p1 * t, k = p3 * t;
        w0[x] = distrust ? p0 + (((p1 + p3) - h) - k) : p0;
        w1[x] = distrust ? h : p1;
        w2[x] = p2;
        w3[x] = distrust ? k : p3;
    }
}

static NOINLINE void blend_row(int64_t w, const float *restrict w0, const float *restrict w1,
                               const float *restrict w2, const float *restrict w3, const float *restrict s,
                               const float *restrict h, const float *restrict r, const float *restrict c,
                               float *restrict blended, float *restrict output) {
    for (int64_t x = 0; x < w; x++) {
        const float v = ((w0[x] * s[x] + w1[x] * h[x]) + w2[x] * r[x]) + w3[x] * c[x];
        blended[x] = v;
        const float y = v < 0.0f ? 0.0f : (v > 1.0f - 1e-6f ? 1.0f - 1e-6f : v);
        output[x] = y / (1.0f - y);
    }
}

int tail_x1(int64_t h, int64_t w, const float *logits, const float *s_out, const float *history,
             const float *rectified, const float *clipped_mean, const float *trust, const uint8_t *valid,
             const float *samples_count, double power, float *blended, float *output, float *new_samples_count,
             int64_t threads) {
    const int64_t plane = h * w;
    const float pw = (float)power;
    int failed = 0;
#pragma omp parallel num_threads(threads)
    {
        float *rows = scratch_alloc(sizeof(float) * 8 * w, &failed);
#pragma omp barrier
        const int64_t rows_to_do = failed ? 0 : h, width = failed ? 0 : w;
        float *w0 = rows, *w1 = rows + w, *w2 = rows + 2 * w, *w3 = rows + 3 * w, *share = rows + 4 * w;
        float *ones = rows + 5 * w, *valid_row = rows + 6 * w, *zeros = rows + 7 * w;
        for (int64_t x = 0; x < width; x++) ones[x] = 1.0f, zeros[x] = 0.0f;
#pragma omp for schedule(static)
        for (int64_t y = 0; y < rows_to_do; y++) {
            const int64_t base = y * w;
            for (int64_t x = 0; x < w; x++) valid_row[x] = valid ? (float)valid[base + x] : 0.0f;
            weights_row(w, logits + base, logits + plane + base, logits + 2 * plane + base, logits + 3 * plane + base,
                        trust ? trust + base : ones, valid_row, trust != NULL, w0, w1, w2, w3, share);
            if (samples_count) {
                const float *restrict count = samples_count + base;
                float *restrict out = new_samples_count + base;
                if (pw == 2.0f)  /* torch's pow(x, 2) is x * x */
                    for (int64_t x = 0; x < w; x++) out[x] = count[x] * (share[x] * share[x]);
                else
                    for (int64_t x = 0; x < w; x++) out[x] = count[x] * powf(share[x], pw);
            }
            for (int k = 0; k < 3; k++) {
                const int64_t o = k * plane + base;
                blend_row(w, w0, w1, w2, w3, s_out + o, history + o, rectified + o, clipped_mean + o, blended + o,
                          output + o);
            }
        }
        free(rows);
    }
    return failed;
}
