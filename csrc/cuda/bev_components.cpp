// CUDA glue of bev_components: the roots of the components from the union-find kernels
// (bev_components_kernel.cu), then numbered in order with a cumulative sum over each mask's
// roots. No value is read on the host.
#include <ATen/ATen.h>
#include <c10/core/DeviceGuard.h>
#include <torch/library.h>

#include <climits>

#include "checks.h"
#include "cuda/kernels.h"
#include "cuda/runtime.h"
#include "cuda/stream.h"

namespace t3fast {
namespace {

constexpr const char* kOp = "bev_components";

std::tuple<at::Tensor, at::Tensor> bev_components_cuda(const at::Tensor& mask) {
  check_bev_mask(mask, kOp);
  const int64_t B = mask.size(0), X = mask.size(1), Y = mask.size(2);
  T3FAST_CHECK(B * X * Y < INT_MAX, kOp, "mask must have fewer than 2^31 cells on CUDA, got ",
               mask.sizes());
  const c10::DeviceGuard device_guard(mask.device());
  const at::Tensor m = mask.contiguous();
  const auto longs = m.options().dtype(at::kLong);
  if (m.numel() == 0) return {at::zeros({B, X, Y}, longs), at::zeros({B}, longs)};
  at::Tensor parent = at::empty({B * X * Y}, m.options().dtype(at::kInt));
  check_launch(cuda::bev_component_roots(m.data_ptr<bool>(), B, static_cast<int>(X),
                                         static_cast<int>(Y), parent.data_ptr<int>(),
                                         current_stream(m.get_device())),
               kOp);
  // a root is its own parent; its number is how many roots its mask has up to it
  const at::Tensor root = parent.eq(at::arange(B * X * Y, parent.options()));
  const at::Tensor rank = root.view({B, X * Y}).cumsum(1);
  const at::Tensor labels =
      at::where(m.view(-1), rank.view(-1).index_select(0, parent.clamp_min(0)), 0);
  return {labels.view({B, X, Y}), rank.select(1, X * Y - 1).contiguous()};
}

}  // namespace

TORCH_LIBRARY_IMPL(t3fast, CUDA, m) { m.impl("bev_components", &bev_components_cuda); }

}  // namespace t3fast
