/* The kernels' scratch memory: an allocation that fails is marked in *failed rather than crashing the process. A
 * kernel allocates first, meets its threads at a barrier, skips its work where anything failed and returns nonzero;
 * the caller raises MemoryError (model/ops/native). */
#ifndef SCRATCH_H
#define SCRATCH_H
#include <stdlib.h>

static inline void *scratch_alloc(size_t bytes, int *failed) {
    void *p = malloc(bytes ? bytes : 1);
    if (!p) {
#pragma omp atomic write
        *failed = 1;
    }
    return p;
}

static inline void *scratch_zeroed(size_t count, size_t size, int *failed) {
    void *p = calloc(count ? count : 1, size);
    if (!p) {
#pragma omp atomic write
        *failed = 1;
    }
    return p;
}

#endif
