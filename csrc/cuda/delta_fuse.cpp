// CUDA glue of delta_fuse and its backward: argument checks (shared with the CPU), allocation,
// dtype dispatch and launches of the kernels in delta_fuse_kernel.cu.
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

constexpr const char* kOp = "delta_fuse";
constexpr const char* kOpBwd = "delta_fuse_backward";

// The kernels count channels with 32-bit integers.
void check_channels(const at::Tensor& weight, const char* op) {
  T3FAST_CHECK(weight.size(0) <= INT_MAX && weight.size(1) <= INT_MAX, op,
               "weight must have fewer than 2^31 channels on CUDA, got shape ", weight.sizes());
}

at::Tensor delta_fuse_cuda(const at::Tensor& delta, const at::Tensor& prev,
                           const at::Tensor& weight, const c10::optional<at::Tensor>& bias) {
  const DeltaFuseShape s = check_delta_fuse(delta, prev, weight, bias, kOp);
  const int64_t B = s.B, C = s.C, Cin = s.C_in, HW = s.H * s.W;
  check_channels(weight, kOp);
  const c10::DeviceGuard device_guard(delta.device());
  const at::Tensor d = delta.detach().contiguous();
  const at::Tensor pv = prev.detach().contiguous();
  const at::Tensor w = weight.detach().contiguous();
  const at::Tensor b = bias.has_value() ? bias->detach().contiguous() : at::Tensor();
  at::Tensor out = at::empty(d.sizes(), d.options());
  if (out.numel() == 0) return out;
  const cudaStream_t stream = current_stream(d.get_device());
  cudaError_t err = cudaSuccess;
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, d.scalar_type(), "delta_fuse_cuda",
                                  [&] {
    using T = cuda_type_t<scalar_t>;
    err = cuda::delta_fuse_forward<T>(ptr<const T>(d), ptr<const T>(pv), ptr<const T>(w),
                                      b.defined() ? ptr<const T>(b) : nullptr, B,
                                      static_cast<int>(C), static_cast<int>(Cin), HW, ptr<T>(out),
                                      stream);
  });
  check_launch(err, kOp);
  return out;
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> delta_fuse_backward_cuda(
    const at::Tensor& grad_out, const at::Tensor& prev, const at::Tensor& weight) {
  const DeltaFuseShape s = check_delta_fuse_backward(grad_out, prev, weight, kOpBwd);
  const int64_t B = s.B, C = s.C, Cin = s.C_in, HW = s.H * s.W;
  check_channels(weight, kOpBwd);
  const c10::DeviceGuard device_guard(prev.device());
  const bool dbl = prev.scalar_type() == at::kDouble;
  const at::Tensor g = grad_out.detach().contiguous();
  const at::Tensor pv = prev.detach().contiguous();
  const at::Tensor w = weight.detach().contiguous();
  at::Tensor grad_prev = at::empty(pv.sizes(), pv.options());
  const auto acc_opts = pv.options().dtype(accumulation_dtype(pv));
  at::Tensor gw = at::zeros({C, Cin}, acc_opts);
  at::Tensor gb = at::zeros({C}, acc_opts);
  if (B * HW > 0) {
    const int available =
        device_attribute(cudaDevAttrMaxSharedMemoryPerBlockOptin, pv.get_device(), kOpBwd);
    const size_t need = cuda::delta_fuse_backward_min_shared_bytes(
        static_cast<int>(C), static_cast<int>(Cin), dbl);
    T3FAST_CHECK(need <= static_cast<size_t>(available), kOpBwd, "C + C_in = ", C + Cin,
                 " channels need ", need, " bytes of shared memory per block in ",
                 pv.scalar_type(), " but the device offers ", available);
    const cudaStream_t stream = current_stream(pv.get_device());
    cudaError_t err = cudaSuccess;
    AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, pv.scalar_type(),
                                    "delta_fuse_backward_cuda", [&] {
      using T = cuda_type_t<scalar_t>;
      using A = cuda::acc_t<T>;
      err = cuda::delta_fuse_backward<T>(ptr<const T>(g), ptr<const T>(pv), ptr<const T>(w), B,
                                         static_cast<int>(C), static_cast<int>(Cin), HW,
                                         ptr<T>(grad_prev), ptr<A>(gw), ptr<A>(gb), stream);
    });
    check_launch(err, kOpBwd);
  }
  return {grad_prev, gw.to(prev.scalar_type()), gb.to(prev.scalar_type())};
}

}  // namespace

TORCH_LIBRARY_IMPL(t3fast, CUDA, m) {
  m.impl("delta_fuse", &delta_fuse_cuda);
  m.impl("delta_fuse_backward", &delta_fuse_backward_cuda);
}

}  // namespace t3fast
