// CUDA glue of box_fit: argument checks (shared with the CPU), the scratch of samples and the
// launch of the kernels in box_fit_kernel.cu.
#include <ATen/ATen.h>
#include <c10/core/DeviceGuard.h>
#include <torch/library.h>

#include <climits>
#include <tuple>

#include "checks.h"
#include "cuda/kernels.h"
#include "cuda/runtime.h"
#include "cuda/stream.h"

namespace t3fast {
namespace {

constexpr const char* kOp = "box_fit";

std::tuple<at::Tensor, at::Tensor> box_fit_cuda(
    const at::Tensor& ids, const at::Tensor& track, const at::Tensor& centroid,
    const at::Tensor& poses, const at::Tensor& start, const at::Tensor& reach,
    c10::ArrayRef<double> lower, double voxel_size, int64_t window, int64_t near, int64_t iters,
    double lr, c10::ArrayRef<double> softness, double accel_prior) {
  check_box_fit(ids, track, centroid, poses, start, reach, lower, voxel_size, window, near, iters,
                lr, softness, kOp);
  const int64_t B = ids.size(0), T = ids.size(1), n = track.size(1);
  T3FAST_CHECK(B * n * T < INT_MAX && ids.size(2) < INT_MAX && ids.size(3) < INT_MAX &&
                   iters < INT_MAX,
               kOp, "too many windows, agents, frames or iterations for CUDA: ids ", ids.sizes(),
               ", track ", track.sizes(), ", iters ", iters);
  const c10::DeviceGuard device_guard(ids.device());
  const at::Tensor id = ids.contiguous(), tr = track.contiguous(), ce = centroid.contiguous(),
                   po = poses.contiguous(), st = start.contiguous(), re = reach.contiguous();
  at::Tensor params = at::empty_like(st), iou = at::empty_like(re);
  if (B * n == 0) return {params, iou};
  const int64_t records = cuda::box_fit_scratch(B, n, T, window);
  at::Tensor samples = at::empty({records * 4}, st.options().dtype(at::kFloat));
  at::Tensor sampled = at::empty({B * n * T}, st.options().dtype(at::kInt));
  const cuda::BoxFitArgs args{id.data_ptr<int64_t>(), tr.data_ptr<int64_t>(), ce.data_ptr<double>(),
                              po.data_ptr<double>(), st.data_ptr<double>(), re.data_ptr<double>(),
                              static_cast<int>(B), static_cast<int>(n), static_cast<int>(T),
                              static_cast<int>(id.size(2)), static_cast<int>(id.size(3)), lower[0],
                              lower[1], voxel_size, static_cast<int>(window), static_cast<int>(near),
                              static_cast<int>(iters), lr, softness[0], softness[1], accel_prior};
  check_launch(cuda::box_fit(args, samples.data_ptr<float>(), sampled.data_ptr<int>(),
                             params.data_ptr<double>(), iou.data_ptr<double>(),
                             current_stream(ids.get_device())),
               kOp);
  return {params, iou};
}

}  // namespace

TORCH_LIBRARY_IMPL(t3fast, CUDA, m) { m.impl("box_fit", &box_fit_cuda); }

}  // namespace t3fast
