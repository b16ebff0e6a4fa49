/* The hot loops of omp.c, included by it once per instruction set it builds for.
 *
 * omp.c defines, before each inclusion: CORE(name), the name of this copy's function `name`;
 * CORE_ATTR, the copy's target attribute (empty for the baseline); and CORE_VECTOR, the
 * doubles per vector register (2: SSE2 or NEON, 4: AVX2), or leaves it undefined for scalar
 * loops (compilers without GCC's vector extension).
 *
 * Blocks of LANES atoms are kept in registers: enough independent sums to hide the additions'
 * latency. Every copy computes each sum in the same order, lane by lane, with no fused
 * multiply-add (the build passes -ffp-contract=off and no copy enables FMA): the copies' codes
 * are the same bits, on x86 and ARM alike. */

#ifdef CORE_VECTOR
typedef double CORE(vd) __attribute__((vector_size(8 * CORE_VECTOR)));
#define CORE_NV (LANES / CORE_VECTOR)
#define CORE_NC (8 / CORE_VECTOR)

/* acc (width: LANES, 8 or 4) = sum_i rows[i * stride + j] * w[i], i = 0..n-1, in order */
CORE_ATTR static inline void CORE(block_sum)(const double *rows, int64_t stride,
                                             const double *w, int64_t n, double *acc,
                                             int width) {
    CORE(vd) a[CORE_NV], d;
    const int nv = width / CORE_VECTOR;
    for (int v = 0; v < nv; v++) {
        memcpy(&d, rows + CORE_VECTOR * v, sizeof d);
        a[v] = d * w[0];
    }
    for (int64_t i = 1; i < n; i++) {
        const double *r = rows + i * stride;
        const double wi = w[i];
        for (int v = 0; v < nv; v++) {
            memcpy(&d, r + CORE_VECTOR * v, sizeof d);
            a[v] += d * wi;
        }
    }
    memcpy(acc, a, (size_t)width * sizeof(double));
}

/* The correlations of CORR_ROWS rows x (F) with width (8 or 4) atoms: c[r * K + j] =
 * sum_f dt[f * K + j] x_r[f], in order of f (as block_sum sums): each loaded atom serves the
 * four rows. */
CORE_ATTR static inline void CORE(block_corr)(const double *dt, int64_t K, const double *x,
                                              int64_t F, double *c, int width) {
    CORE(vd) a[CORR_ROWS][CORE_NC], d;
    const int nc = width / CORE_VECTOR;
    for (int v = 0; v < nc; v++) {
        memcpy(&d, dt + CORE_VECTOR * v, sizeof d);
        for (int r = 0; r < CORR_ROWS; r++) a[r][v] = d * x[r * F];
    }
    for (int64_t f = 1; f < F; f++) {
        const double *row = dt + f * K;
        const double x0 = x[f], x1 = x[F + f], x2 = x[2 * F + f], x3 = x[3 * F + f];
        for (int v = 0; v < nc; v++) {
            memcpy(&d, row + CORE_VECTOR * v, sizeof d);
            a[0][v] += d * x0;
            a[1][v] += d * x1;
            a[2][v] += d * x2;
            a[3][v] += d * x3;
        }
    }
    for (int r = 0; r < CORR_ROWS; r++) memcpy(c + r * K, a[r], (size_t)width * sizeof(double));
}

/* The start of the first block of 8 atoms that holds an |alpha| equal to best (alpha = best or
 * -best: the same test as fabs(alpha) == best), or of the incomplete block after the last, at
 * most K - 1 (where the scalar scan stops when no atom is equal: all NaN). */
CORE_ATTR static inline int64_t CORE(first_block)(const double *alpha, int64_t K, double best) {
    typedef long long CORE(vl) __attribute__((vector_size(8 * CORE_VECTOR)));
    const CORE(vd) zero = {0.0}, pb = zero + best, nb = zero - best;
    int64_t k0 = 0;
    for (; k0 + 8 <= K; k0 += 8) {
        CORE(vl) hit = {0};
        for (int v = 0; v < CORE_NC; v++) {
            CORE(vd) d;
            memcpy(&d, alpha + k0 + CORE_VECTOR * v, sizeof d);
            hit |= (d == pb) | (d == nb);
        }
        long long any = 0;
        for (int l = 0; l < CORE_VECTOR; l++) any |= hit[l];
        if (any) break;
    }
    return k0 < K ? k0 : K - 1;
}
#undef CORE_NV
#undef CORE_NC
#else
CORE_ATTR static int64_t CORE(first_block)(const double *alpha, int64_t K, double best) {
    int64_t k0 = 0;
    for (; k0 + 8 <= K; k0 += 8) {
        int hit = 0;
        for (int j = 0; j < 8; j++) hit |= fabs(alpha[k0 + j]) == best;
        if (hit) break;
    }
    return k0 < K ? k0 : K - 1;
}
CORE_ATTR static void CORE(block_sum)(const double *rows, int64_t stride, const double *w,
                                      int64_t n, double *acc, int width) {
    for (int j = 0; j < width; j++) acc[j] = rows[j] * w[0];
    for (int64_t i = 1; i < n; i++)
        for (int j = 0; j < width; j++) acc[j] += rows[i * stride + j] * w[i];
}
#endif

/* alpha = cov - G[:, chosen] gamma for n chosen atoms whose Gram rows are grow (n, K): each
 * atom's sum runs over the chosen atoms in order. Returns the largest |alpha|. */
CORE_ATTR static double CORE(residual)(const double *cov, const double *grow,
                                       const double *gamma, int64_t n, int64_t K,
                                       double *alpha) {
    double m[LANES] = {0.0}, acc[LANES];
    int64_t k0 = 0;
#define CORE_RESIDUAL_BLOCK(width)                                                              \
    do {                                                                                       \
        CORE(block_sum)(grow + k0, K, gamma, n, acc, width);                                   \
        for (int j = 0; j < (width); j++) {                                                    \
            const double a = cov[k0 + j] - acc[j];                                             \
            alpha[k0 + j] = a;                                                                 \
            m[j] = fabs(a) > m[j] ? fabs(a) : m[j];                                            \
        }                                                                                      \
        k0 += (width);                                                                         \
    } while (0)
    while (k0 + LANES <= K) CORE_RESIDUAL_BLOCK(LANES); /* blocks of LANES, then 16, 8, 4 */
    if (LANES > 16 && k0 + 16 <= K) CORE_RESIDUAL_BLOCK(16);
    if (k0 + 8 <= K) CORE_RESIDUAL_BLOCK(8);
    if (k0 + 4 <= K) CORE_RESIDUAL_BLOCK(4);
#undef CORE_RESIDUAL_BLOCK
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
CORE_ATTR static double CORE(largest_abs)(const double *alpha, int64_t K) {
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
CORE_ATTR static int64_t CORE(atom_of)(const double *alpha, const int64_t *pos, int64_t K, double best) {
    int64_t lam = CORE(first_block)(alpha, K, best); /* then the atom in that block */
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
CORE_ATTR static void CORE(omp_row)(const double *cov, const void *gram, int f32, int64_t K, int64_t S,
                    double eps, Work *w, double *code) {
    double *alpha = w->alpha, *L = w->L, *Lt = w->Lt, *inv = w->inv, *gamma = w->gamma, *z = w->z, *xy = w->xy;
    double *v = w->wrow, *grow = w->grow;
    int64_t *chosen = w->chosen, *pos = w->pos, *perm = w->perm, n_active = 0;
    for (int64_t k = 0; k < K; k++) {
        pos[k] = perm[k] = k;
        alpha[k] = cov[k];
    }
    double best = CORE(largest_abs)(alpha, K);
    for (;;) {
        const int64_t lam = CORE(atom_of)(alpha, pos, K, best);
        if (pos[lam] < n_active || alpha[lam] * alpha[lam] < eps) break; /* chosen, or small */
        const double glam = f32 ? (double)((const float *)gram)[lam * K + lam]
                                : ((const double *)gram)[lam * K + lam];
        if (n_active > 0) {
            /* new Cholesky row: solve L v = G[chosen, lam] (forward substitution) */
            double vv = 0.0;
            for (int64_t i = 0; i < n_active; i++) v[i] = grow[i * K + lam];
            /* column by column, a vector update each, two columns a pass (the same operations
             * on each entry, in the same order, as one column a pass) */
            int64_t i = 0;
            for (; i + 1 < n_active; i += 2) {
                const double *lt = Lt + i * S, *lu = lt + S;
                const double vi = v[i] * inv[i];
                const double vu = (v[i + 1] - lt[i + 1] * vi) * inv[i + 1];
                v[i] = vi;
                v[i + 1] = vu;
                vv += vi * vi;
                vv += vu * vu;
                for (int64_t k = i + 2; k < n_active; k++) v[k] = (v[k] - lt[k] * vi) - lu[k] * vu;
            }
            if (i < n_active) {
                v[i] *= inv[i];
                vv += v[i] * v[i];
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
        /* row by row of L, a vector update each, two rows a pass (as the forward sweep) */
        int64_t j = n_active - 1;
        for (; j >= 1; j -= 2) {
            const double *lj = L + j * S, *lk = lj - S;
            const double gj = gamma[j] * inv[j];
            const double gk = (gamma[j - 1] - lj[j - 1] * gj) * inv[j - 1];
            gamma[j] = gj;
            gamma[j - 1] = gk;
            for (int64_t i = 0; i < j - 1; i++) gamma[i] = (gamma[i] - lj[i] * gj) - lk[i] * gk;
        }
        if (j == 0) gamma[0] *= inv[0];
        if (n_active == S) break; /* the last atom: no residual is needed */
        /* residual correlations cov - G[:, chosen] gamma, summed in the order the atoms were
         * chosen along their Gram rows (G is symmetric) */
        best = CORE(residual)(cov, grow, gamma, n_active, K, alpha);
    }
    memset(code, 0, (size_t)K * sizeof(double));
    for (int64_t i = 0; i < n_active; i++) code[chosen[i]] = gamma[i];
}

/* cov (nb, K): the correlations of the nb rows xr (nb, F) with every atom, from the
 * transposed dictionary dt (F, K): each sum runs over the features in order (the same for a
 * row in any block), LANES atoms at a time in registers. */
CORE_ATTR static void CORE(correlations)(const double *dt, const double *xr, int64_t nb, int64_t F,
                         int64_t K, double *cov) {
    int64_t b = 0;
#ifdef CORE_VECTOR
    for (; b + CORR_ROWS <= nb && K >= 8; b += CORR_ROWS) {
        int64_t k0 = 0;
        for (; k0 + 8 <= K; k0 += 8)
            CORE(block_corr)(dt + k0, K, xr + b * F, F, cov + b * K + k0, 8);
        if (k0 + 4 <= K) {
            CORE(block_corr)(dt + k0, K, xr + b * F, F, cov + b * K + k0, 4);
            k0 += 4;
        }
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
        for (; k0 + LANES <= K; k0 += LANES) CORE(block_sum)(dt + k0, K, x, F, c + k0, LANES);
        if (LANES > 16 && k0 + 16 <= K) {
            CORE(block_sum)(dt + k0, K, x, F, c + k0, 16);
            k0 += 16;
        }
        if (k0 + 8 <= K) {
            CORE(block_sum)(dt + k0, K, x, F, c + k0, 8);
            k0 += 8;
        }
        if (k0 + 4 <= K) {
            CORE(block_sum)(dt + k0, K, x, F, c + k0, 4);
            k0 += 4;
        }
        for (; k0 < K; k0++) {
            double a = dt[k0] * x[0];
            for (int64_t f = 1; f < F; f++) a += dt[f * K + k0] * x[f];
            c[k0] = a;
        }
    }
}
