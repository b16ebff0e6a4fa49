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
    double *alpha, *L, *gamma, *xy, *wrow, *grow; /* (K), (S*S), (S), (S), (S), (S*K) */
    int64_t *chosen, *pos, *perm; /* (S) the atoms in the order chosen; (K) each atom's working
                                   * position; (K) the atom at each working position */
} Work;

/* Atoms a block of the loops below keeps in registers. */
#define LANES 8

/* alpha = cov - G[:, chosen] gamma for n chosen atoms whose Gram rows are grow (n, K): each
 * atom's sum runs over the chosen atoms in order, LANES atoms at a time in registers. */
static void residual(const double *cov, const double *grow, const double *gamma, int64_t n,
                     int64_t K, double *alpha) {
    int64_t k0 = 0;
    for (; k0 + LANES <= K; k0 += LANES) {
        double acc[LANES];
        for (int j = 0; j < LANES; j++) acc[j] = grow[k0 + j] * gamma[0];
        for (int64_t i = 1; i < n; i++) {
            const double *row = grow + i * K + k0, gi = gamma[i];
            for (int j = 0; j < LANES; j++) acc[j] += row[j] * gi;
        }
        for (int j = 0; j < LANES; j++) alpha[k0 + j] = cov[k0 + j] - acc[j];
    }
    for (; k0 < K; k0++) {
        double acc = grow[k0] * gamma[0];
        for (int64_t i = 1; i < n; i++) acc += grow[i * K + k0] * gamma[i];
        alpha[k0] = cov[k0] - acc;
    }
}

/* The atom of largest |alpha|, the first in working order (pos) among equals: scikit-learn's
 * argmax over its working order. Four lanes each keep their largest and its first atom (one
 * running maximum would wait on every comparison) and note a tie with it; ties across or
 * within lanes (rare: duplicate atoms, an all-zero row) are settled by a second scan. */
static int64_t largest(const double *alpha, const int64_t *pos, int64_t K) {
    double m[4] = {-1.0, -1.0, -1.0, -1.0};
    int64_t at[4] = {0, 0, 0, 0};
    int tie = 0;
    int64_t k = 0;
    for (; k + 4 <= K; k += 4)
        for (int j = 0; j < 4; j++) {
            const double a = fabs(alpha[k + j]);
            tie |= a == m[j];
            at[j] = a > m[j] ? k + j : at[j];
            m[j] = a > m[j] ? a : m[j];
        }
    for (; k < K; k++) {
        const double a = fabs(alpha[k]);
        tie |= a == m[0];
        at[0] = a > m[0] ? k : at[0];
        m[0] = a > m[0] ? a : m[0];
    }
    int64_t lam = at[0];
    double best = m[0];
    for (int j = 1; j < 4; j++) {
        tie |= m[j] == best;
        if (m[j] > best) {
            best = m[j];
            lam = at[j];
        }
    }
    if (tie)
        for (k = 0; k < K; k++)
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
    double *alpha = w->alpha, *L = w->L, *gamma = w->gamma, *xy = w->xy;
    double *v = w->wrow, *grow = w->grow;
    int64_t *chosen = w->chosen, *pos = w->pos, *perm = w->perm, n_active = 0;
    for (int64_t k = 0; k < K; k++) {
        pos[k] = perm[k] = k;
        alpha[k] = cov[k];
    }
    for (;;) {
        const int64_t lam = largest(alpha, pos, K);
        if (pos[lam] < n_active || alpha[lam] * alpha[lam] < eps) break; /* chosen, or small */
        const double glam = f32 ? (double)((const float *)gram)[lam * K + lam]
                                : ((const double *)gram)[lam * K + lam];
        if (n_active > 0) {
            /* new Cholesky row: solve L v = G[chosen, lam] (forward substitution) */
            double vv = 0.0;
            for (int64_t i = 0; i < n_active; i++) {
                double s = grow[i * K + lam];
                for (int64_t j = 0; j < i; j++) s -= L[i * S + j] * v[j];
                v[i] = s / L[i * S + i];
                vv += v[i] * v[i];
            }
            const double lkk = glam - vv;
            if (lkk <= eps) break; /* the chosen atoms are dependent */
            for (int64_t j = 0; j < n_active; j++) L[n_active * S + j] = v[j];
            L[n_active * S + n_active] = sqrt(lkk);
        } else {
            L[0] = sqrt(glam);
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
        /* gamma = (L L^T)^-1 xy[:n_active]: forward, then backward substitution */
        for (int64_t i = 0; i < n_active; i++) {
            double s = xy[i];
            for (int64_t j = 0; j < i; j++) s -= L[i * S + j] * gamma[j];
            gamma[i] = s / L[i * S + i];
        }
        for (int64_t i = n_active - 1; i >= 0; i--) {
            double s = gamma[i];
            for (int64_t j = i + 1; j < n_active; j++) s -= L[j * S + i] * gamma[j];
            gamma[i] = s / L[i * S + i];
        }
        /* residual correlations cov - G[:, chosen] gamma, summed in the order the atoms were
         * chosen along their Gram rows (G is symmetric) */
        residual(cov, grow, gamma, n_active, K, alpha);
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
 * row in any block), two rows and LANES atoms at a time in registers. */
static void correlations(const double *dt, const double *xr, int64_t nb, int64_t F,
                         int64_t K, double *cov) {
    for (int64_t b0 = 0; b0 < nb; b0 += 2) {
        const double *x0 = xr + b0 * F, *x1 = xr + (b0 + 1 < nb ? b0 + 1 : b0) * F;
        int64_t k0 = 0;
        for (; k0 + LANES <= K; k0 += LANES) {
            double a0[LANES], a1[LANES];
            for (int j = 0; j < LANES; j++) {
                a0[j] = dt[k0 + j] * x0[0];
                a1[j] = dt[k0 + j] * x1[0];
            }
            for (int64_t f = 1; f < F; f++) {
                const double *d = dt + f * K + k0, u = x0[f], v = x1[f];
                for (int j = 0; j < LANES; j++) {
                    a0[j] += d[j] * u;
                    a1[j] += d[j] * v;
                }
            }
            for (int j = 0; j < LANES; j++) cov[b0 * K + k0 + j] = a0[j];
            if (b0 + 1 < nb)
                for (int j = 0; j < LANES; j++) cov[(b0 + 1) * K + k0 + j] = a1[j];
        }
        for (; k0 < K; k0++)
            for (int64_t b = b0; b < nb && b < b0 + 2; b++) {
                double a = dt[k0] * xr[b * F];
                for (int64_t f = 1; f < F; f++) a += dt[f * K + k0] * xr[b * F + f];
                cov[b * K + k0] = a;
            }
    }
}

static void work_free(Work *w) {
    free(w->alpha); free(w->L); free(w->gamma); free(w->xy); free(w->wrow);
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
    w.gamma = malloc((size_t)S * sizeof(double));
    w.xy = malloc((size_t)S * sizeof(double));
    w.wrow = malloc((size_t)S * sizeof(double));
    w.grow = malloc((size_t)(S * K) * sizeof(double));
    w.chosen = malloc((size_t)S * sizeof(int64_t));
    w.pos = malloc((size_t)K * sizeof(int64_t));
    w.perm = malloc((size_t)K * sizeof(int64_t));
    int status = TACTILE_OK;
    if (!dt || !xr || !cov || !code || !w.alpha || !w.L || !w.gamma || !w.xy ||
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
