// CUDA glue of matching_costs and its backward: argument checks (shared with the CPU),
// allocation, dtype dispatch and launches of the kernels in matching_costs_kernel.cu.
#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <c10/core/DeviceGuard.h>
#include <torch/library.h>

#include <climits>
#include <tuple>

#include "checks.h"
#include "cuda/kernels.h"
#include "cuda/runtime.h"
#include "cuda/scalar_types.h"
#include "cuda/stream.h"

namespace t3fast {
namespace {

constexpr const char* kOp = "matching_costs";
constexpr const char* kOpBwd = "matching_costs_backward";

// The kernels index channels, rows and columns with 32-bit integers.
void check_extents(const MatchingCostsShape& s, const at::Tensor& present, const char* op) {
  T3FAST_CHECK(s.C <= INT_MAX && s.H <= INT_MAX && s.W <= INT_MAX, op,
               "present must have fewer than 2^31 channels, rows and columns on CUDA, got shape ",
               present.sizes());
}

at::Tensor matching_costs_cuda(const at::Tensor& present, const at::Tensor& previous,
                               int64_t radius) {
  const MatchingCostsShape s = check_matching_costs(present, previous, radius, kOp);
  check_extents(s, present, kOp);
  const c10::DeviceGuard device_guard(present.device());
  const at::Tensor p = present.detach().contiguous();
  const at::Tensor q = previous.detach().contiguous();
  at::Tensor out = at::empty({s.B, s.shifts, s.H, s.W}, p.options());
  if (out.numel() == 0) return out;
  const cudaStream_t stream = current_stream(p.get_device());
  cudaError_t err = cudaSuccess;
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, p.scalar_type(), "matching_costs_cuda",
                                  [&] {
    using T = cuda_type_t<scalar_t>;
    err = cuda::matching_costs_forward<T>(ptr<const T>(p), ptr<const T>(q), s.B,
                                          static_cast<int>(s.C), static_cast<int>(s.H),
                                          static_cast<int>(s.W), static_cast<int>(radius),
                                          ptr<T>(out), stream);
  });
  check_launch(err, kOp);
  return out;
}

std::tuple<at::Tensor, at::Tensor> matching_costs_backward_cuda(const at::Tensor& grad,
                                                                 const at::Tensor& present,
                                                                 const at::Tensor& previous,
                                                                 int64_t radius) {
  const MatchingCostsShape s =
      check_matching_costs_backward(grad, present, previous, radius, kOpBwd);
  check_extents(s, present, kOpBwd);
  const c10::DeviceGuard device_guard(present.device());
  const at::Tensor g = grad.detach().contiguous();
  const at::Tensor p = present.detach().contiguous();
  const at::Tensor q = previous.detach().contiguous();
  at::Tensor grad_present = at::empty(p.sizes(), p.options());
  at::Tensor grad_previous = at::empty(q.sizes(), q.options());
  if (p.numel() == 0) return {grad_present, grad_previous};
  const cudaStream_t stream = current_stream(p.get_device());
  cudaError_t err = cudaSuccess;
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, p.scalar_type(),
                                  "matching_costs_backward_cuda", [&] {
    using T = cuda_type_t<scalar_t>;
    err = cuda::matching_costs_backward<T>(ptr<const T>(g), ptr<const T>(p), ptr<const T>(q), s.B,
                                           static_cast<int>(s.C), static_cast<int>(s.H),
                                           static_cast<int>(s.W), static_cast<int>(radius),
                                           ptr<T>(grad_present), ptr<T>(grad_previous), stream);
  });
  check_launch(err, kOpBwd);
  return {grad_present, grad_previous};
}

}  // namespace

TORCH_LIBRARY_IMPL(t3fast, CUDA, m) {
  m.impl("matching_costs", &matching_costs_cuda);
  m.impl("matching_costs_backward", &matching_costs_backward_cuda);
}

}  // namespace t3fast
