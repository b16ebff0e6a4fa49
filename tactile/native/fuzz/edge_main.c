/* Edge inputs for the native kernels, run under AddressSanitizer, UBSan and LeakSanitizer by
 * tests/test_native.py: every status is the documented one, nothing reads or writes out of
 * bounds, nothing leaks. Prints "edge cases passed: N" last and exits 0, or names the failure.
 */
#include <float.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "tactile_native.h"

static int passed, failed;

static void expect(int ok, const char *what, long arg) {
    if (ok) { passed++; return; }
    failed++;
    printf("FAILED: %s (%ld)\n", what, arg);
}

/* Fills x (n) with one of the edge patterns. */
static void pattern(double *x, long n, int kind, unsigned *seed) {
    for (long t = 0; t < n; t++) {
        *seed = *seed * 1103515245u + 12345u;
        const double u = (double)(*seed >> 8) / 16777216.0 - 0.5;
        switch (kind) {
        case 0: x[t] = u; break;                                  /* noise */
        case 1: x[t] = 3.0; break;                                /* constant */
        case 2: x[t] = floor(u * 4.0); break;                     /* quantised, plateaus */
        case 3: x[t] = u * 1e300; break;                          /* huge */
        case 4: x[t] = u * 1e-300; break;                         /* tiny */
        case 5: x[t] = u * DBL_MAX; break;                        /* overflowing differences */
        case 6: x[t] = (t % 7 == 3) ? NAN : u; break;             /* NaN */
        case 7: x[t] = (t == n / 2) ? -INFINITY : u; break;       /* inf */
        case 8: x[t] = (double)t; break;                          /* monotonic */
        case 9: x[t] = (t % 2) ? 1.0 : -1.0; break;               /* alternating */
        case 10: x[t] = (t % 3 == 0) ? 1.0 : 0.0; break;          /* ties everywhere */
        default: x[t] = 5e-324 * (double)(t % 3); break;          /* subnormal */
        }
    }
}

static void emd_cases(void) {
    /* up to the BioTac's 1,100 and 2,200 samples (0.5 and 1 s at 2.2 kHz), there with every
     * IMF the kernel allows */
    static const long lengths[] = {0, 1, 2, 3, 4, 5, 7, 50, 301, 1100, 2200};
    unsigned seed = 1;
    for (int kind = 0; kind < 12; kind++) {
        for (size_t li = 0; li < sizeof lengths / sizeof *lengths; li++) {
            const long n = lengths[li], batch = 3, k = n > 1000 ? TACTILE_EMD_MAX_IMFS : 5;
            double *x = malloc(sizeof(double) * (size_t)(batch * n + 1));
            float *xf = malloc(sizeof(float) * (size_t)(batch * n + 1));
            double *imfs = malloc(sizeof(double) * (size_t)(batch * k * n + 1));
            double *res = malloc(sizeof(double) * (size_t)(batch * n + 1));
            float *imfs_f = malloc(sizeof(float) * (size_t)(batch * k * n + 1));
            float *res_f = malloc(sizeof(float) * (size_t)(batch * n + 1));
            int64_t nv[3];
            for (long b = 0; b < batch; b++) pattern(x + b * n, n, b == 1 ? kind : 0, &seed);
            const int too_big = kind == 3 || kind == 5; /* beyond float's range */
            for (long i = 0; i < batch * n; i++) xf[i] = (float)(too_big ? 0.0 : x[i]);
            const int nonfinite = (kind == 6 && n > 3) || (kind == 7 && n > 0);
            int st = tactile_emd_f64(x, batch, n, (int32_t)k, 6, imfs, res, nv);
            expect(st == (nonfinite ? TACTILE_ENONFINITE : TACTILE_OK), "emd_f64 status", kind);
            for (long b = 0; b < batch; b++)
                expect(nv[b] >= 0 && nv[b] <= k, "n_valid range", kind);
            if (n < 3) expect(nv[0] == 0 && nv[1] == 0, "short rows have no IMFs", n);
            st = tactile_emd_f32(xf, batch, n, (int32_t)k, 3, imfs_f, res_f, nv);
            expect(st == (nonfinite ? TACTILE_ENONFINITE : TACTILE_OK), "emd_f32 status", kind);
            free(x); free(xf); free(imfs); free(res); free(imfs_f); free(res_f);
        }
    }
    double x[8] = {0}, out[64];
    int64_t nv[2];
    expect(tactile_emd_f64(NULL, 1, 8, 4, 10, out, out, nv) == TACTILE_EINVAL, "null x", 0);
    expect(tactile_emd_f64(x, 1, 8, 0, 10, out, out, nv) == TACTILE_EINVAL, "n_imfs 0", 0);
    expect(tactile_emd_f64(x, 1, 8, 4, 1001, out, out, nv) == TACTILE_EINVAL, "n_sifts", 0);
    expect(tactile_emd_f64(x, -1, 8, 4, 10, out, out, nv) == TACTILE_EINVAL, "batch < 0", 0);
    expect(tactile_emd_f64(x, 1, -8, 4, 10, out, out, nv) == TACTILE_EINVAL, "length < 0", 0);
    expect(tactile_emd_f64(NULL, 0, 8, 4, 10, NULL, NULL, NULL) == TACTILE_OK, "batch 0", 0);
    expect(tactile_emd_f64(x, (int64_t)1 << 60, (int64_t)1 << 60, 4, 10, out, out, nv) ==
           TACTILE_EINVAL, "size overflow", 0);
    expect(tactile_native_abi() == TACTILE_NATIVE_ABI, "abi", 0);
}

/* Every edge pattern through both entry points with K atoms (a multiple of 8 or not: the
 * pursuit's vector blocks end at K or leave a remainder); R rows of F features. */
static void omp_patterns(int K) {
    enum { KMAX = 16, F = 8, R = 4 };
    double d[KMAX * F], g[KMAX * KMAX], x[R * F], codes[R * KMAX];
    float df[KMAX * F], gf[KMAX * KMAX], xf[R * F], cf[R * KMAX];
    unsigned seed = 7;
    for (int kind = 0; kind < 12; kind++) {
        pattern(d, K * F, kind == 6 || kind == 7 ? 0 : kind, &seed);
        for (int i = 0; i < K; i++)
            for (int j = 0; j < K; j++) {
                double s = 0.0;
                for (int f = 0; f < F; f++) s += d[i * F + f] * d[j * F + f];
                g[i * K + j] = s;
            }
        pattern(x, R * F, kind, &seed);
        for (int i = 0; i < K * F; i++) df[i] = (float)(kind == 3 || kind == 5 ? 1.0 : d[i]);
        for (int i = 0; i < K * K; i++) gf[i] = (float)(kind == 3 || kind == 5 ? 1.0 : g[i]);
        for (int i = 0; i < R * F; i++) xf[i] = (float)(kind == 3 || kind == 5 ? 1.0 : x[i]);
        for (int s = 1; s <= K; s += 5) {
            int st = tactile_omp_f64(x, R, F, d, g, K, s, codes);
            expect(st == TACTILE_OK || st == TACTILE_ENONFINITE, "omp_f64 status", kind);
            for (int r = 0; r < R; r++) {
                int nz = 0;
                for (int k = 0; k < K; k++) nz += codes[r * K + k] != 0.0;
                expect(nz <= s, "omp non-zeros", kind);
            }
            st = tactile_omp_f32(xf, R, F, df, gf, K, s, cf);
            expect(st == TACTILE_OK || st == TACTILE_ENONFINITE, "omp_f32 status", kind);
        }
    }
}

static void omp_cases(void) {
    enum { K = 12, F = 8, R = 4 };
    double d[K * F], g[K * K], x[R * F], codes[R * K];
    float df[K * F], gf[K * K], xf[R * F], cf[R * K];
    omp_patterns(12);
    omp_patterns(16);
    { /* correlations that overflow to inf, then residuals all NaN (inf - inf, 0 x inf): no
       * atom's |alpha| equals the largest (0), with 16 atoms (no remainder block) */
        enum { K16 = 16 };
        double d16[K16 * F], g16[K16 * K16], x16[F], c16[K16];
        for (int i = 0; i < K16 * F; i++) d16[i] = 1e308;
        for (int i = 0; i < K16 * K16; i++) g16[i] = i % (K16 + 1) == 0;
        for (int i = 0; i < F; i++) x16[i] = 1.0;
        expect(tactile_omp_f64(x16, 1, F, d16, g16, K16, 3, c16) == TACTILE_OK, "NaN residuals", 0);
        /* the first atom of the tie of infinities, then the last (the scan found no equal) */
        expect(c16[0] != 0.0 && c16[15] != 0.0, "NaN residuals: atoms 0 and 15", 0);
    }
    unsigned seed = 7;
    pattern(d, K * F, 0, &seed);
    for (int i = 0; i < K; i++)
        for (int j = 0; j < K; j++) {
            double s = 0.0;
            for (int f = 0; f < F; f++) s += d[i * F + f] * d[j * F + f];
            g[i * K + j] = s;
        }
    pattern(x, R * F, 0, &seed);
    for (int i = 0; i < R * F; i++) xf[i] = (float)x[i];
    expect(tactile_omp_f64(x, R, F, d, g, K, 0, codes) == TACTILE_EINVAL, "n_nonzero 0", 0);
    expect(tactile_omp_f64(x, R, F, d, g, K, K + 1, codes) == TACTILE_EINVAL, "n_nonzero > K", 0);
    expect(tactile_omp_f64(NULL, R, F, d, g, K, 2, codes) == TACTILE_EINVAL, "null x", 0);
    expect(tactile_omp_f64(NULL, 0, F, NULL, NULL, K, 2, NULL) == TACTILE_OK, "rows 0", 0);
    g[5] = NAN;
    expect(tactile_omp_f64(x, R, F, d, g, K, 2, codes) == TACTILE_ENONFINITE, "NaN gram", 0);
    g[5] = 0.0;
    d[K * F - 1] = -INFINITY;
    expect(tactile_omp_f64(x, R, F, d, g, K, 2, codes) == TACTILE_ENONFINITE, "inf dictionary",
           0);
    int zero = 1;
    for (int i = 0; i < R * K; i++) zero &= codes[i] == 0.0;
    expect(zero, "inf dictionary: zero codes", 0);
    for (int i = 0; i < K * F; i++) df[i] = 0.5f;
    for (int i = 0; i < K * K; i++) gf[i] = 0.25f * F;
    gf[K * K - 1] = INFINITY;
    expect(tactile_omp_f32(xf, R, F, df, gf, K, 2, cf) == TACTILE_ENONFINITE, "inf gram f32", 0);
    gf[K * K - 1] = 0.25f * F;
    df[0] = NAN;
    expect(tactile_omp_f32(xf, R, F, df, gf, K, 2, cf) == TACTILE_ENONFINITE, "NaN dictionary f32",
           0);
    df[0] = 0.5f;
    expect(tactile_omp_f32(xf, R, F, df, gf, K, 2, cf) == TACTILE_OK, "finite f32", 0);
}

int main(void) {
    emd_cases();
    omp_cases();
    printf("edge cases passed: %d, failed: %d\n", passed, failed);
    return failed != 0;
}
