/* libFuzzer target over both kernels (bench/fuzz_native.py builds it with clang,
 * -fsanitize=fuzzer,address,undefined, and runs it).
 *
 * Input: byte 0 picks the kernel (bit 0: EMD / OMP), the array type (bit 1: float32 / float64)
 * and how the values are read (bit 2: raw IEEE bytes, any NaN, inf, huge or subnormal, or small
 * integers, plateaus everywhere); the next bytes the shape and settings; the rest the values
 * (repeated when short). Beyond the sanitizers' checks, each call must return a documented
 * status, stay within its documented outputs, and give row 0 the same bits alone as in its
 * batch; otherwise the target traps.
 */
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "tactile_native.h"

#define CHECK(c) do { if (!(c)) __builtin_trap(); } while (0)

typedef struct {
    const uint8_t *p;
    size_t n, i;
} Bytes;

static uint8_t byte(Bytes *b) { return b->n ? b->p[b->i++ % b->n] : 0; }

/* The next value, as a double (f32: through a float). */
static double value(Bytes *b, int raw, int f32) {
    if (!raw) return (double)(int8_t)byte(b) / 4.0;
    if (f32) {
        uint32_t u = 0;
        for (int k = 0; k < 4; k++) u = (u << 8) | byte(b);
        float f;
        memcpy(&f, &u, sizeof f);
        return (double)f;
    }
    uint64_t u = 0;
    for (int k = 0; k < 8; k++) u = (u << 8) | byte(b);
    double d;
    memcpy(&d, &u, sizeof d);
    return d;
}

/* Fills n values of the caller's type into out (float or double). */
static void fill(void *out, size_t n, Bytes *b, int raw, int f32) {
    for (size_t i = 0; i < n; i++) {
        const double v = value(b, raw, f32);
        if (f32) ((float *)out)[i] = (float)v;
        else ((double *)out)[i] = v;
    }
}

static void fuzz_emd(Bytes *b, int raw, int f32) {
    const int64_t batch = 1 + byte(b) % 3, len = ((int64_t)byte(b) << 1 | (byte(b) & 1)) % 400;
    const int32_t n_imfs = 1 + byte(b) % TACTILE_EMD_MAX_IMFS, n_sifts = 1 + byte(b) % 12;
    const size_t es = f32 ? sizeof(float) : sizeof(double), n = (size_t)(batch * len);
    void *x = malloc(es * n + 1), *imfs = malloc(es * n * (size_t)n_imfs + 1);
    void *res = malloc(es * n + 1), *imfs1 = malloc(es * (size_t)(len * n_imfs) + 1);
    void *res1 = malloc(es * (size_t)len + 1);
    int64_t nv[3], nv1;
    CHECK(x && imfs && res && imfs1 && res1);
    fill(x, n, b, raw, f32);
    int st = f32 ? tactile_emd_f32(x, batch, len, n_imfs, n_sifts, imfs, res, nv)
                 : tactile_emd_f64(x, batch, len, n_imfs, n_sifts, imfs, res, nv);
    CHECK(st == TACTILE_OK || st == TACTILE_ENONFINITE);
    for (int64_t r = 0; r < batch; r++) {
        CHECK(nv[r] >= 0 && nv[r] <= n_imfs);
        /* slots past n_valid are zero */
        for (int64_t t = nv[r] * len; t < n_imfs * len; t++) {
            const size_t i = (size_t)(r * n_imfs * len + t);
            CHECK(f32 ? ((float *)imfs)[i] == 0.0f : ((double *)imfs)[i] == 0.0);
        }
    }
    /* row 0 alone: the same bits */
    st = f32 ? tactile_emd_f32(x, 1, len, n_imfs, n_sifts, imfs1, res1, &nv1)
             : tactile_emd_f64(x, 1, len, n_imfs, n_sifts, imfs1, res1, &nv1);
    CHECK(st == TACTILE_OK || st == TACTILE_ENONFINITE);
    CHECK(nv1 == nv[0]);
    CHECK(memcmp(imfs1, imfs, es * (size_t)(len * n_imfs)) == 0);
    CHECK(memcmp(res1, res, es * (size_t)len) == 0);
    free(x); free(imfs); free(res); free(imfs1); free(res1);
}

static void fuzz_omp(Bytes *b, int raw, int f32) {
    const int64_t rows = 1 + byte(b) % 3, F = 1 + byte(b) % 24, K = 1 + byte(b) % 24;
    const int64_t S = 1 + byte(b) % K;
    const int own_gram = byte(b) & 1;
    const size_t es = f32 ? sizeof(float) : sizeof(double);
    void *x = malloc(es * (size_t)(rows * F)), *d = malloc(es * (size_t)(K * F));
    void *g = malloc(es * (size_t)(K * K)), *codes = malloc(es * (size_t)(rows * K));
    void *codes1 = malloc(es * (size_t)K);
    CHECK(x && d && g && codes && codes1);
    fill(x, (size_t)(rows * F), b, raw, f32);
    fill(d, (size_t)(K * F), b, raw, f32);
    if (own_gram) {
        fill(g, (size_t)(K * K), b, raw, f32);
    } else { /* the dictionary's Gram matrix */
        for (int64_t i = 0; i < K; i++)
            for (int64_t j = 0; j < K; j++) {
                double s = 0.0;
                for (int64_t f = 0; f < F; f++)
                    s += f32 ? (double)((float *)d)[i * F + f] * ((float *)d)[j * F + f]
                             : ((double *)d)[i * F + f] * ((double *)d)[j * F + f];
                if (f32) ((float *)g)[i * K + j] = (float)s;
                else ((double *)g)[i * K + j] = s;
            }
    }
    int st = f32 ? tactile_omp_f32(x, rows, F, d, g, K, S, codes)
                 : tactile_omp_f64(x, rows, F, d, g, K, S, codes);
    CHECK(st == TACTILE_OK || st == TACTILE_ENONFINITE);
    for (int64_t r = 0; r < rows; r++) {
        int64_t nz = 0;
        for (int64_t k = 0; k < K; k++)
            nz += f32 ? ((float *)codes)[r * K + k] != 0.0f : ((double *)codes)[r * K + k] != 0.0;
        CHECK(nz <= S);
    }
    st = f32 ? tactile_omp_f32(x, 1, F, d, g, K, S, codes1)
             : tactile_omp_f64(x, 1, F, d, g, K, S, codes1);
    CHECK(st == TACTILE_OK || st == TACTILE_ENONFINITE);
    CHECK(memcmp(codes1, codes, es * (size_t)K) == 0);
    free(x); free(d); free(g); free(codes); free(codes1);
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
    if (size < 1) return 0;
    Bytes b = {data + 1, size - 1, 0};
    const int kind = data[0] & 1, f32 = (data[0] >> 1) & 1, raw = (data[0] >> 2) & 1;
    if (kind) fuzz_omp(&b, raw, f32);
    else fuzz_emd(&b, raw, f32);
    return 0;
}
