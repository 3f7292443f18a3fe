/* The fused step's work between OIDN and the network at 1x, one pass per row (model.methods.fused,
 * Fused._network_inputs): the history where the geometry test holds (else the estimate), the running mean's
 * update, both clipped to the estimate's 3x3 YCoCg moments (model.ops.rectify), the history length, and the
 * network's 35 input channels written channels-last in float32 or bfloat16. Planes are single-image (H, W) float32
 * arrays; a NULL history means no state (the first frame), a NULL mean none in the state. Each row is computed into
 * planar row buffers (vectorized loops), then interleaved into the channels-last output. */
#include <math.h>
#include <omp.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "ycocg_box.h"

#define FEATURES 35

/* float32 to bfloat16, rounding to nearest even as torch's conversion does (the inputs are finite) */
static inline uint16_t to_bf16(float v) {
    uint32_t u;
    memcpy(&u, &v, sizeof u);
    return (uint16_t)((u + 0x7FFFu + ((u >> 16) & 1u)) >> 16);
}

typedef struct {
    const float *s, *s_out, *color, *albedo, *normal, *history, *length, *hidden, *mean, *count, *depth;
    const uint8_t *valid;
    float dmax, lmax, cnorm;
    int64_t plane, w;
} Inputs;

/* Row buffers of one thread: what a missing input reads as (zeros, ones) and log1p(n) / norm for whole n. */
typedef struct {
    const float *zeros, *ones;
    const uint8_t *invalid;
    float *valid;
    float log_count[65];
} Fallbacks;

/* One colour channel of a row: the history where valid (else the estimate), the running mean's update, and their
 * feature rows (the estimate, the tone-mapped colour, the history, |history - estimate|, the mean, |mean -
 * estimate|). */
static __attribute__((noinline)) void colour_row(
        int64_t w, const float *restrict valid, const float *restrict est, const float *restrict sv,
        const float *restrict hist, const float *restrict mean, const float *restrict count,
        const float *restrict color, float *restrict h_out, float *restrict m_out, float *restrict f_s,
        float *restrict f_c, float *restrict f_h, float *restrict f_hd, float *restrict f_m, float *restrict f_md) {
    for (int64_t x = 0; x < w; x++) {
        const float past = hist[x], now = est[x];  /* both read: a select, not a branch */
        const float hv = valid[x] != 0.0f ? past : now;
        /* 1 / n weights over the frames the history held (no mean: the estimate, over 1) */
        const float mv = mean[x] + (now - mean[x]) / count[x];
        h_out[x] = hv;
        m_out[x] = mv;
        f_s[x] = sv[x];
        f_c[x] = color[x] / (1.0f + color[x]);
        f_h[x] = hv;
        f_hd[x] = fabsf(hv - sv[x]);
        f_m[x] = mv;
        f_md[x] = fabsf(mv - sv[x]);
    }
}

/* One row's outputs: the candidates and state (NCHW planes) and the 35 features as planar rows f[c * w + x]. A
 * missing input reads as what the torch code puts in its place: no history is the estimate everywhere invalid, no
 * running mean is the estimate with a count of 1, no state is zero length and hidden features. */
static void features_row(const Inputs *in, const Fallbacks *fb, int64_t y, const float *high, const float *low,
                         float *const out[5], float *restrict f) {
    const int64_t w = in->w, plane = in->plane, base = y * w;
    const uint8_t *restrict valid_bytes = in->valid ? in->valid + base : fb->invalid;
    const float *restrict count = in->count ? in->count + base : fb->ones;
    float *restrict valid = fb->valid;  /* as 0 / 1: the select loops below vectorize over floats */
    for (int64_t x = 0; x < w; x++) valid[x] = (float)valid_bytes[x];
    for (int64_t k = 0; k < 3; k++) {
        const float *restrict est = in->s_out + k * plane + base, *restrict sv = in->s + k * plane + base;
        const float *restrict hist = in->history ? in->history + k * plane + base : est;
        const float *restrict mean = in->mean ? in->mean + k * plane + base : est;
        const float *restrict color = in->color + k * plane + base;
        float *restrict h_out = out[0] + k * plane + base, *restrict m_out = out[2] + k * plane + base;
        colour_row(w, valid, est, sv, hist, mean, count, color, h_out, m_out, f + k * w, f + (3 + k) * w,
                   f + (12 + k) * w, f + (18 + k) * w, f + (28 + k) * w, f + (31 + k) * w);
        memcpy(f + (6 + k) * w, in->albedo + k * plane + base, w * sizeof(float));
        memcpy(f + (9 + k) * w, in->normal + k * plane + base, w * sizeof(float));
    }
    clip_row(out[0] + base, out[1] + base, plane, w, high, low);
    clip_row(out[2] + base, out[3] + base, plane, w, high, low);
    for (int k = 0; k < 3; k++) memcpy(f + (15 + k) * w, out[1] + k * plane + base, w * sizeof(float));
    const float *restrict depth = in->depth + base;
    const float *restrict length = in->length ? in->length + base : fb->zeros;
    float *restrict len_out = out[4] + base, *restrict f_d = f + 21 * w, *restrict f_v = f + 22 * w,
          *restrict f_l = f + 23 * w, *restrict f_n = f + 34 * w;
    const float dmax = in->dmax, lmax = in->lmax;
    for (int64_t x = 0; x < w; x++) {
        const float grown = length[x] + 1.0f < lmax ? length[x] + 1.0f : lmax;
        const float len = valid[x] != 0.0f ? grown : 0.0f;
        len_out[x] = len;
        f_d[x] = depth[x] / dmax;
        f_v[x] = valid[x];
        f_l[x] = len / lmax;
    }
    /* the running mean's count is a whole number of frames: log1p from a table, the library's log1pf otherwise */
    for (int64_t x = 0; x < w; x++) {
        const float c = count[x];
        const int32_t n = (int32_t)c;
        f_n[x] = (n >= 0 && n <= 64 && (float)n == c) ? fb->log_count[n] : log1pf(c) / in->cnorm;
    }
    for (int k = 0; k < 4; k++) {
        const float *restrict hidden = in->hidden ? in->hidden + k * plane + base : fb->zeros;
        float *restrict dst = f + (24 + k) * w;
        for (int64_t x = 0; x < w; x++) dst[x] = valid[x] * hidden[x];
    }
}

int features_x1(int64_t h, int64_t w, const float *s, const float *s_out, const float *color, const float *albedo,
                 const float *normal, const float *history, const uint8_t *valid, const float *length,
                 const float *hidden, const float *mean, const float *count, const float *depth, double depth_max,
                 double max_history, double count_norm, float *out_history, float *out_rectified, float *out_mean,
                 float *out_clipped_mean, float *out_length, void *features, int64_t bf16, int64_t threads) {
    const Inputs in = {s, s_out, color, albedo, normal, history, length, hidden, mean, count, depth, valid,
                       (float)depth_max, (float)max_history, (float)count_norm, h * w, w};
    float *const out[5] = {out_history, out_rectified, out_mean, out_clipped_mean, out_length};
    int failed = 0;
#pragma omp parallel num_threads(threads)
    {
        BoxRows box = box_rows_begin(h, w, omp_get_thread_num(), omp_get_num_threads(), &failed);
        float *f = scratch_alloc(sizeof(float) * FEATURES * w, &failed);
        uint16_t *half = scratch_alloc(sizeof(uint16_t) * FEATURES * w, &failed);
        float *zeros = scratch_zeroed(w, sizeof(float), &failed), *ones = scratch_alloc(sizeof(float) * w, &failed);
        uint8_t *invalid = scratch_zeroed(w, 1, &failed);
        float *valid_row = scratch_alloc(sizeof(float) * w, &failed);
#pragma omp barrier
        Fallbacks fb = {zeros, ones, invalid, valid_row, {0}};
        for (int64_t x = 0; x < (failed ? 0 : w); x++) ones[x] = 1.0f;
        for (int n = 0; n <= 64; n++) fb.log_count[n] = log1pf((float)n) / in.cnorm;
        for (int64_t y = box.y0; y < (failed ? box.y0 : box.y1); y++) {
            box_rows_at(&box, s_out, h, w, y);
            features_row(&in, &fb, y, box.high, box.low, out, f);
            if (bf16) {
                for (int64_t i = 0; i < FEATURES * w; i++) half[i] = to_bf16(f[i]);
                uint16_t *dst = (uint16_t *)features + y * w * FEATURES;
                for (int64_t x = 0; x < w; x++)
                    for (int c = 0; c < FEATURES; c++) dst[x * FEATURES + c] = half[c * w + x];
            } else {
                float *dst = (float *)features + y * w * FEATURES;
                for (int64_t x = 0; x < w; x++)
                    for (int c = 0; c < FEATURES; c++) dst[x * FEATURES + c] = f[c * w + x];
            }
        }
        box_rows_end(&box);
        free(f), free(half), free(zeros), free(ones), free(invalid), free(valid_row);
    }
    return failed;
}
