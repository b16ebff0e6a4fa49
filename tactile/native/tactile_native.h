/* The toolkit's native kernels: EMD and OMP sparse codes on C arrays (C99, libc and libm only).
 *
 * Every entry point returns a status (TACTILE_OK or one of the codes below), keeps no state
 * between calls, allocates what it needs per call and frees it before returning, and computes
 * in double precision whatever the array type. Rows are independent: a row's result is the
 * same bits in any batch. Arrays are dense and C-ordered.
 */
#ifndef TACTILE_NATIVE_H
#define TACTILE_NATIVE_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define TACTILE_OK 0
#define TACTILE_EINVAL 1    /* a null pointer, a negative size, a setting out of range */
#define TACTILE_ENOMEM 2    /* the workspace could not be allocated (nothing written) */
#define TACTILE_ENONFINITE 3 /* NaN or inf in the input: those rows hold a defined result */

#define TACTILE_EMD_MAX_IMFS 16
#define TACTILE_EMD_MAX_SIFTS 1000
#define TACTILE_NATIVE_ABI 1

/* The ABI version of this library (TACTILE_NATIVE_ABI): callers check it before use. */
int tactile_native_abi(void);

/* EMD of `batch` signals of `length` samples, `n_imfs` IMF slots (1..16) of `n_sifts` sifts
 * (1..1000) each, as PyEMD EMD(FIXE=n_sifts).emd(x, max_imf=n_imfs) and the toolkit's torch
 * module compute it.
 *
 * x: (batch, length). imfs: (batch, n_imfs, length), zero past n_valid. residue: (batch,
 * length), x minus the sum of the IMFs. n_valid: (batch,). A row shorter than 3 samples, or
 * holding NaN or inf, has no IMFs: residue = x, n_valid = 0 (and the status is
 * TACTILE_ENONFINITE if any row held NaN or inf). */
int tactile_emd_f64(const double *x, int64_t batch, int64_t length, int32_t n_imfs,
                    int32_t n_sifts, double *imfs, double *residue, int64_t *n_valid);
int tactile_emd_f32(const float *x, int64_t batch, int64_t length, int32_t n_imfs,
                    int32_t n_sifts, float *imfs, float *residue, int64_t *n_valid);

/* OMP codes of `rows` signals of `features` values on `atoms` atoms, at most `n_nonzero`
 * (1..atoms) non-zero per row, as scikit-learn's orthogonal_mp_gram(gram, dictionary @ x,
 * n_nonzero_coefs=n_nonzero) computes them (its early exits with the epsilon of the array
 * type: float32's for the f32 entry point, float64's for the f64 one).
 *
 * x: (rows, features). dictionary: (atoms, features). gram: (atoms, atoms), the dictionary's
 * Gram matrix (symmetric: only its rows are read). codes: (rows, atoms). A row holding NaN or
 * inf gets zero codes; a dictionary or Gram matrix holding them gives zero codes everywhere
 * (status TACTILE_ENONFINITE). */
int tactile_omp_f64(const double *x, int64_t rows, int64_t features, const double *dictionary,
                    const double *gram, int64_t atoms, int64_t n_nonzero, double *codes);
int tactile_omp_f32(const float *x, int64_t rows, int64_t features, const float *dictionary,
                    const float *gram, int64_t atoms, int64_t n_nonzero, float *codes);

#ifdef __cplusplus
}
#endif

#endif
