// CUDA glue of axis_pool and its backward: argument checks (shared with the CPU), allocation,
// dtype dispatch and launches of the kernels in axis_pool_kernel.cu.
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

constexpr const char* kOp = "axis_pool";
constexpr const char* kOpBwd = "axis_pool_backward";

std::tuple<at::Tensor, at::Tensor, at::Tensor> axis_pool_cuda(const at::Tensor& volume) {
  const VolumeShape s = check_volume(volume, kOp);
  const int64_t B = s.B, C = s.C, X = s.X, Y = s.Y, Z = s.Z;
  T3FAST_CHECK(X <= INT_MAX && Y * Z <= INT_MAX, kOp,
               "volume must have X < 2^31 and Y * Z < 2^31 on CUDA, got ", volume.sizes());
  const c10::DeviceGuard device_guard(volume.device());
  const at::Tensor v = volume.detach().contiguous();
  at::Tensor xy = at::empty({B, C, X, Y}, v.options());
  at::Tensor xz = at::empty({B, C, X, Z}, v.options());
  at::Tensor yz = at::empty({B, C, Y, Z}, v.options());
  if (v.numel() == 0) return {xy, xz, yz};

  const int device = v.get_device();
  const bool dbl = v.scalar_type() == at::kDouble;
  const cuda::AxisPoolPlan plan = cuda::axis_pool_plan(
      B, C, X, Y, Z, device_attribute(cudaDevAttrMultiProcessorCount, device, kOp), dbl);
  const int available = device_attribute(cudaDevAttrMaxSharedMemoryPerBlockOptin, device, kOp);
  T3FAST_CHECK(plan.shared_bytes <= static_cast<size_t>(available), kOp, "volume ",
               volume.sizes(), " needs ", plan.shared_bytes,
               " bytes of shared memory per block (it grows with Z) but the device offers ",
               available);
  at::Tensor workspace;
  if (plan.workspace_elems > 0) {
    workspace =
        at::empty({plan.workspace_elems}, v.options().dtype(accumulation_dtype(v)));
  }
  const cudaStream_t stream = current_stream(device);
  cudaError_t err = cudaSuccess;
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, v.scalar_type(), "axis_pool_cuda",
                                  [&] {
    using T = cuda_type_t<scalar_t>;
    using A = cuda::acc_t<T>;
    err = cuda::axis_pool_forward<T>(ptr<const T>(v), B, C, X, Y, Z, plan, ptr<T>(xy), ptr<T>(xz),
                                     ptr<T>(yz), workspace.defined() ? ptr<A>(workspace) : nullptr,
                                     stream);
  });
  check_launch(err, kOp);
  return {xy, xz, yz};
}

at::Tensor axis_pool_backward_cuda(const at::Tensor& grad_xy, const at::Tensor& grad_xz,
                                   const at::Tensor& grad_yz) {
  const VolumeShape s = check_planes(grad_xy, grad_xz, grad_yz, kPlaneGrads, kOpBwd);
  const int64_t B = s.B, C = s.C, X = s.X, Y = s.Y, Z = s.Z;
  T3FAST_CHECK(B * C * X <= INT_MAX && Y * Z <= INT_MAX, kOpBwd,
               "the volume gradient must have B * C * X < 2^31 and Y * Z < 2^31 on CUDA, got ",
               "[", B, ", ", C, ", ", X, ", ", Y, ", ", Z, "]");
  const c10::DeviceGuard device_guard(grad_xy.device());
  const at::Tensor gxy = grad_xy.detach().contiguous(), gxz = grad_xz.detach().contiguous(),
                   gyz = grad_yz.detach().contiguous();
  at::Tensor out = at::empty({B, C, X, Y, Z}, gxy.options());
  if (out.numel() == 0) return out;
  const cudaStream_t stream = current_stream(gxy.get_device());
  cudaError_t err = cudaSuccess;
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, gxy.scalar_type(),
                                  "axis_pool_backward_cuda", [&] {
    using T = cuda_type_t<scalar_t>;
    err = cuda::axis_pool_backward<T>(ptr<const T>(gxy), ptr<const T>(gxz), ptr<const T>(gyz), B,
                                      C, X, Y, Z, ptr<T>(out), stream);
  });
  check_launch(err, kOpBwd);
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(t3fast, CUDA, m) {
  m.impl("axis_pool", &axis_pool_cuda);
  m.impl("axis_pool_backward", &axis_pool_backward_cuda);
}

}  // namespace t3fast
