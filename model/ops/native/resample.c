/* The fused step's unjittered resample at 1x in one pass per pixel (model.methods.fused.sample_mean_resample and
 * unjittered_resample): the image read bicubic at a uniform sub-pixel shift (model.ops.separable_sample, border
 * replicated), clamped to the 3x3 max and min of the source read nearest at the same shift, then blended with the
 * image by 1 / count. The shift is the same for every pixel, so the caller passes the tap weights and the nearest
 * indices as small tables computed by the torch code itself: the reads agree exactly (half-to-even rounding
 * included). Planes are single-image (H, W) float32 arrays, three channels. */
#include <omp.h>
#include <stdint.h>
#include <stdlib.h>

#include "scratch.h"

#define SLOTS 5  /* x-filtered rows kept per thread: the 4 a row reads, by source row mod SLOTS */
#define CHANNELS 3

static inline int64_t clampi(int64_t v, int64_t lo, int64_t hi) { return v < lo ? lo : (v > hi ? hi : v); }

/* The first of the 4 taps that carry weight: torch sums 5 (whole-pixel shifts -2..2), one of them 0 * x, which is
 * exact to leave out. */
static inline int first_tap(const float *weights) { return weights[0] == 0.0f ? 1 : 0; }

/* One source row read with the x weights, as separable_sample sums them: tap by tap, left to right. */
static void filter_row(const float *src, int64_t w, const float *wx, float *pad, float *out) {
    pad[0] = pad[1] = src[0];
    for (int64_t x = 0; x < w; x++) pad[x + 2] = src[x];
    pad[w + 2] = pad[w + 3] = src[w - 1];
    const int k = first_tap(wx);
    const float *p = pad + k;
    const float w0 = wx[k], w1 = wx[k + 1], w2 = wx[k + 2], w3 = wx[k + 3];
    for (int64_t x = 0; x < w; x++) out[x] = p[x] * w0 + p[x + 1] * w1 + p[x + 2] * w2 + p[x + 3] * w3;
}

/* The 3x3 max and min around each pixel of source row ry, edges replicated (vmax, vmin: w + 2 scratch). */
static void row_extremes(const float *src, int64_t h, int64_t w, int64_t ry, float *vmax, float *vmin, float *hmax,
                         float *hmin) {
    const float *up = src + clampi(ry - 1, 0, h - 1) * w, *mid = src + ry * w;
    const float *down = src + clampi(ry + 1, 0, h - 1) * w;
    for (int64_t x = 0; x < w; x++) {
        const float a = up[x], b = mid[x], d = down[x];
        const float hi = a > b ? a : b, lo = a < b ? a : b;
        vmax[x + 1] = hi > d ? hi : d;
        vmin[x + 1] = lo < d ? lo : d;
    }
    vmax[0] = vmax[1], vmin[0] = vmin[1], vmax[w + 1] = vmax[w], vmin[w + 1] = vmin[w];
    for (int64_t x = 0; x < w; x++) {
        const float a = vmax[x], b = vmax[x + 1], d = vmax[x + 2];
        const float e = vmin[x], f = vmin[x + 1], g = vmin[x + 2];
        const float hi = a > b ? a : b, lo = e < f ? e : f;
        hmax[x] = hi > d ? hi : d;
        hmin[x] = lo < g ? lo : g;
    }
}

/* Columns [x0, x1) of one output row, whose nearest reads all lie `offset` columns away: the vertical taps, the
 * clamp to the bounds read there, the blend (cnt NULL: none). */
static void blend_run(int64_t x0, int64_t x1, int64_t offset, const float *const t[4], const float *wy,
                      const float *hmin, const float *hmax, const float *cnt, const float *img, float *dst) {
    const float w0 = wy[0], w1 = wy[1], w2 = wy[2], w3 = wy[3];
    for (int64_t x = x0; x < x1; x++) {
        const float read = t[0][x] * w0 + t[1][x] * w1 + t[2][x] * w2 + t[3][x] * w3;
        const float lo = hmin[x + offset], hi = hmax[x + offset];
        float v = read < lo ? lo : read;  /* torch.clamp: max with the low bound, then min with the high */
        v = v > hi ? hi : v;
        if (cnt) {
            const float n = cnt[x] < 1.0f ? 1.0f : cnt[x];
            v = img[x] + (1.0f / n) * (v - img[x]);
        }
        dst[x] = v;
    }
}

/* count NULL: unjittered_resample (the clamped read itself); otherwise image + (read - image) / max(count, 1).
 * wx, wy: the 5 tap weights per axis; columns, rows: the pixel each output column and row reads nearest. */
int resample_x1(int64_t h, int64_t w, const float *image, const float *count, const float *wx, const float *wy,
                 const int32_t *columns, const int32_t *rows, float *out, int64_t threads) {
    const int64_t plane = h * w;
    const int ky = first_tap(wy);
    /* the columns in runs of one offset to their nearest read (a few: the shift is uniform), so no gathers */
    int failed = 0;
    int64_t *runs = scratch_alloc(sizeof(int64_t) * (w + 1), &failed), n_runs = 0;
    if (failed) return failed;
    for (int64_t x = 0; x < w; x++)
        if (x == 0 || columns[x] - x != columns[x - 1] - (x - 1)) runs[n_runs++] = x;
    runs[n_runs] = w;
    /* rows in contiguous blocks per thread, so each x-filtered row is computed once and kept for the 4 that use it */
#pragma omp parallel num_threads(threads)
    {
        const int64_t nt = omp_get_num_threads(), t = omp_get_thread_num();
        const int64_t y0 = h * t / nt, y1 = h * (t + 1) / nt;
        float *filtered = scratch_alloc(sizeof(float) * SLOTS * CHANNELS * w, &failed);
        float *pad = scratch_alloc(sizeof(float) * (w + 4), &failed);
        float *vmax = scratch_alloc(sizeof(float) * (w + 2), &failed);
        float *vmin = scratch_alloc(sizeof(float) * (w + 2), &failed);
        float *hmax = scratch_alloc(sizeof(float) * w, &failed), *hmin = scratch_alloc(sizeof(float) * w, &failed);
        int64_t tag[SLOTS];
        for (int s = 0; s < SLOTS; s++) tag[s] = -1;
#pragma omp barrier
        for (int64_t y = y0; y < (failed ? y0 : y1); y++) {
            const float *taps[CHANNELS][4];
            for (int j = 0; j < 4; j++) {
                const int64_t r = clampi(y - 2 + ky + j, 0, h - 1), s = r % SLOTS;
                if (tag[s] != r) {
                    for (int c = 0; c < CHANNELS; c++)
                        filter_row(image + c * plane + r * w, w, wx, pad, filtered + (s * CHANNELS + c) * w);
                    tag[s] = r;
                }
                for (int c = 0; c < CHANNELS; c++) taps[c][j] = filtered + (s * CHANNELS + c) * w;
            }
            for (int c = 0; c < CHANNELS; c++) {
                const float *src = image + c * plane;
                row_extremes(src, h, w, rows[y], vmax, vmin, hmax, hmin);
                const float *cnt = count ? count + y * w : NULL;
                for (int64_t r = 0; r < n_runs; r++)
                    blend_run(runs[r], runs[r + 1], columns[runs[r]] - runs[r], taps[c], wy + ky, hmin, hmax, cnt,
                              src + y * w, out + c * plane + y * w);
            }
        }
        free(filtered), free(pad), free(vmax), free(vmin), free(hmax), free(hmin);
    }
    free(runs);
    return failed;
}
