// How the CUDA glue hands torch tensors to the kernels: torch's scalar types as the CUDA
// types the kernels are written in, and tensor data as pointers to them.
#pragma once

#include <ATen/core/Tensor.h>
#include <c10/util/BFloat16.h>
#include <c10/util/Half.h>
#include <cuda_bf16.h>
#include <cuda_fp16.h>

#include <type_traits>

namespace t3fast {

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

}  // namespace t3fast
