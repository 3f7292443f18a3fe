/* e^-a for a >= 0 in loops that vectorize (the C library's expf does not); shared by stale.c and tail.c. */
#ifndef EXP_NEGATIVE_H
#define EXP_NEGATIVE_H
#include <stdint.h>

typedef union { float f; int32_t i; } bits32;

/* e^-a for a >= 0 to about 2 ulp (Cephes' expf: -a = n ln 2 + r, |r| <= ln 2 / 2, a polynomial in r times 2^n), in
 * loops that vectorize: the flags keep float traps, so the compiler would not turn a float comparison into a select;
 * the clamp compares bit patterns (ordered as the values are, for a >= 0). 0 past 87, where e^-a leaves float32's
 * normal range (torch gives a denormal there, under 2e-38). */
static inline float exp_negative(float a) {
    const bits32 in = {.f = a}, limit = {.f = 87.0f};
    const int over = in.i > limit.i;
    const bits32 clamped = {.i = over ? limit.i : in.i};
    const int32_t k = (int32_t)(clamped.f * -1.44269504088896341f - 0.5f); /* rounded: truncation of a value <= 0 */
    const float n = (float)k;
    const float r = (-clamped.f - n * 0.693359375f) - n * -2.12194440e-4f;
    float p = 1.9875691500e-4f;
    p = p * r + 1.3981999507e-3f;
    p = p * r + 8.3334519073e-3f;
    p = p * r + 4.1665795894e-2f;
    p = p * r + 1.6666665459e-1f;
    p = p * r + 5.0000001201e-1f;
    p = p * (r * r) + r + 1.0f;
    const bits32 scale = {.i = over ? 0 : (k + 127) << 23}; /* 2^n, n in [-126, 0] */
    return p * scale.f;
}

#endif
