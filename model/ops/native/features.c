/* The fused step's work between OIDN and the network at 1x, one pass per pixel (model.methods.fused, Fused.step):
 * the history where the geometry test holds (else the estimate), the running mean's update, both clipped to the
 * estimate's 3x3 YCoCg moments (model.ops.rectify), the history length, and the network's 35 input channels written
 * channels-last. Planes are single-image (H, W) float32 arrays; a NULL history means no state (the first frame). */
#include <math.h>
#include <stdint.h>
#include <string.h>

static inline int64_t clampi(int64_t v, int64_t lo, int64_t hi) { return v < lo ? lo : (v > hi ? hi : v); }

static inline void to_ycocg(float r, float g, float b, float out[3]) {
    out[0] = 0.25f * r + 0.5f * g + 0.25f * b;
    out[1] = 0.5f * r - 0.5f * b;
    out[2] = -0.25f * r + 0.5f * g - 0.25f * b;
}

/* clamp rgb, in YCoCg, to [low, high]; rgb out */
static inline void clip(const float in[3], const float high[3], const float low[3], float out[3]) {
    float c[3];
    to_ycocg(in[0], in[1], in[2], c);
    for (int k = 0; k < 3; k++) c[k] = fmaxf(fminf(c[k], high[k]), low[k]);
    out[0] = c[0] + c[1] - c[2];
    out[1] = c[0] + c[2];
    out[2] = c[0] - c[1] - c[2];
}

void features_x1(int64_t h, int64_t w, const float *s, const float *s_out, const float *color, const float *albedo,
                 const float *normal, const float *history, const uint8_t *valid, const float *length,
                 const float *hidden, const float *mean, const float *count, const float *depth, double depth_max,
                 double max_history, double count_norm, float *out_history, float *out_rectified, float *out_mean,
                 float *out_clipped_mean, float *out_length, float *features, int64_t channels, int64_t threads) {
    const int64_t plane = h * w;
    const float dmax = (float)depth_max, lmax = (float)max_history, cnorm = (float)count_norm;
#pragma omp parallel for num_threads(threads) schedule(static)
    for (int64_t y = 0; y < h; y++) {
        int64_t rows[3] = {clampi(y - 1, 0, h - 1) * w, y * w, clampi(y + 1, 0, h - 1) * w};
        for (int64_t x = 0; x < w; x++) {
            const int64_t i = y * w + x;
            int64_t cols[3] = {clampi(x - 1, 0, w - 1), x, clampi(x + 1, 0, w - 1)};
            /* the estimate's 3x3 moments in YCoCg, summed as the box filter sums: a + (b + c) along x, then y */
            float m1[3][3], m2[3][3];
            for (int r = 0; r < 3; r++) {
                float v[3][3];
                for (int q = 0; q < 3; q++) {
                    const int64_t j = rows[r] + cols[q];
                    to_ycocg(s_out[j], s_out[plane + j], s_out[2 * plane + j], v[q]);
                }
                for (int k = 0; k < 3; k++) {
                    m1[r][k] = v[0][k] + (v[1][k] + v[2][k]);
                    m2[r][k] = v[0][k] * v[0][k] + (v[1][k] * v[1][k] + v[2][k] * v[2][k]);
                }
            }
            float high[3], low[3];
            for (int k = 0; k < 3; k++) {
                const float mu = (m1[0][k] + (m1[1][k] + m1[2][k])) / 9.0f;
                const float sq = (m2[0][k] + (m2[1][k] + m2[2][k])) / 9.0f;
                const float sd = sqrtf(fmaxf(sq - mu * mu, 0.0f));
                high[k] = mu + sd;
                low[k] = mu - sd;
            }
            const int ok = valid != NULL && valid[i];
            float est[3], hist[3], mu[3], sv[3], rect[3], cmean[3];
            for (int k = 0; k < 3; k++) {
                est[k] = s_out[k * plane + i];
                sv[k] = s[k * plane + i];
                hist[k] = history != NULL && ok ? history[k * plane + i] : est[k];
                /* 1 / n weights over the frames the history held; no state: the estimate itself */
                mu[k] = mean != NULL ? mean[k * plane + i] + (est[k] - mean[k * plane + i]) / count[i] : est[k];
            }
            clip(hist, high, low, rect);
            clip(mu, high, low, cmean);
            const float len = ok ? fminf(length[i] + 1.0f, lmax) : 0.0f;
            float *f = features + i * channels;
            for (int k = 0; k < 3; k++) {
                const float c = color[k * plane + i];
                f[k] = sv[k];
                f[3 + k] = c / (1.0f + c);
                f[6 + k] = albedo[k * plane + i];
                f[9 + k] = normal[k * plane + i];
                f[12 + k] = hist[k];
                f[15 + k] = rect[k];
                f[18 + k] = fabsf(hist[k] - sv[k]);
                f[28 + k] = mu[k];
                f[31 + k] = fabsf(mu[k] - sv[k]);
                out_history[k * plane + i] = hist[k];
                out_rectified[k * plane + i] = rect[k];
                out_mean[k * plane + i] = mu[k];
                out_clipped_mean[k * plane + i] = cmean[k];
            }
            f[21] = depth[i] / dmax;
            f[22] = ok ? 1.0f : 0.0f;
            f[23] = len / lmax;
            for (int k = 0; k < 4; k++) f[24 + k] = hidden != NULL && ok ? hidden[k * plane + i] : 0.0f;
            f[34] = log1pf(count != NULL ? count[i] : 1.0f) / cnorm;
            out_length[i] = len;
        }
    }
}
