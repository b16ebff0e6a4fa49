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
    double *xy, *alpha, *beta, *L, *gamma, *wrow; /* (K), (K), (K), (S*S), (S), (S) */
    int64_t *perm;                         /* (K) atom at each working position */
} Work;

/* Gram entry of the atoms at working positions p and q. */
#define G(p, q) gram[perm[(p)] * K + perm[(q)]]

/* Codes of one row from its correlations cov (K) with the atoms; code (K) is written. */
static void omp_row(const double *cov, const double *gram, int64_t K, int64_t S, double eps,
                    Work *w, double *code) {
    double *xy = w->xy, *alpha = w->alpha, *beta = w->beta, *L = w->L, *gamma = w->gamma;
    double *v = w->wrow;
    int64_t *perm = w->perm, n_active = 0;
    for (int64_t p = 0; p < K; p++) {
        perm[p] = p;
        xy[p] = alpha[p] = cov[p];
    }
    for (;;) {
        int64_t lam = 0;
        for (int64_t p = 1; p < K; p++)
            if (fabs(alpha[p]) > fabs(alpha[lam])) lam = p;
        if (lam < n_active || alpha[lam] * alpha[lam] < eps) break; /* chosen, or too small */
        if (n_active > 0) {
            /* new Cholesky row: solve L v = G[lam, active] (forward substitution) */
            double vv = 0.0;
            for (int64_t i = 0; i < n_active; i++) {
                double s = G(lam, i);
                for (int64_t j = 0; j < i; j++) s -= L[i * S + j] * v[j];
                v[i] = s / L[i * S + i];
                vv += v[i] * v[i];
            }
            const double lkk = G(lam, lam) - vv;
            if (lkk <= eps) break; /* the chosen atoms are dependent */
            for (int64_t j = 0; j < n_active; j++) L[n_active * S + j] = v[j];
            L[n_active * S + n_active] = sqrt(lkk);
        } else {
            L[0] = sqrt(G(lam, lam));
        }
        /* swap the atom into working position n_active */
        int64_t ti = perm[n_active]; perm[n_active] = perm[lam]; perm[lam] = ti;
        double td = xy[n_active]; xy[n_active] = xy[lam]; xy[lam] = td;
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
        /* residual correlations cov - G[:, chosen] gamma, summed in atom order along the
         * chosen atoms' Gram rows (contiguous; G is symmetric), then put in working order */
        for (int64_t k = 0; k < K; k++) beta[k] = 0.0;
        for (int64_t i = 0; i < n_active; i++) {
            const double *row = gram + perm[i] * K, gi = gamma[i];
            for (int64_t k = 0; k < K; k++) beta[k] += row[k] * gi;
        }
        for (int64_t p = 0; p < K; p++) alpha[p] = xy[p] - beta[perm[p]];
        if (n_active == S) break;
    }
    memset(code, 0, (size_t)K * sizeof(double));
    for (int64_t i = 0; i < n_active; i++) code[perm[i]] = gamma[i];
}

/* Rows whose correlations are computed together: each atom's row of the dictionary is read
 * once for the block (the dictionary, not the arithmetic, bounded the time). */
#define ROW_BLOCK 4

/* cov (nb, K): the correlations of the nb rows xr (nb, F) with every atom, D x. Each sum is
 * four partial sums (the additions' latency, not their count, bounds a single running sum)
 * added pairwise: a BLAS-like order, not numpy's exact bits, and the same for a row in any
 * block. */
static void correlations(const double *dict, const double *xr, int64_t nb, int64_t F,
                         int64_t K, double *cov) {
    for (int64_t k = 0; k < K; k++) {
        const double *dk = dict + k * F;
        double s[ROW_BLOCK][4] = {{0.0}};
        int64_t f = 0;
        for (; f + 4 <= F; f += 4) {
            for (int64_t b = 0; b < nb; b++) {
                const double *xb = xr + b * F;
                s[b][0] += dk[f] * xb[f];
                s[b][1] += dk[f + 1] * xb[f + 1];
                s[b][2] += dk[f + 2] * xb[f + 2];
                s[b][3] += dk[f + 3] * xb[f + 3];
            }
        }
        for (; f < F; f++)
            for (int64_t b = 0; b < nb; b++) s[b][0] += dk[f] * xr[b * F + f];
        for (int64_t b = 0; b < nb; b++)
            cov[b * K + k] = (s[b][0] + s[b][1]) + (s[b][2] + s[b][3]);
    }
}

static void work_free(Work *w) {
    free(w->xy); free(w->alpha); free(w->beta); free(w->L); free(w->gamma); free(w->wrow);
    free(w->perm);
}

/* The shared body of both entry points; x, dictionary, gram, codes are float (f32) or double. */
static int omp_batch(const void *x, int f32, int64_t rows, int64_t F, const void *dictionary,
                     const void *gram_in, int64_t K, int64_t S, void *codes) {
    if (rows < 0 || F < 1 || K < 1 || S < 1 || S > K) return TACTILE_EINVAL;
    if (rows == 0) return TACTILE_OK;
    if (!x || !dictionary || !gram_in || !codes) return TACTILE_EINVAL;
    const uint64_t cap = (uint64_t)(SIZE_MAX < INT64_MAX ? SIZE_MAX : INT64_MAX) / 16u;
    if ((uint64_t)K > cap / (uint64_t)K || (uint64_t)F > cap / (uint64_t)K ||
        (uint64_t)rows > cap / (uint64_t)(K > F ? K : F))
        return TACTILE_EINVAL;
    const double eps = f32 ? (double)FLT_EPSILON : DBL_EPSILON;
    Work w;
    memset(&w, 0, sizeof w);
    double *dict = malloc((size_t)(K * F) * sizeof(double));
    double *gram = malloc((size_t)(K * K) * sizeof(double));
    double *xr = malloc((size_t)(ROW_BLOCK * F) * sizeof(double));
    double *cov = malloc((size_t)(ROW_BLOCK * K) * sizeof(double));
    double *code = malloc((size_t)K * sizeof(double));
    w.xy = malloc((size_t)K * sizeof(double));
    w.alpha = malloc((size_t)K * sizeof(double));
    w.beta = malloc((size_t)K * sizeof(double));
    w.L = malloc((size_t)(S * S) * sizeof(double));
    w.gamma = malloc((size_t)S * sizeof(double));
    w.wrow = malloc((size_t)S * sizeof(double));
    w.perm = malloc((size_t)K * sizeof(int64_t));
    int status = TACTILE_OK;
    if (!dict || !gram || !xr || !cov || !code || !w.xy || !w.alpha || !w.beta || !w.L ||
        !w.gamma || !w.wrow || !w.perm) {
        status = TACTILE_ENOMEM;
        goto done;
    }
    int finite = 1;
    for (int64_t i = 0; i < K * F; i++) {
        dict[i] = f32 ? (double)((const float *)dictionary)[i] : ((const double *)dictionary)[i];
        finite &= isfinite(dict[i]) != 0;
    }
    for (int64_t i = 0; i < K * K; i++) {
        gram[i] = f32 ? (double)((const float *)gram_in)[i] : ((const double *)gram_in)[i];
        finite &= isfinite(gram[i]) != 0;
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
        correlations(dict, xr, nb, F, K, cov);
        for (int64_t b = 0; b < nb; b++) {
            const int64_t r = r0 + b;
            if (ok[b]) {
                omp_row(cov + b * K, gram, K, S, eps, &w, code);
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
    free(dict); free(gram); free(xr); free(cov); free(code); work_free(&w);
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
