/* The 3x3 YCoCg moments box of model.ops.rectify (neighbourhood_moments, moment_bounds with gamma 1,
 * clip_to_bounds) for rows of single-image planes, in torch's arithmetic and order; shared by rectify.c and
 * features.c. A thread keeps SLOTS rows of column sums, so each source row is summed once. */
#ifndef YCOCG_BOX_H
#define YCOCG_BOX_H
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#include "scratch.h"

#define SLOTS 3    /* row sums kept per thread: the 3 a row reads, by source row mod SLOTS */
#define MOMENTS 6  /* Y, Co, Cg and their squares */

static inline int64_t clampi(int64_t v, int64_t lo, int64_t hi) { return v < lo ? lo : (v > hi ? hi : v); }

/* rgb_to_ycocg, its products and sums in torch's order */
static inline void ycocg(float r, float g, float b, float *y, float *co, float *cg) {
    *y = 0.25f * r + 0.5f * g + 0.25f * b;
    *co = 0.5f * r - 0.5f * b;
    *cg = -0.25f * r + 0.5f * g - 0.25f * b;
}

/* One guide row's YCoCg and squares summed over 3 columns as box_filter._window_sums does: p[x] + (p[x+1] + p[x+2])
 * over the row padded by one replicated pixel each side. */
static void row_sums(const float *r, const float *g, const float *b, int64_t w, float *pad, float *out) {
    const int64_t stride = w + 2;
#pragma GCC ivdep
    for (int64_t x = 0; x < w; x++) {
        float y, co, cg;
        ycocg(r[x], g[x], b[x], &y, &co, &cg);
        pad[x + 1] = y, pad[stride + x + 1] = co, pad[2 * stride + x + 1] = cg;
        pad[3 * stride + x + 1] = y * y, pad[4 * stride + x + 1] = co * co, pad[5 * stride + x + 1] = cg * cg;
    }
    for (int m = 0; m < MOMENTS; m++) {
        float *p = pad + m * stride, *o = out + m * w;
        p[0] = p[1], p[w + 1] = p[w];
        for (int64_t x = 0; x < w; x++) o[x] = p[x] + (p[x + 1] + p[x + 2]);
    }
}

/* One row of an image clipped to the box in YCoCg (torch.minimum with the high bound, then torch.maximum with the
 * low), RGB out. */
static void clip_row(const float *src, float *dst, int64_t plane, int64_t w, const float *high, const float *low) {
    const float *r = src, *g = src + plane, *b = src + 2 * plane;
    float *d0 = dst, *d1 = dst + plane, *d2 = dst + 2 * plane;
#pragma GCC ivdep
    for (int64_t x = 0; x < w; x++) {
        float y, co, cg;
        ycocg(r[x], g[x], b[x], &y, &co, &cg);
        y = y < high[x] ? y : high[x], y = y > low[x] ? y : low[x];
        co = co < high[w + x] ? co : high[w + x], co = co > low[w + x] ? co : low[w + x];
        cg = cg < high[2 * w + x] ? cg : high[2 * w + x], cg = cg > low[2 * w + x] ? cg : low[2 * w + x];
        /* ycocg_to_rgb */
        d0[x] = y + co - cg;
        d1[x] = y + cg;
        d2[x] = y - co - cg;
    }
}

/* The box (mean + std, mean - std per YCoCg channel: high, low, 3 x w each) of row y from its 3 rows of sums. */
static void box_row(const float *const rows[3], int64_t w, float *high, float *low) {
    for (int m = 0; m < 3; m++) {
        const float *a = rows[0] + m * w, *b = rows[1] + m * w, *c = rows[2] + m * w;
        const float *a2 = a + 3 * w, *b2 = b + 3 * w, *c2 = c + 3 * w;
        float *hi = high + m * w, *lo = low + m * w;
        for (int64_t x = 0; x < w; x++) {
            const float mean = (a[x] + (b[x] + c[x])) / 9.0f;
            const float mean_sq = (a2[x] + (b2[x] + c2[x])) / 9.0f;
            float var = mean_sq - mean * mean;
            var = var < 0.0f ? 0.0f : var;
            const float std = sqrtf(var);
            hi[x] = mean + std;
            lo[x] = mean - std;
        }
    }
}

/* The 3 rows of sums row y's window reads (rows[3]), summing a source row only when its slot holds another. */
static void window_rows(const float *guide, int64_t plane, int64_t h, int64_t w, int64_t y, float *sums, float *pad,
                        int64_t tag[SLOTS], const float *rows[3]) {
    for (int j = 0; j < 3; j++) {
        const int64_t r = clampi(y - 1 + j, 0, h - 1), s = r % SLOTS;
        if (tag[s] != r) {
            row_sums(guide + r * w, guide + plane + r * w, guide + 2 * plane + r * w, w, pad, sums + s * MOMENTS * w);
            tag[s] = r;
        }
        rows[j] = sums + s * MOMENTS * w;
    }
}

/* One thread's block of rows and its scratch for the box: rows y0 .. y1 - 1 in a contiguous block, so each source
 * row's sums are computed once and kept for the 3 windows that read them. */
typedef struct {
    int64_t y0, y1, tag[SLOTS];
    float *sums, *pad, *high, *low;
} BoxRows;

static BoxRows box_rows_begin(int64_t h, int64_t w, int64_t thread, int64_t threads, int *failed) {
    BoxRows b = {h * thread / threads, h * (thread + 1) / threads, {0},
                 scratch_alloc(sizeof(float) * SLOTS * MOMENTS * w, failed),
                 scratch_alloc(sizeof(float) * MOMENTS * (w + 2), failed), scratch_alloc(sizeof(float) * 3 * w, failed),
                 scratch_alloc(sizeof(float) * 3 * w, failed)};
    for (int s = 0; s < SLOTS; s++) b.tag[s] = -1;
    return b;
}

/* the box of row y of the guide (b->high, b->low) */
static void box_rows_at(BoxRows *b, const float *guide, int64_t h, int64_t w, int64_t y) {
    const float *rows[3];
    window_rows(guide, h * w, h, w, y, b->sums, b->pad, b->tag, rows);
    box_row(rows, w, b->high, b->low);
}

static void box_rows_end(BoxRows *b) { free(b->sums), free(b->pad), free(b->high), free(b->low); }

#endif
