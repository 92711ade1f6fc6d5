// Small helpers of the CUDA glue files (csrc/cuda/<op>.cpp).
//
// The stream comes from stream.cpp, the only file that includes c10/cuda headers, so that the
// other glue files compile against any torch build (the CPU wheels ship c10/cuda headers
// that do not compile) and can be syntax-checked on machines without a CUDA torch.
#pragma once

#include <ATen/core/Tensor.h>
#include <c10/util/BFloat16.h>
#include <c10/util/Half.h>
#include <cuda_bf16.h>
#include <cuda_fp16.h>
#include <cuda_runtime.h>

#include <type_traits>

#include "checks.h"

namespace t3fast {

// The current CUDA stream of a device (torch's, so kernels order with torch's own work).
cudaStream_t current_stream(int device_index);

// The CUDA type of a torch scalar type: at::Half -> __half, at::BFloat16 -> __nv_bfloat16,
// float and double unchanged (same size and bit layout).
template <typename S>
using cuda_type_t = std::conditional_t<
    std::is_same_v<S, c10::Half>, __half,
    std::conditional_t<std::is_same_v<S, c10::BFloat16>, __nv_bfloat16, S>>;

// A tensor's data as the kernel's element type.
template <typename T>
T* ptr(const at::Tensor& t) {
  return static_cast<T*>(t.data_ptr());
}

// Turns a launcher's CUDA error into an error naming the op.
inline void check_launch(cudaError_t err, const char* op) {
  T3FAST_CHECK(err == cudaSuccess, op, "CUDA kernel launch failed: ", cudaGetErrorString(err));
}

}  // namespace t3fast
