// CUDA glue of label_conv3d: argument checks (shared with the CPU), allocation, dtype dispatch
// and the launch of the kernel in label_conv3d_kernel.cu.
#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <c10/core/DeviceGuard.h>
#include <torch/library.h>

#include <climits>

#include "checks.h"
#include "cuda/kernels.h"
#include "cuda/runtime.h"
#include "cuda/scalar_types.h"
#include "cuda/stream.h"
#include "label_types.h"

namespace t3fast {
namespace {

constexpr const char* kOp = "label_conv3d";
constexpr const char* kOpBwd = "label_conv3d_backward";

template <typename T>
cudaError_t launch(const at::Tensor& labels, const at::Tensor& table, const LabelConvShape& s,
                   at::Tensor& out, cudaStream_t stream) {
  const int X = static_cast<int>(s.X), Y = static_cast<int>(s.Y), Z = static_cast<int>(s.Z);
  const int K = static_cast<int>(s.K), C = static_cast<int>(s.C);
  return dispatch_label_type(labels.scalar_type(), [&](auto label) {
    using L = decltype(label);
    return cuda::label_conv3d_forward<T>(ptr<const L>(labels), ptr<const T>(table), s.B, X, Y, Z,
                                         K, C, ptr<T>(out), stream);
  });
}

at::Tensor label_conv3d_cuda(const at::Tensor& labels, const at::Tensor& table) {
  const LabelConvShape s = check_label_conv3d(labels, table, kOp);
  T3FAST_CHECK(s.X * s.Y * s.Z <= INT_MAX && s.K <= INT_MAX && s.C <= INT_MAX, kOp,
               "labels must have X * Y * Z < 2^31 and table fewer than 2^31 classes and "
               "channels on CUDA, got labels ", labels.sizes(), " and table ", table.sizes());
  const c10::DeviceGuard device_guard(labels.device());
  const at::Tensor l = labels.contiguous(), t = table.detach().contiguous();
  at::Tensor out = at::empty({s.B, s.C, s.X, s.Y, s.Z}, t.options());
  if (out.numel() == 0) return out;
  const cudaStream_t stream = current_stream(l.get_device());
  cudaError_t err = cudaSuccess;
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, t.scalar_type(), "label_conv3d_cuda",
                                  [&] {
    err = launch<cuda_type_t<scalar_t>>(l, t, s, out, stream);
  });
  check_launch(err, kOp);
  return out;
}

// The table gradient as the weight gradient of the convolution of the one-hot labels (cuDNN's
// wgrad: a scatter into 27 * K * C entries would serialise on the atomics of the common
// classes). Labels outside [0, K) are masked out rather than checked (no host sync).
at::Tensor label_conv3d_backward_cuda(const at::Tensor& grad, const at::Tensor& labels,
                                      int64_t classes) {
  const LabelConvShape s = check_label_conv3d_backward(grad, labels, classes, kOpBwd);
  const c10::DeviceGuard device_guard(grad.device());
  const at::Tensor g = grad.detach().contiguous();
  if (g.numel() == 0) return at::zeros({27, s.K, s.C}, g.options());
  const at::Tensor ids = labels.to(at::kLong);
  const at::Tensor inside = (ids >= 0).logical_and(ids < classes).to(g.scalar_type());
  const at::Tensor one_hot = at::zeros({s.B, s.K, s.X, s.Y, s.Z}, g.options())
                                 .scatter_(1, ids.clamp(0, classes - 1).unsqueeze(1),
                                           inside.unsqueeze(1));
  const at::Tensor weight = at::empty({s.C, s.K, 3, 3, 3}, g.options());
  const auto grads = at::convolution_backward(
      g, one_hot, weight, /*bias_sizes=*/c10::nullopt, /*stride=*/{1, 1, 1}, /*padding=*/{1, 1, 1},
      /*dilation=*/{1, 1, 1}, /*transposed=*/false, /*output_padding=*/{0, 0, 0}, /*groups=*/1,
      /*output_mask=*/{false, true, false});
  // [C, K, dx, dy, dz] -> [27, K, C]
  return std::get<1>(grads).permute({2, 3, 4, 1, 0}).reshape({27, s.K, s.C}).contiguous();
}

}  // namespace

TORCH_LIBRARY_IMPL(t3fast, CUDA, m) {
  m.impl("label_conv3d", &label_conv3d_cuda);
  m.impl("label_conv3d_backward", &label_conv3d_backward_cuda);
}

}  // namespace t3fast
