// CUDA glue of group_norm_silu and its backward: argument checks (shared with the CPU),
// allocation, dtype dispatch and launches of the kernels in group_norm_silu_kernel.cu.
#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <c10/core/DeviceGuard.h>
#include <torch/library.h>

#include <cmath>
#include <tuple>

#include "checks.h"
#include "cuda/kernels.h"
#include "cuda/runtime.h"
#include "cuda/scalar_types.h"
#include "cuda/stream.h"

namespace t3fast {
namespace {

constexpr const char* kOp = "group_norm_silu";
constexpr const char* kOpBwd = "group_norm_silu_backward";

std::tuple<at::Tensor, at::Tensor, at::Tensor> group_norm_silu_cuda(
    const at::Tensor& input, const at::Tensor& weight, const at::Tensor& bias, int64_t groups,
    double eps, const c10::optional<at::Tensor>& residual) {
  const GroupNormShape s = check_group_norm_silu(input, weight, bias, residual, groups, eps, kOp);
  const c10::DeviceGuard device_guard(input.device());
  const at::Tensor x = input.detach().contiguous();
  const at::Tensor w = weight.detach().contiguous(), b = bias.detach().contiguous();
  const at::Tensor r = residual.has_value() ? residual->detach().contiguous() : at::Tensor();
  at::Tensor out = at::empty_like(x);
  const auto acc = x.options().dtype(accumulation_dtype(x));
  at::Tensor mean = at::empty({s.B, s.G}, acc), rstd = at::empty({s.B, s.G}, acc);
  if (s.S == 0) {  // an empty group: its mean is undefined (as group_norm's)
    mean.fill_(NAN);
    rstd.fill_(NAN);
    return {out, mean, rstd};
  }
  at::Tensor workspace = at::empty({s.B * s.C * cuda::group_norm_silu_chunks(s.S) * 2}, acc);
  const cudaStream_t stream = current_stream(x.get_device());
  cudaError_t err = cudaSuccess;
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, x.scalar_type(), "group_norm_silu_cuda",
                                  [&] {
    using T = cuda_type_t<scalar_t>;
    using A = cuda::acc_t<T>;
    err = cuda::group_norm_silu_forward<T>(
        ptr<const T>(x), ptr<const T>(w), ptr<const T>(b), r.defined() ? ptr<const T>(r) : nullptr,
        s.B, s.C, s.S, s.G, eps, ptr<T>(out), ptr<A>(mean), ptr<A>(rstd), ptr<A>(workspace), stream);
  });
  check_launch(err, kOp);
  return {out, mean, rstd};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> group_norm_silu_backward_cuda(
    const at::Tensor& grad, const at::Tensor& input, const at::Tensor& weight,
    const at::Tensor& bias, const c10::optional<at::Tensor>& residual, const at::Tensor& mean,
    const at::Tensor& rstd, int64_t groups) {
  const GroupNormShape s = check_group_norm_silu_backward(grad, input, weight, bias, residual, mean,
                                                          rstd, groups, kOpBwd);
  const c10::DeviceGuard device_guard(input.device());
  const at::Tensor g = grad.detach().contiguous(), x = input.detach().contiguous();
  const at::Tensor w = weight.detach().contiguous(), b = bias.detach().contiguous();
  const at::Tensor r = residual.has_value() ? residual->detach().contiguous() : at::Tensor();
  const at::Tensor m = mean.detach().contiguous(), rs = rstd.detach().contiguous();
  at::Tensor grad_input = at::empty_like(x);
  at::Tensor grad_residual = r.defined() ? at::empty_like(r) : at::empty({0}, x.options());
  const auto acc = x.options().dtype(accumulation_dtype(x));
  at::Tensor row_sums = at::zeros({s.B, s.C, 2}, acc);
  const int64_t chunks = cuda::group_norm_silu_chunks(s.S);
  if (s.S > 0 && s.B > 0) {
    at::Tensor workspace = at::empty({s.B * s.C * chunks * 2}, acc);
    const cudaStream_t stream = current_stream(x.get_device());
    cudaError_t err = cudaSuccess;
    AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, x.scalar_type(),
                                    "group_norm_silu_backward_cuda", [&] {
      using T = cuda_type_t<scalar_t>;
      using A = cuda::acc_t<T>;
      err = cuda::group_norm_silu_backward<T>(
          ptr<const T>(g), ptr<const T>(x), ptr<const T>(w), ptr<const T>(b),
          r.defined() ? ptr<const T>(r) : nullptr, ptr<const A>(m), ptr<const A>(rs), s.B, s.C,
          s.S, s.G, ptr<T>(grad_input), r.defined() ? ptr<T>(grad_residual) : nullptr,
          ptr<A>(row_sums), ptr<A>(workspace), stream);
    });
    check_launch(err, kOpBwd);
  }
  // the weight's and bias' gradients: each row's sums added over the batch
  const at::Tensor totals = row_sums.sum(0);
  return {grad_input, totals.select(1, 1).to(w.scalar_type()).contiguous(),
          totals.select(1, 0).to(b.scalar_type()).contiguous(), grad_residual};
}

}  // namespace

TORCH_LIBRARY_IMPL(t3fast, CUDA, m) {
  m.impl("group_norm_silu", &group_norm_silu_cuda);
  m.impl("group_norm_silu_backward", &group_norm_silu_backward_cuda);
}

}  // namespace t3fast
