/* The small part of onnxruntime's C API that the custom-op library (ort_ops.c) uses, declared
 * here because the onnxruntime wheel ships no C headers. Checked against onnxruntime's
 * include/onnxruntime/core/session/onnxruntime_c_api.h (last at commit a437bfb0ed09, whose
 * ORT_API_VERSION is 23: every position and signature below, and OrtCustomOp's field order):
 *
 * - OrtApi is a table of function pointers whose positions are append-only (ABI-stable since
 *   version 1): the library reads the entries it needs by position from the table that
 *   OrtApiBase::GetApi(ORT_OPS_API_VERSION) returns, instead of declaring the whole struct.
 *   The positions below are those of the header's "Version 1" block (0..101), which no later
 *   version changes.
 * - OrtCustomOp is laid out field by field in declaration order; onnxruntime reads a field only
 *   when the op's `version` is at least the version that added it, so this declares the struct
 *   up to the fields of the newest header (1.2x) and the library fills the ones a version-19
 *   op has (KernelComputeV2 and CreateKernelV2 since 16, the start/end versions since 17).
 *
 * Nothing here links to libonnxruntime: every call goes through the table onnxruntime passes
 * to RegisterCustomOps.
 */
#ifndef TACTILE_ORT_API_H
#define TACTILE_ORT_API_H

#include <stddef.h>
#include <stdint.h>

/* The oldest onnxruntime the package supports (pyproject: onnxruntime>=1.19): its OrtApi
 * version is 19. A newer onnxruntime serves this version's table too. */
#define ORT_OPS_API_VERSION 19

typedef struct OrtStatus OrtStatus;
typedef struct OrtApi OrtApi;  /* opaque here: read through ort_fn() */
typedef struct OrtValue OrtValue;
typedef struct OrtSessionOptions OrtSessionOptions;
typedef struct OrtCustomOpDomain OrtCustomOpDomain;
typedef struct OrtKernelInfo OrtKernelInfo;
typedef struct OrtKernelContext OrtKernelContext;
typedef struct OrtTensorTypeAndShapeInfo OrtTensorTypeAndShapeInfo;
typedef struct OrtShapeInferContext OrtShapeInferContext;
struct OrtCustomOp;

typedef enum ONNXTensorElementDataType {
  ONNX_TENSOR_ELEMENT_DATA_TYPE_UNDEFINED = 0,
  ONNX_TENSOR_ELEMENT_DATA_TYPE_FLOAT = 1,
  ONNX_TENSOR_ELEMENT_DATA_TYPE_INT64 = 7,
  ONNX_TENSOR_ELEMENT_DATA_TYPE_DOUBLE = 11
} ONNXTensorElementDataType;

typedef enum OrtErrorCode {
  ORT_OK = 0,
  ORT_FAIL = 1,
  ORT_INVALID_ARGUMENT = 2,
  ORT_RUNTIME_EXCEPTION = 6
} OrtErrorCode;

typedef enum OrtCustomOpInputOutputCharacteristic {
  INPUT_OUTPUT_REQUIRED = 0,
  INPUT_OUTPUT_OPTIONAL,
  INPUT_OUTPUT_VARIADIC
} OrtCustomOpInputOutputCharacteristic;

typedef enum OrtMemType { OrtMemTypeDefault = 0 } OrtMemType;

typedef struct OrtApiBase {
  const OrtApi *(*GetApi)(uint32_t version);
  const char *(*GetVersionString)(void);
} OrtApiBase;

/* Positions in the OrtApi table (the header's declaration order, from 0). */
enum {
  ORT_CreateStatus = 0,
  ORT_CreateCustomOpDomain = 26,
  ORT_CustomOpDomain_Add = 27,
  ORT_AddCustomOpDomain = 28,
  ORT_GetTensorMutableData = 51,
  ORT_GetTensorElementType = 60,
  ORT_GetDimensionsCount = 61,
  ORT_GetDimensions = 62,
  ORT_GetTensorTypeAndShape = 65,
  ORT_KernelInfoGetAttribute_int64 = 86,
  ORT_KernelContext_GetInputCount = 88,
  ORT_KernelContext_GetInput = 90,
  ORT_KernelContext_GetOutput = 91,
  ORT_ReleaseStatus = 93,
  ORT_ReleaseTensorTypeAndShapeInfo = 99
};

/* The signatures of those entries. */
typedef OrtStatus *(*OrtCreateStatusFn)(OrtErrorCode code, const char *msg);
typedef OrtStatus *(*OrtCreateCustomOpDomainFn)(const char *domain, OrtCustomOpDomain **out);
typedef OrtStatus *(*OrtCustomOpDomainAddFn)(OrtCustomOpDomain *domain,
                                             const struct OrtCustomOp *op);
typedef OrtStatus *(*OrtAddCustomOpDomainFn)(OrtSessionOptions *options,
                                             OrtCustomOpDomain *domain);
typedef OrtStatus *(*OrtGetTensorMutableDataFn)(OrtValue *value, void **out);
typedef OrtStatus *(*OrtGetTensorElementTypeFn)(const OrtTensorTypeAndShapeInfo *info,
                                                ONNXTensorElementDataType *out);
typedef OrtStatus *(*OrtGetDimensionsCountFn)(const OrtTensorTypeAndShapeInfo *info, size_t *out);
typedef OrtStatus *(*OrtGetDimensionsFn)(const OrtTensorTypeAndShapeInfo *info, int64_t *dims,
                                         size_t n);
typedef OrtStatus *(*OrtGetTensorTypeAndShapeFn)(const OrtValue *value,
                                                 OrtTensorTypeAndShapeInfo **out);
typedef OrtStatus *(*OrtKernelInfoGetAttributeInt64Fn)(const OrtKernelInfo *info,
                                                       const char *name, int64_t *out);
typedef OrtStatus *(*OrtKernelContextGetInputCountFn)(const OrtKernelContext *ctx, size_t *out);
typedef OrtStatus *(*OrtKernelContextGetInputFn)(const OrtKernelContext *ctx, size_t index,
                                                 const OrtValue **out);
typedef OrtStatus *(*OrtKernelContextGetOutputFn)(OrtKernelContext *ctx, size_t index,
                                                  const int64_t *dims, size_t n,
                                                  OrtValue **out);
typedef void (*OrtReleaseStatusFn)(OrtStatus *status);
typedef void (*OrtReleaseTensorTypeAndShapeInfoFn)(OrtTensorTypeAndShapeInfo *info);

/* Entry `pos` of the table `api` (an array of function pointers), as a function of `type`. */
typedef void (*OrtAnyFn)(void);
#define ORT_FN(api, type, pos) ((type)(((const OrtAnyFn *)(const void *)(api))[pos]))

/* OrtCustomOp, in the header's field order; the comments give the version that added a field. */
typedef struct OrtCustomOp {
  uint32_t version;
  void *(*CreateKernel)(const struct OrtCustomOp *op, const OrtApi *api,
                        const OrtKernelInfo *info);
  const char *(*GetName)(const struct OrtCustomOp *op);
  const char *(*GetExecutionProviderType)(const struct OrtCustomOp *op);
  ONNXTensorElementDataType (*GetInputType)(const struct OrtCustomOp *op, size_t index);
  size_t (*GetInputTypeCount)(const struct OrtCustomOp *op);
  ONNXTensorElementDataType (*GetOutputType)(const struct OrtCustomOp *op, size_t index);
  size_t (*GetOutputTypeCount)(const struct OrtCustomOp *op);
  void (*KernelCompute)(void *op_kernel, OrtKernelContext *context);
  void (*KernelDestroy)(void *op_kernel);
  /* 8 */
  OrtCustomOpInputOutputCharacteristic (*GetInputCharacteristic)(const struct OrtCustomOp *op,
                                                                 size_t index);
  OrtCustomOpInputOutputCharacteristic (*GetOutputCharacteristic)(const struct OrtCustomOp *op,
                                                                  size_t index);
  /* 13 */
  OrtMemType (*GetInputMemoryType)(const struct OrtCustomOp *op, size_t index);
  /* 14 */
  int (*GetVariadicInputMinArity)(const struct OrtCustomOp *op);
  int (*GetVariadicInputHomogeneity)(const struct OrtCustomOp *op);
  int (*GetVariadicOutputMinArity)(const struct OrtCustomOp *op);
  int (*GetVariadicOutputHomogeneity)(const struct OrtCustomOp *op);
  /* 16 */
  OrtStatus *(*CreateKernelV2)(const struct OrtCustomOp *op, const OrtApi *api,
                               const OrtKernelInfo *info, void **kernel);
  OrtStatus *(*KernelComputeV2)(void *op_kernel, OrtKernelContext *context);
  /* 17 */
  OrtStatus *(*InferOutputShapeFn)(const struct OrtCustomOp *op, OrtShapeInferContext *ctx);
  int (*GetStartVersion)(const struct OrtCustomOp *op);
  int (*GetEndVersion)(const struct OrtCustomOp *op);
  /* 18 */
  size_t (*GetMayInplace)(int **input_index, int **output_index);
  void (*ReleaseMayInplace)(int *input_index, int *output_index);
  /* 20 */
  size_t (*GetAliasMap)(int **input_index, int **output_index);
  void (*ReleaseAliasMap)(int *input_index, int *output_index);
} OrtCustomOp;

#endif
