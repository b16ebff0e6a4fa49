/* The kernels as an onnxruntime custom-op library: domain "ai.tactile", ops EMD and SparseCode
 * (version 1), registered by RegisterCustomOps, which onnxruntime calls when a session's
 * options load this library (SessionOptions.register_custom_ops_library in Python).
 *
 *   EMD(x_in) -> imfs, residue, n_valid          attributes n_imfs (1..16), n_sifts (1..1000)
 *     x_in (batch, channels, time) float32; imfs (batch, channels, n_imfs, time) float32, zero
 *     past n_valid; residue (batch, channels, time) float32; n_valid (batch, channels) int64:
 *     the outputs of the portable EMD graph (tactile.export.emd_graph), same layout and dtypes.
 *   SparseCode(x, dictionary, gram) -> codes     attribute n_nonzero (1..atoms)
 *     x (rows, features), dictionary (atoms, features), gram (atoms, atoms), codes (rows, atoms),
 *     all float32: the portable coder graph's (tactile.export.coder_graph). The node's other
 *     attribute, variant, only picks the fallback function's body; the kernel ignores it.
 *
 * The inputs come from a model file and a device: every shape, type and setting is checked and
 * a bad one gives an error status that onnxruntime reports (the session's run fails with its
 * message); nothing here aborts. NaN or inf in an input gives the kernels' defined result (no
 * IMFs and the input as residue; zero codes), as tactile_native.h states. Only the C API table
 * onnxruntime passes in is used (ort_api.h): no link to libonnxruntime.
 */
#include <limits.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "ort_api.h"
#include "tactile_native.h"

#if defined(_WIN32)
#define TACTILE_EXPORT __declspec(dllexport)
#else
#define TACTILE_EXPORT __attribute__((visibility("default")))
#endif

#define MAX_DIMS 8

typedef struct {
  const OrtApi *api;
  int64_t a, b; /* EMD: n_imfs, n_sifts; SparseCode: n_nonzero, unused */
  int is_emd;
} Kernel;

static OrtStatus *fail(const OrtApi *api, OrtErrorCode code, const char *fmt, long long v1,
                       long long v2) {
  char msg[256];
  snprintf(msg, sizeof msg, fmt, v1, v2);
  return ORT_FN(api, OrtCreateStatusFn, ORT_CreateStatus)(code, msg);
}

/* The element type and shape of input `index` (at most MAX_DIMS dimensions). */
static OrtStatus *input_of(const OrtApi *api, OrtKernelContext *ctx, size_t index,
                           const OrtValue **value, ONNXTensorElementDataType *type,
                           int64_t *dims, size_t *ndim) {
  OrtTensorTypeAndShapeInfo *info = NULL;
  OrtStatus *st = ORT_FN(api, OrtKernelContextGetInputFn, ORT_KernelContext_GetInput)(
      ctx, index, value);
  if (st) return st;
  if (*value == NULL) return fail(api, ORT_INVALID_ARGUMENT, "ai.tactile: input %lld missing",
                                  (long long)index, 0);
  st = ORT_FN(api, OrtGetTensorTypeAndShapeFn, ORT_GetTensorTypeAndShape)(*value, &info);
  if (st) return st;
  st = ORT_FN(api, OrtGetTensorElementTypeFn, ORT_GetTensorElementType)(info, type);
  if (!st) st = ORT_FN(api, OrtGetDimensionsCountFn, ORT_GetDimensionsCount)(info, ndim);
  if (!st && *ndim > MAX_DIMS)
    st = fail(api, ORT_INVALID_ARGUMENT, "ai.tactile: input %lld has %lld dimensions",
              (long long)index, (long long)*ndim);
  if (!st) st = ORT_FN(api, OrtGetDimensionsFn, ORT_GetDimensions)(info, dims, *ndim);
  ORT_FN(api, OrtReleaseTensorTypeAndShapeInfoFn, ORT_ReleaseTensorTypeAndShapeInfo)(info);
  return st;
}

static OrtStatus *data_of(const OrtApi *api, const OrtValue *value, void **out) {
  /* onnxruntime's accessor takes a non-const value; the kernel only reads inputs */
  OrtStatus *st = ORT_FN(api, OrtGetTensorMutableDataFn, ORT_GetTensorMutableData)(
      (OrtValue *)value, out);
  if (!st && *out == NULL) *out = (void *)"";  /* an empty tensor may have no buffer */
  return st;
}

static OrtStatus *output_of(const OrtApi *api, OrtKernelContext *ctx, size_t index,
                            const int64_t *dims, size_t ndim, void **data) {
  OrtValue *value = NULL;
  OrtStatus *st = ORT_FN(api, OrtKernelContextGetOutputFn, ORT_KernelContext_GetOutput)(
      ctx, index, dims, ndim, &value);
  if (st) return st;
  return data_of(api, value, data);
}

/* n = product of dims, 0 if any is 0; an error for a negative dimension or an overflow. */
static int checked_count(const int64_t *dims, size_t ndim, int64_t *n) {
  int64_t count = 1;
  for (size_t i = 0; i < ndim; i++) {
    if (dims[i] < 0) return 0;
    if (dims[i] != 0 && count > INT64_MAX / 8 / dims[i]) return 0;
    count *= dims[i];
  }
  *n = count;
  return 1;
}

static OrtStatus *kernel_status(const OrtApi *api, int status, const char *op) {
  char msg[160];
  if (status == TACTILE_OK || status == TACTILE_ENONFINITE) return NULL;
  snprintf(msg, sizeof msg, "ai.tactile %s: %s (status %d)", op,
           status == TACTILE_ENOMEM ? "out of memory" : "the kernel refused its arguments",
           status);
  return ORT_FN(api, OrtCreateStatusFn, ORT_CreateStatus)(
      status == TACTILE_ENOMEM ? ORT_RUNTIME_EXCEPTION : ORT_INVALID_ARGUMENT, msg);
}

static OrtStatus *emd_compute(const Kernel *k, OrtKernelContext *ctx) {
  const OrtApi *api = k->api;
  const OrtValue *x;
  ONNXTensorElementDataType type;
  int64_t d[MAX_DIMS], n;
  size_t nd;
  void *px, *pi, *pr, *pv;
  OrtStatus *st = input_of(api, ctx, 0, &x, &type, d, &nd);
  if (st) return st;
  if (type != ONNX_TENSOR_ELEMENT_DATA_TYPE_FLOAT)
    return fail(api, ORT_INVALID_ARGUMENT, "ai.tactile EMD: input must be float32 (type %lld)",
                (long long)type, 0);
  if (nd != 3)
    return fail(api, ORT_INVALID_ARGUMENT,
                "ai.tactile EMD: input must be (batch, channels, time), got %lld dimensions",
                (long long)nd, 0);
  if (!checked_count(d, 3, &n) || d[2] > INT32_MAX || !checked_count(
          (int64_t[]){d[0], d[1], k->a, d[2]}, 4, &n))
    return fail(api, ORT_INVALID_ARGUMENT, "ai.tactile EMD: input shape out of range "
                "(time %lld, channels %lld)", (long long)d[2], (long long)d[1]);
  if ((st = data_of(api, x, &px))) return st;
  {
    int64_t imf_dims[4] = {d[0], d[1], k->a, d[2]};
    if ((st = output_of(api, ctx, 0, imf_dims, 4, &pi))) return st;
    if ((st = output_of(api, ctx, 1, d, 3, &pr))) return st;
    if ((st = output_of(api, ctx, 2, d, 2, &pv))) return st;
  }
  if (d[0] * d[1] == 0) return NULL;  /* nothing to decompose: empty outputs */
  return kernel_status(api, tactile_emd_f32((const float *)px, d[0] * d[1], d[2],
                                            (int32_t)k->a, (int32_t)k->b, (float *)pi,
                                            (float *)pr, (int64_t *)pv), "EMD");
}

static OrtStatus *code_compute(const Kernel *k, OrtKernelContext *ctx) {
  const OrtApi *api = k->api;
  const OrtValue *v[3];
  ONNXTensorElementDataType type;
  int64_t d[3][MAX_DIMS], n;
  size_t nd;
  void *p[3], *pc;
  static const char *names[3] = {"x", "dictionary", "gram"};
  OrtStatus *st;
  for (size_t i = 0; i < 3; i++) {
    if ((st = input_of(api, ctx, i, &v[i], &type, d[i], &nd))) return st;
    if (type != ONNX_TENSOR_ELEMENT_DATA_TYPE_FLOAT || nd != 2) {
      char msg[160];
      snprintf(msg, sizeof msg, "ai.tactile SparseCode: %s must be a 2-d float32 tensor "
               "(type %d, %d dimensions)", names[i], (int)type, (int)nd);
      return ORT_FN(api, OrtCreateStatusFn, ORT_CreateStatus)(ORT_INVALID_ARGUMENT, msg);
    }
    if (!checked_count(d[i], 2, &n))
      return fail(api, ORT_INVALID_ARGUMENT, "ai.tactile SparseCode: input %lld has a bad "
                  "shape (%lld ...)", (long long)i, (long long)d[i][0]);
    if ((st = data_of(api, v[i], &p[i]))) return st;
  }
  int64_t rows = d[0][0], features = d[0][1], atoms = d[1][0];
  if (d[1][1] != features || atoms < 1 || features < 1)
    return fail(api, ORT_INVALID_ARGUMENT, "ai.tactile SparseCode: x has %lld features, the "
                "dictionary %lld", (long long)features, (long long)d[1][1]);
  if (d[2][0] != atoms || d[2][1] != atoms)
    return fail(api, ORT_INVALID_ARGUMENT, "ai.tactile SparseCode: gram must be (%lld, %lld)",
                (long long)atoms, (long long)atoms);
  if (k->a > atoms)
    return fail(api, ORT_INVALID_ARGUMENT, "ai.tactile SparseCode: n_nonzero %lld > %lld atoms",
                (long long)k->a, (long long)atoms);
  int64_t out_dims[2] = {rows, atoms};
  if (!checked_count(out_dims, 2, &n))
    return fail(api, ORT_INVALID_ARGUMENT, "ai.tactile SparseCode: %lld x %lld codes",
                (long long)rows, (long long)atoms);
  if ((st = output_of(api, ctx, 0, out_dims, 2, &pc))) return st;
  if (rows == 0) return NULL;
  return kernel_status(api, tactile_omp_f32((const float *)p[0], rows, features,
                                            (const float *)p[1], (const float *)p[2], atoms,
                                            k->a, (float *)pc), "SparseCode");
}

/* --- the OrtCustomOp callbacks ------------------------------------------------------------ */

static int is_emd(const OrtCustomOp *op);

static OrtStatus *create_kernel(const OrtCustomOp *op, const OrtApi *api,
                                const OrtKernelInfo *info, void **out) {
  OrtKernelInfoGetAttributeInt64Fn attr =
      ORT_FN(api, OrtKernelInfoGetAttributeInt64Fn, ORT_KernelInfoGetAttribute_int64);
  Kernel k = {api, 0, 0, is_emd(op)};
  OrtStatus *st;
  *out = NULL;
  if (k.is_emd) {
    if ((st = attr(info, "n_imfs", &k.a)) || (st = attr(info, "n_sifts", &k.b))) return st;
    if (k.a < 1 || k.a > TACTILE_EMD_MAX_IMFS || k.b < 1 || k.b > TACTILE_EMD_MAX_SIFTS)
      return fail(api, ORT_INVALID_ARGUMENT, "ai.tactile EMD: n_imfs=%lld, n_sifts=%lld out of "
                  "range (1..16, 1..1000)", (long long)k.a, (long long)k.b);
  } else {
    if ((st = attr(info, "n_nonzero", &k.a))) return st;
    if (k.a < 1)
      return fail(api, ORT_INVALID_ARGUMENT, "ai.tactile SparseCode: n_nonzero=%lld < 1",
                  (long long)k.a, 0);
  }
  Kernel *made = malloc(sizeof *made);
  if (!made) return fail(api, ORT_RUNTIME_EXCEPTION, "ai.tactile: out of memory", 0, 0);
  *made = k;
  *out = made;
  return NULL;
}

static OrtStatus *compute(void *kernel, OrtKernelContext *ctx) {
  const Kernel *k = kernel;
  return k->is_emd ? emd_compute(k, ctx) : code_compute(k, ctx);
}

static void destroy(void *kernel) { free(kernel); }
static const char *emd_name(const OrtCustomOp *op) { (void)op; return "EMD"; }
static const char *code_name(const OrtCustomOp *op) { (void)op; return "SparseCode"; }
static const char *provider(const OrtCustomOp *op) { (void)op; return "CPUExecutionProvider"; }
static size_t emd_inputs(const OrtCustomOp *op) { (void)op; return 1; }
static size_t emd_outputs(const OrtCustomOp *op) { (void)op; return 3; }
static size_t code_inputs(const OrtCustomOp *op) { (void)op; return 3; }
static size_t code_outputs(const OrtCustomOp *op) { (void)op; return 1; }
static ONNXTensorElementDataType f32(const OrtCustomOp *op, size_t i) {
  (void)op; (void)i;
  return ONNX_TENSOR_ELEMENT_DATA_TYPE_FLOAT;
}
static ONNXTensorElementDataType emd_out_type(const OrtCustomOp *op, size_t i) {
  (void)op;
  return i == 2 ? ONNX_TENSOR_ELEMENT_DATA_TYPE_INT64 : ONNX_TENSOR_ELEMENT_DATA_TYPE_FLOAT;
}
static OrtCustomOpInputOutputCharacteristic required(const OrtCustomOp *op, size_t i) {
  (void)op; (void)i;
  return INPUT_OUTPUT_REQUIRED;
}
static OrtMemType cpu_memory(const OrtCustomOp *op, size_t i) {
  (void)op; (void)i;
  return OrtMemTypeDefault;
}
static int one(const OrtCustomOp *op) { (void)op; return 1; }
static int since_version(const OrtCustomOp *op) { (void)op; return 1; }
static int any_version(const OrtCustomOp *op) { (void)op; return INT_MAX; }
static size_t no_pairs(int **in, int **out) { *in = NULL; *out = NULL; return 0; }
static void release_pairs(int *in, int *out) { (void)in; (void)out; }

#define OP(NAME, INS, OUTS, OUT_TYPE)                                                   \
  {ORT_OPS_API_VERSION, NULL, NAME, provider, f32, INS, OUT_TYPE, OUTS, NULL, destroy, \
   required, required, cpu_memory, one, one, one, one, create_kernel, compute, NULL,  \
   since_version, any_version, no_pairs, release_pairs, no_pairs, release_pairs}

static const OrtCustomOp EMD_OP = OP(emd_name, emd_inputs, emd_outputs, emd_out_type);
static const OrtCustomOp CODE_OP = OP(code_name, code_inputs, code_outputs, f32);

static int is_emd(const OrtCustomOp *op) { return op == &EMD_OP; }

/* The library's entry point: registers domain ai.tactile with EMD and SparseCode on `options`.
 * Against an onnxruntime older than ORT_OPS_API_VERSION it registers nothing (the model's
 * portable functions then run) and says so in the returned status when it can. */
TACTILE_EXPORT OrtStatus *RegisterCustomOps(OrtSessionOptions *options, const OrtApiBase *base) {
  const OrtApi *api = base ? base->GetApi(ORT_OPS_API_VERSION) : NULL;
  OrtCustomOpDomain *domain = NULL;
  OrtStatus *st;
  if (api == NULL) return NULL;  /* too old: no table to report with; nothing registered */
  /* The domain must outlive every session that uses these options: it is not released (one
   * small object per registration, as onnxruntime's own examples do). */
  if ((st = ORT_FN(api, OrtCreateCustomOpDomainFn, ORT_CreateCustomOpDomain)("ai.tactile",
                                                                            &domain)))
    return st;
  if ((st = ORT_FN(api, OrtCustomOpDomainAddFn, ORT_CustomOpDomain_Add)(domain, &EMD_OP)))
    return st;
  if ((st = ORT_FN(api, OrtCustomOpDomainAddFn, ORT_CustomOpDomain_Add)(domain, &CODE_OP)))
    return st;
  return ORT_FN(api, OrtAddCustomOpDomainFn, ORT_AddCustomOpDomain)(options, domain);
}
