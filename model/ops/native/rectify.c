/* The fused step's rectification at 1x in one pass per pixel (model.ops.rectify): the guide's YCoCg moments over
 * each 3x3 window, edges replicated (neighbourhood_moments), the box mean +- std (moment_bounds, gamma 1), and one
 * or two images clipped to it in YCoCg (clip_to_bounds), with torch's arithmetic in its order. Planes are
 * single-image (H, W) float32 arrays, three channels. */
#include <math.h>
#include <omp.h>
#include <stdint.h>
#include <stdlib.h>

#include "ycocg_box.h"

/* second and second_out may be NULL (one image clipped). */
void clip_pair_x1(int64_t h, int64_t w, const float *guide, const float *first, float *first_out,
                  const float *second, float *second_out, int64_t threads) {
    const int64_t plane = h * w;
    /* rows in contiguous blocks per thread, so each row's sums are computed once and kept for the 3 that use them */
#pragma omp parallel num_threads(threads)
    {
        const int64_t nt = omp_get_num_threads(), t = omp_get_thread_num();
        const int64_t y0 = h * t / nt, y1 = h * (t + 1) / nt;
        float *sums = malloc(sizeof(float) * SLOTS * MOMENTS * w);
        float *pad = malloc(sizeof(float) * MOMENTS * (w + 2));
        float *high = malloc(sizeof(float) * 3 * w), *low = malloc(sizeof(float) * 3 * w);
        int64_t tag[SLOTS];
        for (int s = 0; s < SLOTS; s++) tag[s] = -1;
        for (int64_t y = y0; y < y1; y++) {
            const float *rows[3];
            window_rows(guide, plane, h, w, y, sums, pad, tag, rows);
            box_row(rows, w, high, low);
            clip_row(first + y * w, first_out + y * w, plane, w, high, low);
            if (second) clip_row(second + y * w, second_out + y * w, plane, w, high, low);
        }
        free(sums), free(pad), free(high), free(low);
    }
}
