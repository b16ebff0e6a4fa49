/* Orthogonal matching pursuit on a Gram matrix, row by row, as scikit-learn's _gram_omp does it
 * (sklearn/linear_model/_omp.py; what SparseCoder(transform_algorithm="omp") and the toolkit's
 * torch SparseCoder compute):
 *
 * 1. pick the atom whose residual correlation is largest in magnitude (the first such in the
 *    working order, which swaps every chosen atom to the front, as scikit-learn's does);
 * 2. stop early if it is already chosen, if its correlation squared is below epsilon, or
 *    (from the second atom on) if the new Cholesky pivot is at most epsilon;
 * 3. extend the Cholesky factor of the chosen atoms' Gram matrix, solve for their coefficients,
 *    update the residual correlations; repeat until n_nonzero atoms are chosen.
 *
 * All arithmetic is in double; epsilon is that of the caller's array type.
 */
#include <float.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "tactile_native.h"

typedef struct {
    double *alpha, *L, *Lt, *inv, *gamma, *z, *xy, *wrow, *grow; /* (K), (S*S) x 2, (S) x 5, (S*K) */
    int64_t *chosen, *pos, *perm; /* (S) the atoms in the order chosen; (K) each atom's working
                                   * position; (K) the atom at each working position */
} Work;

/* Atoms whose sums a block of the hot loops keeps in registers (16: 8 vector registers of 2
 * doubles; the AVX2 copy below keeps 32, 8 registers of 4, enough independent additions in
 * flight to hide their latency); rows whose correlations are computed together (each row of
 * the transposed dictionary read once for them); rows of a block of 4 in the correlations'
 * register tile. */
#define LANES 16
#define ROW_BLOCK 8
#define CORR_ROWS 4

/* The hot loops (omp_core.h), once for the baseline instruction set and, on x86-64 with GCC
 * or Clang, once more for AVX2 (4 doubles a register instead of 2), picked per call by what
 * the processor supports; TACTILE_NATIVE_SIMD=base in the environment keeps the baseline.
 * Both copies compute the same bits. */
#if defined(__GNUC__) || defined(__clang__)
#define CORE_VECTOR 2
#endif
#define CORE(name) name##_base
#define CORE_ATTR
#include "omp_core.h"
#undef CORE
#undef CORE_ATTR
#undef CORE_VECTOR

#if (defined(__GNUC__) || defined(__clang__)) && defined(__x86_64__)
#define CORE_VECTOR 4
#undef LANES
#define LANES 32
#define CORE(name) name##_avx2
#define CORE_ATTR __attribute__((target("avx2")))
#include "omp_core.h"
#undef CORE
#undef CORE_ATTR
#undef CORE_VECTOR
#define HAVE_AVX2_CORE 1
#else
#define omp_row_avx2 omp_row_base
#define correlations_avx2 correlations_base
#endif

typedef void (*RowFn)(const double *, const void *, int, int64_t, int64_t, double, Work *,
                      double *);
typedef void (*CorrFn)(const double *, const double *, int64_t, int64_t, int64_t, double *);

/* 1 when the AVX2 copy runs: built, supported by this processor, not turned off. */
static int use_avx2(void) {
#ifdef HAVE_AVX2_CORE
    const char *want = getenv("TACTILE_NATIVE_SIMD");
    if (want && strcmp(want, "base") == 0) return 0;
    __builtin_cpu_init();
    return __builtin_cpu_supports("avx2") != 0;
#else
    return 0;
#endif
}

/* 1 when any of the n values is an infinity or NaN (an exponent of all ones). */
static int nonfinite_f32(const float *v, int64_t n) {
    uint32_t bad = 0;
    for (int64_t i = 0; i < n; i++) {
        uint32_t u;
        memcpy(&u, v + i, sizeof u);
        bad |= (uint32_t)((u & 0x7f800000u) == 0x7f800000u);
    }
    return bad != 0;
}
static int nonfinite_f64(const double *v, int64_t n) {
    uint64_t bad = 0;
    for (int64_t i = 0; i < n; i++) {
        uint64_t u;
        memcpy(&u, v + i, sizeof u);
        bad |= (uint64_t)((u & 0x7ff0000000000000u) == 0x7ff0000000000000u);
    }
    return bad != 0;
}

static void work_free(Work *w) {
    free(w->alpha); free(w->L); free(w->Lt); free(w->inv); free(w->z); free(w->gamma); free(w->xy); free(w->wrow);
    free(w->grow); free(w->chosen); free(w->pos); free(w->perm);
}

/* The shared body of both entry points; x, dictionary, gram, codes are float (f32) or double. */
static int omp_batch(const void *x, int f32, int64_t rows, int64_t F, const void *dictionary,
                     const void *gram, int64_t K, int64_t S, void *codes) {
    if (rows < 0 || F < 1 || K < 1 || S < 1 || S > K) return TACTILE_EINVAL;
    if (rows == 0) return TACTILE_OK;
    if (!x || !dictionary || !gram || !codes) return TACTILE_EINVAL;
    const uint64_t cap = (uint64_t)(SIZE_MAX < INT64_MAX ? SIZE_MAX : INT64_MAX) / 16u;
    if ((uint64_t)K > cap / (uint64_t)K || (uint64_t)F > cap / (uint64_t)K ||
        (uint64_t)rows > cap / (uint64_t)(K > F ? K : F))
        return TACTILE_EINVAL;
    const double eps = f32 ? (double)FLT_EPSILON : DBL_EPSILON;
    Work w;
    memset(&w, 0, sizeof w);
    double *dt = malloc((size_t)(K * F) * sizeof(double));
    double *xr = malloc((size_t)(ROW_BLOCK * F) * sizeof(double));
    double *cov = malloc((size_t)(ROW_BLOCK * K) * sizeof(double));
    double *code = malloc((size_t)K * sizeof(double));
    w.alpha = malloc((size_t)K * sizeof(double));
    w.L = malloc((size_t)(S * S) * sizeof(double));
    w.Lt = malloc((size_t)(S * S) * sizeof(double));
    w.z = malloc((size_t)S * sizeof(double));
    w.inv = malloc((size_t)S * sizeof(double));
    w.gamma = malloc((size_t)S * sizeof(double));
    w.xy = malloc((size_t)S * sizeof(double));
    w.wrow = malloc((size_t)S * sizeof(double));
    w.grow = malloc((size_t)(S * K) * sizeof(double));
    w.chosen = malloc((size_t)S * sizeof(int64_t));
    w.pos = malloc((size_t)K * sizeof(int64_t));
    w.perm = malloc((size_t)K * sizeof(int64_t));
    const int avx2 = use_avx2();
    const RowFn row = avx2 ? omp_row_avx2 : omp_row_base;
    const CorrFn corr = avx2 ? correlations_avx2 : correlations_base;
    int status = TACTILE_OK;
    if (!dt || !xr || !cov || !code || !w.alpha || !w.L || !w.Lt || !w.z || !w.inv || !w.gamma || !w.xy ||
        !w.wrow || !w.grow || !w.chosen || !w.pos || !w.perm) {
        status = TACTILE_ENOMEM;
        goto done;
    }
    /* the transposed dictionary; finiteness from the exponent bits (all ones: inf or NaN),
     * an integer test the compiler vectorises */
    int finite;
    if (f32) {
        const float *d = dictionary, *g = gram;
        for (int64_t k = 0; k < K; k++)
            for (int64_t f = 0; f < F; f++) dt[f * K + k] = (double)d[k * F + f];
        finite = !nonfinite_f32(d, K * F) && !nonfinite_f32(g, K * K);
    } else {
        const double *d = dictionary, *g = gram;
        for (int64_t k = 0; k < K; k++)
            for (int64_t f = 0; f < F; f++) dt[f * K + k] = d[k * F + f];
        finite = !nonfinite_f64(d, K * F) && !nonfinite_f64(g, K * K);
    }
    if (!finite) status = TACTILE_ENONFINITE;
    for (int64_t r0 = 0; r0 < rows; r0 += ROW_BLOCK) {
        const int64_t nb = rows - r0 < ROW_BLOCK ? rows - r0 : ROW_BLOCK;
        int ok[ROW_BLOCK];
        for (int64_t b = 0; b < nb; b++) {
            ok[b] = finite;
            for (int64_t f = 0; f < F; f++) {
                const int64_t i = (r0 + b) * F + f;
                xr[b * F + f] = f32 ? (double)((const float *)x)[i] : ((const double *)x)[i];
                ok[b] &= isfinite(xr[b * F + f]) != 0;
            }
        }
        corr(dt, xr, nb, F, K, cov);
        for (int64_t b = 0; b < nb; b++) {
            const int64_t r = r0 + b;
            if (ok[b]) {
                row(cov + b * K, gram, f32, K, S, eps, &w, code);
            } else {
                status = TACTILE_ENONFINITE;
                memset(code, 0, (size_t)K * sizeof(double));
            }
            for (int64_t k = 0; k < K; k++) {
                if (f32) ((float *)codes)[r * K + k] = (float)code[k];
                else ((double *)codes)[r * K + k] = code[k];
            }
        }
    }
done:
    free(dt); free(xr); free(cov); free(code); work_free(&w);
    return status;
}

int tactile_omp_f64(const double *x, int64_t rows, int64_t features, const double *dictionary,
                    const double *gram, int64_t atoms, int64_t n_nonzero, double *codes) {
    return omp_batch(x, 0, rows, features, dictionary, gram, atoms, n_nonzero, codes);
}

int tactile_omp_f32(const float *x, int64_t rows, int64_t features, const float *dictionary,
                    const float *gram, int64_t atoms, int64_t n_nonzero, float *codes) {
    return omp_batch(x, 1, rows, features, dictionary, gram, atoms, n_nonzero, codes);
}
