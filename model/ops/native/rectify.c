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
int clip_pair_x1(int64_t h, int64_t w, const float *guide, const float *first, float *first_out,
                  const float *second, float *second_out, int64_t threads) {
    const int64_t plane = h * w;
    int failed = 0;
#pragma omp parallel num_threads(threads)
    {
        BoxRows box = box_rows_begin(h, w, omp_get_thread_num(), omp_get_num_threads(), &failed);
#pragma omp barrier
        for (int64_t y = box.y0; y < (failed ? box.y0 : box.y1); y++) {
            box_rows_at(&box, guide, h, w, y);
            clip_row(first + y * w, first_out + y * w, plane, w, box.high, box.low);
            if (second) clip_row(second + y * w, second_out + y * w, plane, w, box.high, box.low);
        }
        box_rows_end(&box);
    }
    return failed;
}
