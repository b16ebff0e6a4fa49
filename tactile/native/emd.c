/* Empirical mode decomposition, one signal at a time, exactly as the reference EMD computes it:
 * PyEMD EMD(FIXE=k, spline_kind='cubic', nbsym=2, extrema_detection='simple') with max_imf
 * slots, and the toolkit's torch module (training/emd). Sections are EMD_SPEC's, as in the
 * torch module (docs/emd.md): §1.2 outer loop, §1.3 sifting, §1.4 extrema, §1.5 boundary,
 * §1.6 spline.
 *
 * All arithmetic is in double. Knots carry half values (h / 2), as the torch module's do: the
 * spline is linear in its values, so the two half envelopes add up to the mean envelope, and
 * huge signals overflow no sooner than the signal itself.
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "tactile_native.h"

#define RANGE_THR 1e-3 /* §1.2: end when max(res) - min(res) is below this (absolute) */
#define POWER_THR 5e-3 /* §1.2: end when sum |res| is below this (absolute) */

/* One envelope's spline: knots, then the arrays of its solve, (N + 8) each. */
typedef struct {
    double *kx, *ky;               /* knot positions, half values */
    double *hk, *sl, *m, *cp, *dp; /* spacings, slopes, M / 6, the Thomas sweep */
    double *c1, *c2, *c3;          /* each piece's power-basis coefficients */
    unsigned char *up;             /* (N) knots at each sample (the pieces that start there) */
    int64_t n;                     /* knots */
} Env;

typedef struct {
    double *h, *acc, *mean;      /* (N) current proto-IMF, sum of IMFs, mean envelope */
    Env env[2];                  /* the upper and the lower envelope */
    int64_t *pmax, *pmin;        /* (N) extremum positions */
} Work;

static int sign_of(double d) { return (d > 0.0) - (d < 0.0); }

/* round(v / 2) for v >= 0, half to even, as np.round and torch.round do. */
static int64_t half_even(int64_t v) { return (v / 2) + ((v & 1) && ((v / 2) & 1)); }

/* §1.4 Extrema, 'simple'. A flat run between non-zero differences j and e (e == j + 1 is the
 * strict case) gives one extremum at round((j + 1 + e) / 2) when their signs differ. Quirks:
 * (1) a run starting at difference 1 is dropped; (2) a run starting at difference 0 takes the
 * last difference as its entry slope (wrap-around); (3) a run reaching the end is dropped. */
static void find_extrema(const double *h, int64_t n, Work *w, int64_t *na, int64_t *nb) {
    int64_t a = 0, b = 0, j = -1, e;
    int sj = 0;
    for (e = 0; e < n - 1; e++) {
        int se = sign_of(h[e + 1] - h[e]);
        if (se == 0) continue;
        if (j < 0) { /* first non-zero difference: quirk 2 when d[0] == 0 */
            int last = sign_of(h[n - 1] - h[n - 2]);
            if (e > 0 && last * se < 0) {
                if (last > 0) w->pmax[a++] = half_even(e);
                else w->pmin[b++] = half_even(e);
            }
        } else if (sj * se < 0 && !(j == 0 && e > 1)) { /* quirk 1: j == 0 with a gap */
            int64_t mid = half_even(j + 1 + e);
            if (sj > 0) w->pmax[a++] = mid;
            else w->pmin[b++] = mid;
        }
        j = e;
        sj = se;
    }
    *na = a;
    *nb = b;
}

/* Up to 3 source samples of one side of one envelope, in PyEMD's order. */
typedef struct {
    int64_t i[3];
    int n;
} Src;

/* src = list[lo:hi] reversed (numpy slice bounds: clamped, empty when hi <= lo). */
static void take_rev(Src *s, const int64_t *list, int64_t len, int64_t lo, int64_t hi) {
    s->n = 0;
    if (lo < 0) lo = 0;
    if (hi > len) hi = len;
    for (int64_t k = hi - 1; k >= lo && s->n < 3; k--) s->i[s->n++] = list[k];
}

static void push(Src *s, int64_t i) {
    if (s->n < 3) s->i[s->n++] = i;
}

/* An empty source list is replaced by the whole list (one element whenever it happens). */
static void or_whole(Src *s, const int64_t *list, int64_t len) {
    if (s->n == 0 && len > 0) {
        s->i[0] = list[0];
        s->n = 1;
    }
}

/* §1.5 Boundary: the mirrored sources and symmetry points of both envelopes at both ends
 * (PyEMD prepare_points_simple, a port of Rilling's boundary_conditions.m). P: maxima (a),
 * Q: minima (b), both non-empty. */
static void boundary(const double *S, int64_t n, const int64_t *P, int64_t a, const int64_t *Q,
                     int64_t b, Src *lmax, Src *lmin, int64_t *lsym, Src *rmax, Src *rmin,
                     int64_t *rsym) {
    const int64_t n1 = n - 1;
    /* Left side: cases A1, A2 (first extremum a maximum), B1, B2 (a minimum). */
    if (P[0] < Q[0]) {
        if (S[0] > S[Q[0]]) { /* A1 */
            take_rev(lmax, P, a, 1, 3); take_rev(lmin, Q, b, 0, 2); *lsym = P[0];
        } else { /* A2 */
            take_rev(lmax, P, a, 0, 2); take_rev(lmin, Q, b, 0, 1); push(lmin, 0); *lsym = 0;
        }
    } else {
        if (S[0] < S[P[0]]) { /* B1 */
            take_rev(lmax, P, a, 0, 2); take_rev(lmin, Q, b, 1, 3); *lsym = Q[0];
        } else { /* B2 */
            take_rev(lmax, P, a, 0, 1); push(lmax, 0); take_rev(lmin, Q, b, 0, 2); *lsym = 0;
        }
    }
    /* Right side: cases C1, C2 (last extremum a minimum), D1, D2 (a maximum). */
    if (P[a - 1] < Q[b - 1]) {
        if (S[n1] < S[P[a - 1]]) { /* C1 */
            take_rev(rmax, P, a, a - 2, a); take_rev(rmin, Q, b, b - 3, b - 1); *rsym = Q[b - 1];
        } else { /* C2: P[a-1:a] + [N1], reversed */
            rmax->n = 0; push(rmax, n1); push(rmax, P[a - 1]);
            take_rev(rmin, Q, b, b - 2, b); *rsym = n1;
        }
    } else {
        if (S[n1] > S[Q[b - 1]]) { /* D1 */
            take_rev(rmax, P, a, a - 3, a - 1); take_rev(rmin, Q, b, b - 2, b); *rsym = P[a - 1];
        } else { /* D2: Q[b-1:b] + [N1], reversed */
            take_rev(rmax, P, a, a - 2, a); rmin->n = 0; push(rmin, n1); push(rmin, Q[b - 1]);
            *rsym = n1;
        }
    }
    or_whole(lmin, Q, b); or_whole(rmin, Q, b); or_whole(lmax, P, a); or_whole(rmax, P, a);
    /* Left fallback: the outermost mirrored knot of either list does not reach past sample 0. */
    if (2 * *lsym - lmin->i[0] > 0 || 2 * *lsym - lmax->i[0] > 0) {
        if (*lsym == P[0]) take_rev(lmax, P, a, 0, 2);
        else take_rev(lmin, Q, b, 0, 2);
        *lsym = 0;
    }
    /* Right fallback: the same past sample N - 1. */
    if (2 * *rsym - rmin->i[rmin->n - 1] < n1 || 2 * *rsym - rmax->i[rmax->n - 1] < n1) {
        if (*rsym == P[a - 1]) take_rev(rmax, P, a, a - 2, a);
        else take_rev(rmin, Q, b, b - 2, b);
        *rsym = n1;
    }
}

/* Knots of one envelope: [left mirrored | interior | right mirrored], ascending, adjacent
 * duplicate positions dropped (they carry the same sample). Returns the knot count. */
static int64_t knots(const double *S, const Src *l, int64_t lsym, const int64_t *E, int64_t ne,
                     const Src *r, int64_t rsym, double *kx, double *ky) {
    int64_t k = 0;
    for (int pass = 0; pass < 3; pass++) {
        int64_t cnt = pass == 0 ? l->n : pass == 1 ? ne : r->n;
        for (int64_t i = 0; i < cnt; i++) {
            int64_t src = pass == 0 ? l->i[i] : pass == 1 ? E[i] : r->i[i];
            int64_t pos = pass == 0 ? 2 * lsym - src : pass == 1 ? src : 2 * rsym - src;
            if (k > 0 && (double)pos <= kx[k - 1]) continue; /* duplicate (never descending) */
            kx[k] = (double)pos;
            ky[k] = 0.5 * S[src];
            k++;
        }
    }
    return k;
}

/* §1.6 Spline: the cubic spline through n knots, not-a-knot for n > 3, natural for n == 3,
 * evaluated at 0..len-1 (the knots span [0, len - 1]). Solved for m = M / 6 (the second
 * derivatives over 6) by the Thomas algorithm on the eliminated system of §4.6, which is
 * strictly diagonally dominant; evaluated in scipy's local power basis.
 *
 * The two envelopes' systems are solved side by side, row j of one beside row j of the other:
 * each sweep is a chain of divisions, and two independent chains keep the processor busy. */

/* Spacings, slopes and the ends of m; 1 when the system has rows to sweep (n > 3). */
static int spline_setup(Env *e) {
    const int64_t n = e->n;
    if (n < 3) return 0;
    for (int64_t k = 0; k < n - 1; k++) {
        e->hk[k] = e->kx[k + 1] - e->kx[k];
        e->sl[k] = (e->ky[k + 1] - e->ky[k]) / e->hk[k];
    }
    e->m[0] = e->m[n - 1] = 0.0;
    if (n == 3) { /* natural: m0 = m2 = 0 */
        e->m[1] = (e->sl[1] - e->sl[0]) / (2.0 * (e->hk[0] + e->hk[1]));
        return 0;
    }
    return 1;
}

/* Forward sweep, row j (1 .. n-2) of h[j-1] m[j-1] + 2 (h[j-1] + h[j]) m[j] + h[j] m[j+1] =
 * s[j] - s[j-1]; not-a-knot eliminates m[0] from row 1 and m[n-1] from row n-2. */
static inline void sweep_row(Env *e, int64_t j) {
    const double *hk = e->hk, *sl = e->sl;
    const int64_t n = e->n;
    double a = hk[j - 1], b = 2.0 * (hk[j - 1] + hk[j]), c = hk[j];
    const double r = sl[j] - sl[j - 1];
    if (j == 1) {
        const double h0 = hk[0], h1 = hk[1];
        a = 0.0;
        b = (h0 + h1) * (h0 + 2.0 * h1) / h1;
        c = (h1 * h1 - h0 * h0) / h1;
    }
    if (j == n - 2) {
        const double hq = hk[n - 3], hl = hk[n - 2];
        c = 0.0;
        b = (hq + hl) * (2.0 * hq + hl) / hq;
        a = (hq * hq - hl * hl) / hq;
    }
    const double den = b - (j > 1 ? a * e->cp[j - 1] : 0.0);
    e->cp[j] = c / den;
    e->dp[j] = (r - (j > 1 ? a * e->dp[j - 1] : 0.0)) / den;
}

/* Back substitution, row j (n-3 .. 1), after m[n-2] = dp[n-2]. */
static inline void back_row(Env *e, int64_t j) { e->m[j] = e->dp[j] - e->cp[j] * e->m[j + 1]; }

/* The not-a-knot ends of m. */
static void spline_ends(Env *e) {
    const int64_t n = e->n;
    const double *hk = e->hk;
    double *m = e->m;
    const double h0 = hk[0], h1 = hk[1], hq = hk[n - 3], hl = hk[n - 2];
    m[0] = ((h0 + h1) * m[1] - h0 * m[2]) / h1;            /* left */
    m[n - 1] = ((hq + hl) * m[n - 2] - hl * m[n - 3]) / hq; /* and right */
}

/* m of both envelopes. */
static void spline_solve(Env *u, Env *l) {
    const int64_t ju = spline_setup(u) ? u->n - 2 : 0, jl = spline_setup(l) ? l->n - 2 : 0;
    const int64_t both = ju < jl ? ju : jl;
    int64_t j = 1;
    for (; j <= both; j++) {
        sweep_row(u, j);
        sweep_row(l, j);
    }
    for (; j <= ju; j++) sweep_row(u, j);
    for (; j <= jl; j++) sweep_row(l, j);
    if (ju) u->m[ju] = u->dp[ju];
    if (jl) l->m[jl] = l->dp[jl];
    int64_t iu = ju - 1, il = jl - 1; /* n - 3 */
    for (; iu > jl - 1 && iu >= 1; iu--) back_row(u, iu); /* the longer one's extra rows first */
    for (; il > ju - 1 && il >= 1; il--) back_row(l, il);
    for (; iu >= 1; iu--, il--) {
        back_row(u, iu);
        back_row(l, il);
    }
    if (ju) spline_ends(u);
    if (jl) spline_ends(l);
}

/* The half envelopes' sum is the mean envelope, taken from h: the upper one (h == NULL) is
 * written to out as 0 + value, the lower one (h given) is added to it and the sum subtracted
 * from h in the same pass: the operations, in order, of a mean set to zero, both envelopes
 * added into it, then h -= mean. */
#define SPLINE_STORE(t, v)                                                                      \
    do {                                                                                       \
        if (h) h[t] -= out[t] + (v);                                                           \
        else out[t] = 0.0 + (v);                                                               \
    } while (0)
static void spline_eval(const Env *e, int64_t len, double *out, double *h) {
    const double *kx = e->kx, *ky = e->ky, *hk = e->hk, *sl = e->sl, *m = e->m;
    const int64_t n = e->n;
    if (n < 3) { /* unreachable with > 2 extrema; a line (or a constant) keeps it defined */
        for (int64_t t = 0; t < len; t++) {
            double v = n == 0 ? 0.0 : ky[0];
            if (n == 2) v += (ky[1] - ky[0]) / (kx[1] - kx[0]) * ((double)t - kx[0]);
            SPLINE_STORE(t, v);
        }
        return;
    }
    /* sample t lies in the piece k with kx[k] <= t < kx[k + 1] (the first piece before the
     * first knot, the last one past n - 2); a piece's coefficients are computed once */
    int64_t t = 0;
    for (int64_t k = 0; k <= n - 2 && t < len; k++) {
        const double c2 = 3.0 * m[k], c3 = (m[k + 1] - m[k]) / hk[k];
        const double c1 = sl[k] - hk[k] * (2.0 * m[k] + m[k + 1]);
        const double x0 = kx[k], y0 = ky[k];
        int64_t end = len;
        if (k < n - 2) { /* the knots are whole sample positions: t < kx[k + 1] exactly */
            const double e = kx[k + 1] < (double)len ? kx[k + 1] : (double)len;
            end = e > (double)t ? (int64_t)ceil(e) : t;
        }
        double B = (double)t - x0; /* whole numbers: B + 1.0 is exact */
        if (h)
            for (; t < end; t++, B += 1.0) h[t] -= out[t] + (y0 + B * (c1 + B * (c2 + B * c3)));
        else
            for (; t < end; t++, B += 1.0) out[t] = 0.0 + (y0 + B * (c1 + B * (c2 + B * c3)));
    }
}

/* The pieces' coefficients and where they start: sample t lies in piece k = the number of
 * knots 1 .. n-2 at or before t (the first piece also before the first knot, the last one
 * past knot n - 2; knots are whole sample positions). Returns the piece of sample 0. */
static int64_t spline_pieces(Env *e, int64_t len) {
    const int64_t n = e->n;
    const double *hk = e->hk, *sl = e->sl, *m = e->m;
    for (int64_t k = 0; k <= n - 2; k++) {
        e->c1[k] = sl[k] - hk[k] * (2.0 * m[k] + m[k + 1]);
        e->c2[k] = 3.0 * m[k];
        e->c3[k] = (m[k + 1] - m[k]) / hk[k];
    }
    memset(e->up, 0, (size_t)len);
    int64_t first = 0;
    for (int64_t j = 1; j <= n - 2; j++) {
        const double p = e->kx[j];
        if (p <= 0.0) first++;
        else if (p < (double)len) e->up[(int64_t)p]++;
    }
    return first;
}

/* h -= upper + lower (the half envelopes), both evaluated at every sample in one pass, with no
 * branch on the piece: the operations, in order, of a mean set to zero, the upper envelope
 * then the lower added into it, then h -= mean. */
static void subtract_mean(Env *u, Env *l, int64_t len, double *h, double *mean) {
    if (u->n < 3 || l->n < 3) { /* unreachable with > 2 extrema; kept defined */
        spline_eval(u, len, mean, NULL);
        spline_eval(l, len, mean, h);
        return;
    }
    int64_t ku = spline_pieces(u, len), kl = spline_pieces(l, len);
    const double *ux = u->kx, *uy = u->ky, *u1 = u->c1, *u2 = u->c2, *u3 = u->c3;
    const double *lx = l->kx, *ly = l->ky, *l1 = l->c1, *l2 = l->c2, *l3 = l->c3;
    const unsigned char *uu = u->up, *lu = l->up;
    for (int64_t t = 0; t < len; t++) {
        ku += uu[t];
        kl += lu[t];
        const double bu = (double)t - ux[ku], bl = (double)t - lx[kl];
        const double vu = uy[ku] + bu * (u1[ku] + bu * (u2[ku] + bu * u3[ku]));
        const double vl = ly[kl] + bl * (l1[kl] + bl * (l2[kl] + bl * l3[kl]));
        h[t] -= (0.0 + vu) + vl;
    }
}

/* §1.3 One sift of h: h -= (upper + lower) / 2. Returns 0 when h has 2 extrema or fewer
 * (h is then left as it is: the row's decomposition is finished). */
static int sift(double *h, int64_t n, Work *w) {
    int64_t a, b;
    find_extrema(h, n, w, &a, &b);
    /* a + b > 2 implies both kinds (they alternate); the guard keeps it so on any input */
    if (a + b <= 2 || a == 0 || b == 0) return 0;
    Src lmax, lmin, rmax, rmin;
    int64_t lsym, rsym;
    boundary(h, n, w->pmax, a, w->pmin, b, &lmax, &lmin, &lsym, &rmax, &rmin, &rsym);
    Env *up = &w->env[0], *lo = &w->env[1];
    up->n = knots(h, &lmax, lsym, w->pmax, a, &rmax, rsym, up->kx, up->ky);
    lo->n = knots(h, &lmin, lsym, w->pmin, b, &rmin, rsym, lo->kx, lo->ky);
    spline_solve(up, lo);
    subtract_mean(up, lo, n, h, w->mean); /* h -= mean */
    return 1;
}

/* §1.2 Outer loop of one row: IMF after IMF, n_sifts sifts each. imfs (n_imfs, n) and
 * residue (n) are written; returns n_valid. */
static int64_t emd_row(const double *x, int64_t n, int n_imfs, int n_sifts, Work *w,
                       double *imfs, double *residue) {
    int64_t n_valid = 0;
    int alive = n >= 3;
    memset(imfs, 0, (size_t)n_imfs * (size_t)n * sizeof(double));
    memset(w->acc, 0, (size_t)n * sizeof(double));
    for (int k = 0; k < n_imfs && alive; k++) {
        for (int64_t t = 0; t < n; t++) w->h[t] = x[t] - w->acc[t];
        for (int s = 0; s < n_sifts && alive; s++) alive = sift(w->h, n, w);
        if (!alive) break; /* a sift found <= 2 extrema: this IMF is dropped */
        double lo = INFINITY, hi = -INFINITY, sum = 0.0;
        for (int64_t t = 0; t < n; t++) {
            imfs[(int64_t)k * n + t] = w->h[t];
            w->acc[t] += w->h[t];
            const double r = x[t] - w->acc[t];
            lo = r < lo ? r : lo;
            hi = r > hi ? r : hi;
            sum += fabs(r);
        }
        n_valid++;
        /* written as "stays alive while >=" so that NaN ends the row, as in the torch module */
        alive = (hi - lo >= RANGE_THR) && (sum >= POWER_THR);
    }
    for (int64_t t = 0; t < n; t++) residue[t] = x[t] - w->acc[t];
    return n_valid;
}

static void work_free(Work *w) {
    free(w->h); free(w->acc); free(w->mean); free(w->pmax); free(w->pmin);
    for (int i = 0; i < 2; i++) {
        Env *e = &w->env[i];
        free(e->kx); free(e->ky); free(e->hk); free(e->sl); free(e->m); free(e->cp); free(e->dp);
        free(e->c1); free(e->c2); free(e->c3); free(e->up);
    }
}

static int work_alloc(Work *w, int64_t n) {
    memset(w, 0, sizeof *w);
    const size_t nn = (size_t)n + 8, nd = nn * sizeof(double), ni = nn * sizeof(int64_t);
    int ok = (w->h = malloc(nd)) && (w->acc = malloc(nd)) && (w->mean = malloc(nd)) &&
             (w->pmax = malloc(ni)) && (w->pmin = malloc(ni));
    for (int i = 0; i < 2 && ok; i++) {
        Env *e = &w->env[i];
        ok = (e->kx = malloc(nd)) && (e->ky = malloc(nd)) && (e->hk = malloc(nd)) &&
             (e->sl = malloc(nd)) && (e->m = malloc(nd)) && (e->cp = malloc(nd)) &&
             (e->dp = malloc(nd)) && (e->c1 = malloc(nd)) && (e->c2 = malloc(nd)) &&
             (e->c3 = malloc(nd)) && (e->up = malloc(nn));
    }
    if (!ok) work_free(w);
    return ok;
}

/* The shared body of both entry points; x, imfs, residue are float (f32) or double. */
static int emd_batch(const void *x, int f32, int64_t batch, int64_t len, int32_t n_imfs,
                     int32_t n_sifts, void *imfs, void *residue, int64_t *n_valid) {
    if (batch < 0 || len < 0 || n_imfs < 1 || n_imfs > TACTILE_EMD_MAX_IMFS || n_sifts < 1 ||
        n_sifts > TACTILE_EMD_MAX_SIFTS)
        return TACTILE_EINVAL;
    if (batch == 0 || len == 0) {
        if (batch > 0 && !n_valid) return TACTILE_EINVAL;
        for (int64_t i = 0; i < batch; i++) n_valid[i] = 0;
        return TACTILE_OK;
    }
    if (!x || !imfs || !residue || !n_valid) return TACTILE_EINVAL;
    /* sizes: every output index fits in size_t and int64 (len * 16 * batch) */
    const uint64_t cap = (uint64_t)(SIZE_MAX < INT64_MAX ? SIZE_MAX : INT64_MAX) / 64u;
    if ((uint64_t)len > cap / (uint64_t)n_imfs ||
        (uint64_t)batch > cap / ((uint64_t)len * (uint64_t)n_imfs))
        return TACTILE_EINVAL;
    Work w;
    if (!work_alloc(&w, len)) return TACTILE_ENOMEM;
    double *row = malloc((size_t)len * sizeof(double));
    double *out = malloc(((size_t)n_imfs + 1) * (size_t)len * sizeof(double));
    if (!row || !out) {
        free(row); free(out); work_free(&w);
        return TACTILE_ENOMEM;
    }
    int status = TACTILE_OK;
    for (int64_t i = 0; i < batch; i++) {
        int finite = 1;
        if (f32) {
            const float *xi = (const float *)x + i * len;
            for (int64_t t = 0; t < len; t++) row[t] = (double)xi[t];
        } else {
            memcpy(row, (const double *)x + i * len, (size_t)len * sizeof(double));
        }
        for (int64_t t = 0; t < len; t++) finite &= isfinite(row[t]) != 0;
        if (finite) {
            n_valid[i] = emd_row(row, len, n_imfs, n_sifts, &w, out, out + (int64_t)n_imfs * len);
        } else { /* no IMFs, residue = x */
            status = TACTILE_ENONFINITE;
            n_valid[i] = 0;
            memset(out, 0, (size_t)n_imfs * (size_t)len * sizeof(double));
            memcpy(out + (int64_t)n_imfs * len, row, (size_t)len * sizeof(double));
        }
        const int64_t ni = (int64_t)n_imfs * len;
        if (f32) {
            float *im = (float *)imfs + i * ni, *re = (float *)residue + i * len;
            for (int64_t t = 0; t < ni; t++) im[t] = (float)out[t];
            for (int64_t t = 0; t < len; t++) re[t] = (float)out[ni + t];
        } else {
            memcpy((double *)imfs + i * ni, out, (size_t)ni * sizeof(double));
            memcpy((double *)residue + i * len, out + ni, (size_t)len * sizeof(double));
        }
    }
    free(row); free(out); work_free(&w);
    return status;
}

int tactile_emd_f64(const double *x, int64_t batch, int64_t length, int32_t n_imfs,
                    int32_t n_sifts, double *imfs, double *residue, int64_t *n_valid) {
    return emd_batch(x, 0, batch, length, n_imfs, n_sifts, imfs, residue, n_valid);
}

int tactile_emd_f32(const float *x, int64_t batch, int64_t length, int32_t n_imfs,
                    int32_t n_sifts, float *imfs, float *residue, int64_t *n_valid) {
    return emd_batch(x, 1, batch, length, n_imfs, n_sifts, imfs, residue, n_valid);
}

int tactile_native_abi(void) { return TACTILE_NATIVE_ABI; }
