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

/* Atoms a block of the loops below keeps in registers: enough independent sums to hide the
 * additions' latency. With GCC or Clang the blocks are written as vectors of 2 doubles (one
 * SSE2 or NEON register); the arithmetic is the same, lane by lane, as the scalar loops other
 * compilers get: each sum in the same order, no fused multiply-add. */
#define LANES 16

#if defined(__GNUC__) || defined(__clang__)
typedef double v2d __attribute__((vector_size(16)));
#define NV (LANES / 2)
static inline v2d load2(const double *p) {
    v2d v;
    memcpy(&v, p, sizeof v);
    return v;
}
static inline void store2(double *p, v2d v) { memcpy(p, &v, sizeof v); }

/* acc (LANES) = sum_i rows[i * stride + j] * w[i], i = 0..n-1, in order */
static inline void block_sum(const double *rows, int64_t stride, const double *w, int64_t n,
                             double *acc) {
    v2d a[NV];
    for (int v = 0; v < NV; v++) a[v] = load2(rows + 2 * v) * w[0];
    for (int64_t i = 1; i < n; i++) {
        const double *r = rows + i * stride;
        const double wi = w[i];
        for (int v = 0; v < NV; v++) a[v] += load2(r + 2 * v) * wi;
    }
    for (int v = 0; v < NV; v++) store2(acc + 2 * v, a[v]);
}
/* The correlations of 4 rows x (F) with 8 atoms: c[r * K + j] = sum_f dt[f * K + j] x_r[f],
 * in order of f (as block_sum sums): each loaded pair of atoms serves four rows. */
#define CORR_ROWS 4
static inline void block_corr(const double *dt, int64_t K, const double *x, int64_t F,
                              double *c) {
    v2d a[CORR_ROWS][4];
    for (int v = 0; v < 4; v++) {
        const v2d d = load2(dt + 2 * v);
        for (int r = 0; r < CORR_ROWS; r++) a[r][v] = d * x[r * F];
    }
    for (int64_t f = 1; f < F; f++) {
        const double *row = dt + f * K;
        const double x0 = x[f], x1 = x[F + f], x2 = x[2 * F + f], x3 = x[3 * F + f];
        for (int v = 0; v < 4; v++) {
            const v2d d = load2(row + 2 * v);
            a[0][v] += d * x0;
            a[1][v] += d * x1;
            a[2][v] += d * x2;
            a[3][v] += d * x3;
        }
    }
    for (int r = 0; r < CORR_ROWS; r++)
        for (int v = 0; v < 4; v++) store2(c + r * K + 2 * v, a[r][v]);
}
#define HAVE_BLOCK_CORR 1
#else
static void block_sum(const double *rows, int64_t stride, const double *w, int64_t n,
                      double *acc) {
    for (int j = 0; j < LANES; j++) acc[j] = rows[j] * w[0];
    for (int64_t i = 1; i < n; i++)
        for (int j = 0; j < LANES; j++) acc[j] += rows[i * stride + j] * w[i];
}
#endif

/* alpha = cov - G[:, chosen] gamma for n chosen atoms whose Gram rows are grow (n, K): each
 * atom's sum runs over the chosen atoms in order. Returns the largest |alpha|. */
static double residual(const double *cov, const double *grow, const double *gamma, int64_t n,
                       int64_t K, double *alpha) {
    double m[LANES] = {0.0}, acc[LANES];
    int64_t k0 = 0;
    for (; k0 + LANES <= K; k0 += LANES) {
        block_sum(grow + k0, K, gamma, n, acc);
        for (int j = 0; j < LANES; j++) {
            const double a = cov[k0 + j] - acc[j];
            alpha[k0 + j] = a;
            m[j] = fabs(a) > m[j] ? fabs(a) : m[j];
        }
    }
    for (; k0 < K; k0++) {
        double a = grow[k0] * gamma[0];
        for (int64_t i = 1; i < n; i++) a += grow[i * K + k0] * gamma[i];
        alpha[k0] = cov[k0] - a;
        m[0] = fabs(alpha[k0]) > m[0] ? fabs(alpha[k0]) : m[0];
    }
    double best = m[0];
    for (int j = 1; j < LANES; j++) best = m[j] > best ? m[j] : best;
    return best;
}

/* The largest |alpha| of the initial correlations (LANES running maxima). */
static double largest_abs(const double *alpha, int64_t K) {
    double m[LANES] = {0.0};
    int64_t k0 = 0;
    for (; k0 + LANES <= K; k0 += LANES)
        for (int j = 0; j < LANES; j++)
            m[j] = fabs(alpha[k0 + j]) > m[j] ? fabs(alpha[k0 + j]) : m[j];
    for (; k0 < K; k0++) m[0] = fabs(alpha[k0]) > m[0] ? fabs(alpha[k0]) : m[0];
    double best = m[0];
    for (int j = 1; j < LANES; j++) best = m[j] > best ? m[j] : best;
    return best;
}

/* The atom whose |alpha| is best, the first in working order (pos) among equals: scikit-
 * learn's argmax over its working order. Equals are rare (duplicate atoms, an all-zero row):
 * the scan stops at the first, then counts the others before settling them by pos. */
static int64_t atom_of(const double *alpha, const int64_t *pos, int64_t K, double best) {
    int64_t lam = 0;
    while (lam < K - 1 && fabs(alpha[lam]) != best) lam++;
    int64_t more = 0;
    for (int64_t k = lam + 1; k < K; k++) more += fabs(alpha[k]) == best;
    if (more)
        for (int64_t k = lam + 1; k < K; k++)
            if (fabs(alpha[k]) == best && pos[k] < pos[lam]) lam = k;
    return lam;
}

/* Codes of one row from its correlations cov (K) with the atoms; code (K) is written.
 *
 * The arrays are kept in atom order (so that every loop over the atoms is a plain vector
 * loop); scikit-learn's working order, which swaps each chosen atom to the front, survives
 * only where it decides anything: among atoms of equal largest |correlation| it picks the one
 * first in working order (pos). grow holds the chosen atoms' Gram rows in double. */
static void omp_row(const double *cov, const void *gram, int f32, int64_t K, int64_t S,
                    double eps, Work *w, double *code) {
    double *alpha = w->alpha, *L = w->L, *Lt = w->Lt, *inv = w->inv, *gamma = w->gamma, *z = w->z, *xy = w->xy;
    double *v = w->wrow, *grow = w->grow;
    int64_t *chosen = w->chosen, *pos = w->pos, *perm = w->perm, n_active = 0;
    for (int64_t k = 0; k < K; k++) {
        pos[k] = perm[k] = k;
        alpha[k] = cov[k];
    }
    double best = largest_abs(alpha, K);
    for (;;) {
        const int64_t lam = atom_of(alpha, pos, K, best);
        if (pos[lam] < n_active || alpha[lam] * alpha[lam] < eps) break; /* chosen, or small */
        const double glam = f32 ? (double)((const float *)gram)[lam * K + lam]
                                : ((const double *)gram)[lam * K + lam];
        if (n_active > 0) {
            /* new Cholesky row: solve L v = G[chosen, lam] (forward substitution) */
            double vv = 0.0;
            for (int64_t i = 0; i < n_active; i++) v[i] = grow[i * K + lam];
            for (int64_t i = 0; i < n_active; i++) { /* column by column: a vector update */
                const double vi = v[i] * inv[i], *lt = Lt + i * S;
                v[i] = vi;
                vv += vi * vi;
                for (int64_t k = i + 1; k < n_active; k++) v[k] -= lt[k] * vi;
            }
            const double lkk = glam - vv;
            if (lkk <= eps) break; /* the chosen atoms are dependent */
            for (int64_t j = 0; j < n_active; j++) L[n_active * S + j] = v[j];
            L[n_active * S + n_active] = sqrt(lkk);
            inv[n_active] = 1.0 / L[n_active * S + n_active];
        } else {
            L[0] = sqrt(glam);
            inv[0] = 1.0 / L[0];
        }
        /* the atom takes working position n_active; the atom there takes lam's old one */
        const int64_t other = perm[n_active];
        pos[other] = pos[lam];
        perm[pos[lam]] = other;
        pos[lam] = n_active;
        perm[n_active] = lam;
        chosen[n_active] = lam;
        xy[n_active] = cov[lam];
        double *g = grow + n_active * K;
        if (f32) {
            const float *gr = (const float *)gram + lam * K;
            for (int64_t k = 0; k < K; k++) g[k] = (double)gr[k];
        } else {
            memcpy(g, (const double *)gram + lam * K, (size_t)K * sizeof(double));
        }
        n_active++;
        /* gamma = (L L^T)^-1 xy[:n_active]: forward substitution (z = L^-1 xy; only its new
         * entry is new, the others are the same sums as before), then backward substitution
         * (Lt = L^T keeps L's columns contiguous for the forward sweeps) */
        {
            const int64_t i = n_active - 1;
            double s = xy[i];
            for (int64_t j = 0; j < i; j++) s -= L[i * S + j] * z[j];
            z[i] = s * inv[i];
            for (int64_t j = 0; j <= i; j++) Lt[j * S + i] = L[i * S + j];
        }
        for (int64_t i = 0; i < n_active; i++) gamma[i] = z[i];
        for (int64_t j = n_active - 1; j >= 0; j--) { /* row by row of L: a vector update */
            const double gj = gamma[j] * inv[j], *lj = L + j * S;
            gamma[j] = gj;
            for (int64_t i = 0; i < j; i++) gamma[i] -= lj[i] * gj;
        }
        /* residual correlations cov - G[:, chosen] gamma, summed in the order the atoms were
         * chosen along their Gram rows (G is symmetric) */
        best = residual(cov, grow, gamma, n_active, K, alpha);
        if (n_active == S) break;
    }
    memset(code, 0, (size_t)K * sizeof(double));
    for (int64_t i = 0; i < n_active; i++) code[chosen[i]] = gamma[i];
}

/* Rows whose correlations are computed together: each row of the transposed dictionary is
 * read once for the block. */
#define ROW_BLOCK 8

/* cov (nb, K): the correlations of the nb rows xr (nb, F) with every atom, from the
 * transposed dictionary dt (F, K): each sum runs over the features in order (the same for a
 * row in any block), LANES atoms at a time in registers. */
static void correlations(const double *dt, const double *xr, int64_t nb, int64_t F,
                         int64_t K, double *cov) {
    int64_t b = 0;
#ifdef HAVE_BLOCK_CORR
    for (; b + CORR_ROWS <= nb && K >= 8; b += CORR_ROWS) {
        int64_t k0 = 0;
        for (; k0 + 8 <= K; k0 += 8) block_corr(dt + k0, K, xr + b * F, F, cov + b * K + k0);
        for (; k0 < K; k0++)
            for (int64_t r = b; r < b + CORR_ROWS; r++) {
                double a = dt[k0] * xr[r * F];
                for (int64_t f = 1; f < F; f++) a += dt[f * K + k0] * xr[r * F + f];
                cov[r * K + k0] = a;
            }
    }
#endif
    for (; b < nb; b++) {
        const double *x = xr + b * F;
        double *c = cov + b * K;
        int64_t k0 = 0;
        for (; k0 + LANES <= K; k0 += LANES) block_sum(dt + k0, K, x, F, c + k0);
        for (; k0 < K; k0++) {
            double a = dt[k0] * x[0];
            for (int64_t f = 1; f < F; f++) a += dt[f * K + k0] * x[f];
            c[k0] = a;
        }
    }
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
    int status = TACTILE_OK;
    if (!dt || !xr || !cov || !code || !w.alpha || !w.L || !w.Lt || !w.z || !w.inv || !w.gamma || !w.xy ||
        !w.wrow || !w.grow || !w.chosen || !w.pos || !w.perm) {
        status = TACTILE_ENOMEM;
        goto done;
    }
    int finite = 1;
    for (int64_t k = 0; k < K; k++)
        for (int64_t f = 0; f < F; f++) {
            const int64_t i = k * F + f;
            const double d = f32 ? (double)((const float *)dictionary)[i]
                                 : ((const double *)dictionary)[i];
            dt[f * K + k] = d;
            finite &= isfinite(d) != 0;
        }
    for (int64_t i = 0; i < K * K; i++)
        finite &= isfinite(f32 ? (double)((const float *)gram)[i] : ((const double *)gram)[i]) != 0;
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
        correlations(dt, xr, nb, F, K, cov);
        for (int64_t b = 0; b < nb; b++) {
            const int64_t r = r0 + b;
            if (ok[b]) {
                omp_row(cov + b * K, gram, f32, K, S, eps, &w, code);
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
