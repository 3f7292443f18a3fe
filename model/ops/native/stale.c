/* The stale-history test of model.ops.stale_history and the sample-mean update of model.ops.sample_mean for one
 * image. Box means are separable: along each row box_sum's own sums of doubling spans over a zero-padded copy (the
 * same float32 additions in the same order, and loops that vectorize, where a running sum along the row would be
 * one serial chain), then down the columns as running sums with one accumulator row per thread, kept in double so
 * adding and removing rows does not drift the way a float32 running sum would. Each window sum is rounded to float32
 * and divided by its count inside the image, as box_mean does. Planes are single-image (H, W) float32 arrays. */
#include <math.h>
#include <omp.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "exp_negative.h"
#include "scratch.h"

static inline int64_t min64(int64_t a, int64_t b) { return a < b ? a : b; }
static inline int64_t max64(int64_t a, int64_t b) { return a > b ? a : b; }

/* How many of the window's positions around i lie inside a line of n pixels (box_mean's count). */
static inline float inside_count(int64_t i, int64_t r, int64_t n) {
    return (float)(min64(i + r, n - 1) - max64(i - r, 0) + 1);
}

static void add_shifted(const float *restrict from, int64_t length, int64_t shift, float *restrict to) {
    for (int64_t k = 0; k < length; k++) to[k] = from[k] + from[k + shift];
}

static void accumulate(const float *restrict from, int64_t length, int first, float *restrict out) {
    if (first)
        for (int64_t x = 0; x < length; x++) out[x] = from[x];
    else
        for (int64_t x = 0; x < length; x++) out[x] = out[x] + from[x];
}

/* Window sums of radius r along one row, as box_mean's _window_sums adds them: sums of 1, 2, 4, ... entries, then
 * one of each binary digit of the window's size. pad holds the row at [r, r + w) and zeros around it (length
 * w + 2r); scratch holds two such rows. */
static void row_sums(const float *pad, int64_t w, int64_t r, float *scratch, float *out) {
    const int64_t padded = w + 2 * r;
    const float *sums = pad;
    int64_t remaining = 2 * r + 1, offset = 0, span = 1, length = padded, turn = 0;
    int first = 1;
    for (;;) {
        if (remaining & 1) {
            accumulate(sums + offset, w, first, out);
            first = 0;
            offset += span;
        }
        remaining >>= 1;
        if (!remaining) return;
        float *next = scratch + turn * padded;
        add_shifted(sums, length - span, span, next);
        sums = next;
        length -= span;
        span *= 2;
        turn ^= 1;
    }
}

/* The column window sums of radius r of n planes of row sums (each H x W) at row y0, in double: acc (n * w). */
static void column_start(const float **planes, int64_t n, int64_t y0, int64_t h, int64_t w, int64_t r, double *acc) {
    for (int64_t c = 0; c < n; c++) {
        double *a = acc + c * w;
        for (int64_t x = 0; x < w; x++) a[x] = 0.0;
        for (int64_t j = max64(y0 - r, 0); j <= min64(y0 + r, h - 1); j++) {
            const float *p = planes[c] + j * w;
            for (int64_t x = 0; x < w; x++) a[x] += p[x];
        }
    }
}

/* acc from row y's column sums to row y + 1's: the row entering the window added, the one leaving removed. */
static void column_step(const float **planes, int64_t n, int64_t y, int64_t h, int64_t w, int64_t r, double *acc) {
    const int64_t enter = y + r + 1, leave = y - r;
    for (int64_t c = 0; c < n; c++) {
        double *a = acc + c * w;
        if (enter < h) {
            const float *p = planes[c] + enter * w;
            for (int64_t x = 0; x < w; x++) a[x] += p[x];
        }
        if (leave >= 0) {
            const float *p = planes[c] + leave * w;
            for (int64_t x = 0; x < w; x++) a[x] -= p[x];
        }
    }
}

/* exp(-max(z - sigmas, 0)^2 / 2), history_trust's arithmetic; (d + |d|) / 2 is max(d, 0) exactly. */
static inline float trust_of(float z, float sigmas) {
    const float d = z - sigmas, excess = (d + fabsf(d)) * 0.5f;
    return exp_negative(excess * excess / 2.0f);
}

/* One row of stale_history_z from the window sums of value, past and value^2 (acc, 3 * w): the box means are the
 * sums over the window's count inside the image (the row's ch times each column's). */
static void z_row(const double *restrict acc, int64_t w, float ch, const float *restrict columns, float floor_,
                  float block_area, float *restrict z) {
    for (int64_t x = 0; x < w; x++) {
        const float count = ch * columns[x];
        const float mean = (float)acc[x] / count, past = (float)acc[w + x] / count;
        const float square = (float)acc[2 * w + x] / count;
        const float spread = square - mean * mean, variance = spread > 0.0f ? spread : 0.0f;
        const float scaled = floor_ * past;
        const float error = sqrtf(variance / block_area + scaled * scaled + 1e-6f);
        z[x] = fabsf(mean - past) / error;
    }
}

static void trust_row(const float *restrict z, int64_t w, float sigmas, float *restrict trust) {
    for (int64_t x = 0; x < w; x++) trust[x] = trust_of(z[x], sigmas);
}

static void capped_row(const float *restrict z, int64_t w, float cap, float *restrict capped) {
    for (int64_t x = 0; x < w; x++) {
        const float c = z[x] < cap ? z[x] : cap;
        capped[x] = c * c;
    }
}

/* The regional test for one row from the window sums of the capped squares (acc, w): the lesser of both trusts. */
static void regional_row(const double *restrict acc, int64_t w, float ch, const float *restrict columns,
                         float sigmas, float *restrict trust) {
    for (int64_t x = 0; x < w; x++) {
        const float z = sqrtf((float)acc[x] / (ch * columns[x]));
        const float t = trust_of(z, sigmas);
        trust[x] = t < trust[x] ? t : trust[x];
    }
}

/* stale_history_trust: noisy and history are 3 planes each; trust (H x W) is written. region 0: no regional test. */
int stale_trust(int64_t h, int64_t w, const float **noisy, const float **history, double sigmas, int64_t block,
                 int64_t region, double relative_floor, double region_cap, double region_sigmas, float *trust,
                 int64_t threads) {
    const int64_t plane = h * w, rb = block / 2, rr = region / 2;
    const float s = (float)sigmas, floor_ = (float)relative_floor, cap = (float)region_cap;
    const float rs = (float)region_sigmas, block_area = (float)(block * block);
    int failed = 0;
    float *sums = scratch_alloc(sizeof(float) * 3 * plane, &failed); /* row sums of value, past, value^2 */
    /* min(z, cap)^2, then its row sums */
    float *capped = region ? scratch_alloc(sizeof(float) * 2 * plane, &failed) : NULL;
    const float *planes[3] = {sums, sums + plane, sums + 2 * plane};

#pragma omp parallel num_threads(threads)
    {
        const int64_t pad_length = w + 2 * (rb > rr ? rb : rr);
        float *pad = scratch_zeroed((size_t)(5 * pad_length), sizeof(float), &failed), *scratch = pad + 3 * pad_length;
        double *acc = scratch_alloc(sizeof(double) * 3 * w, &failed);
        float *z = scratch_alloc(sizeof(float) * w, &failed);
        /* each column's count of window positions inside the image */
        float *columns = scratch_alloc(sizeof(float) * w, &failed);
#pragma omp barrier
        const int t = omp_get_thread_num(), nt = omp_get_num_threads();
        /* after a failed allocation every thread skips every row */
        const int64_t y0 = failed ? 0 : h * t / nt, y1 = failed ? 0 : h * (t + 1) / nt, rows = failed ? 0 : h;
        const int64_t width = failed ? 0 : w;

#pragma omp for schedule(static)
        for (int64_t y = 0; y < rows; y++) {
            float *v = pad + rb, *p = pad + pad_length + rb, *q = pad + 2 * pad_length + rb;
            const int64_t i = y * w;
            for (int64_t x = 0; x < w; x++) {
                const float value = (noisy[0][i + x] + noisy[1][i + x] + noisy[2][i + x]) / 3.0f;
                v[x] = value;
                p[x] = (history[0][i + x] + history[1][i + x] + history[2][i + x]) / 3.0f;
                q[x] = value * value;
            }
            for (int c = 0; c < 3; c++) row_sums(pad + c * pad_length, w, rb, scratch, sums + c * plane + i);
        }
        /* the implicit barrier above: every row's sums are written */
        for (int64_t x = 0; x < width; x++) columns[x] = inside_count(x, rb, w);
        if (!failed) column_start(planes, 3, y0, h, w, rb, acc);
        for (int64_t y = y0; y < y1; y++) {
            const int64_t i = y * w;
            z_row(acc, w, inside_count(y, rb, h), columns, floor_, block_area, z);
            trust_row(z, w, s, trust + i);
            if (region) capped_row(z, w, cap, capped + i);
            column_step(planes, 3, y, h, w, rb, acc);
        }
        if (region) {
#pragma omp barrier
            const int64_t region_pad = w + 2 * rr;
            for (int64_t x = 0; x < (failed ? 0 : region_pad); x++) pad[x] = 0.0f;
#pragma omp for schedule(static)
            for (int64_t y = 0; y < rows; y++) {
                memcpy(pad + rr, capped + y * w, sizeof(float) * w);
                row_sums(pad, w, rr, scratch, capped + plane + y * w);
            }
            const float *row_planes[1] = {capped + plane};
            for (int64_t x = 0; x < width; x++) columns[x] = inside_count(x, rr, w);
            if (!failed) column_start(row_planes, 1, y0, h, w, rr, acc);
            for (int64_t y = y0; y < y1; y++) {
                regional_row(acc, w, inside_count(y, rr, h), columns, rs, trust + y * w);
                column_step(row_planes, 1, y, h, w, rr, acc);
            }
        }
        free(pad);
        free(acc);
        free(z);
        free(columns);
    }
    free(sums);
    free(capped);
    return failed;
}

/* update_sample_mean's count arithmetic and mean update for n_channels planes; trust and spread may be NULL. */
int sample_mean_update(int64_t h, int64_t w, int64_t n_channels, const float **noisy, const float **mean,
                        const float *count, const float *trust, const float *spread, const uint8_t *valid,
                        double max_frames, float **out_mean, float *out_count, int64_t threads) {
    const float most = (float)max_frames;
    int failed = 0;
#pragma omp parallel num_threads(threads)
    {
        float *keep = scratch_alloc(sizeof(float) * w, &failed); /* 1 - 1 / n, shared by the channels */
#pragma omp barrier
        const int64_t rows = failed ? 0 : h;
#pragma omp for schedule(static)
        for (int64_t y = 0; y < rows; y++) {
            const int64_t i = y * w;
            float *n = out_count + i;
            for (int64_t x = 0; x < w; x++) n[x] = count[i + x];
            if (trust)
                for (int64_t x = 0; x < w; x++) n[x] = n[x] * trust[i + x];
            if (spread)
                for (int64_t x = 0; x < w; x++) {
                    const float s = spread[i + x] > 0.0f ? spread[i + x] : 0.0f;
                    n[x] = n[x] * (1.0f - (s < 1.0f ? s : 1.0f));
                }
            for (int64_t x = 0; x < w; x++) {
                const float k = (valid[i + x] ? n[x] : 0.0f) + 1.0f;
                n[x] = k < most ? k : most;
                keep[x] = 1.0f - 1.0f / n[x];
            }
            for (int64_t c = 0; c < n_channels; c++) {
                const float *a = noisy[c] + i, *b = mean[c] + i;
                float *o = out_mean[c] + i;
                for (int64_t x = 0; x < w; x++) o[x] = a[x] / n[x] + keep[x] * b[x];
            }
        }
        free(keep);
    }
    return failed;
}
