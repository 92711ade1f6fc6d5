// CUDA glue of draw_boxes: argument checks (shared with the CPU), the copy of the volumes to
// draw into, the winner buffer and the launch of the kernels in draw_boxes_kernel.cu.
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

constexpr const char* kOp = "draw_boxes";

at::Tensor draw_boxes_cuda(const at::Tensor& volume, const at::Tensor& boxes,
                           const at::Tensor& levels, const at::Tensor& labels,
                           c10::ArrayRef<double> lower, double voxel_size, int64_t reach) {
  check_draw_boxes(volume, boxes, levels, labels, lower, voxel_size, reach, kOp);
  T3FAST_CHECK(boxes.size(1) < INT_MAX && reach < 4096 && volume.size(1) < INT_MAX &&
                   volume.size(2) < INT_MAX && volume.size(3) < INT_MAX,
               kOp, "too many boxes, too far a reach or too large a volume for CUDA: boxes ",
               boxes.sizes(), ", reach ", reach, ", volume ", volume.sizes());
  const c10::DeviceGuard device_guard(volume.device());
  at::Tensor out = volume.contiguous().clone();
  if (out.numel() == 0 || boxes.size(1) == 0) return out;
  const at::Tensor b = boxes.contiguous(), lv = levels.contiguous(), lb = labels.contiguous();
  at::Tensor winner = at::zeros(out.sizes(), out.options().dtype(at::kInt));
  check_launch(cuda::draw_boxes(b.data_ptr<double>(), lv.data_ptr<int64_t>(),
                                lb.data_ptr<uint8_t>(), lv.dim() == 3, out.size(0),
                                static_cast<int>(b.size(1)), static_cast<int>(out.size(1)),
                                static_cast<int>(out.size(2)), static_cast<int>(out.size(3)),
                                lower[0], lower[1], voxel_size, static_cast<int>(reach),
                                winner.data_ptr<int>(), out.data_ptr<uint8_t>(),
                                current_stream(out.get_device())),
               kOp);
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(t3fast, CUDA, m) { m.impl("draw_boxes", &draw_boxes_cuda); }

}  // namespace t3fast
