// CPU kernel of draw_boxes: each volume of the batch is copied, then its boxes are painted in
// order (a later box overwrites an earlier one), each over the (2 reach + 1)^2 columns around its
// centre column. The footprint test is the reference's float64 arithmetic, operation for
// operation (no fused multiply-add: each product and sum rounded on its own), so the same
// columns are drawn.
#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>

#include "checks.h"

namespace t3fast {
namespace {

constexpr const char* kOp = "draw_boxes";

struct Grid {
  int64_t X, Y, Z;
  double lower_x, lower_y, voxel;
};

// One box (x, y, cos, sin, half length, half width) into one volume [X, Y, Z].
__attribute__((optimize("fp-contract=off"))) void draw_box(const double* box, int64_t bottom, int64_t top, uint8_t label, const Grid& g,
              int64_t reach, uint8_t* out) {
  const double x = box[0], y = box[1], c = box[2], s = box[3], half_l = box[4], half_w = box[5];
  const int64_t z0 = std::max<int64_t>(bottom, 0), z1 = std::min<int64_t>(top, g.Z);
  if (z0 >= z1) return;
  const auto row0 = static_cast<int64_t>(std::floor((x - g.lower_x) / g.voxel));
  const auto col0 = static_cast<int64_t>(std::floor((y - g.lower_y) / g.voxel));
  for (int64_t dr = -reach; dr <= reach; ++dr) {
    const int64_t r = row0 + dr;
    if (r < 0 || r >= g.X) continue;
    const double dx = g.lower_x + g.voxel * (static_cast<double>(r) + 0.5) - x;
    for (int64_t dc = -reach; dc <= reach; ++dc) {
      const int64_t col = col0 + dc;
      if (col < 0 || col >= g.Y) continue;
      const double dy = g.lower_y + g.voxel * (static_cast<double>(col) + 0.5) - y;
      const double along = c * dx + s * dy, across = -s * dx + c * dy;
      // the column under the centre always: small agents never vanish
      const bool inside =
          (dr == 0 && dc == 0) || (std::fabs(along) <= half_l && std::fabs(across) <= half_w);
      if (!inside) continue;
      uint8_t* column = out + (r * g.Y + col) * g.Z;
      for (int64_t z = z0; z < z1; ++z) column[z] = label;
    }
  }
}

at::Tensor draw_boxes_cpu(const at::Tensor& volume, const at::Tensor& boxes,
                          const at::Tensor& levels, const at::Tensor& labels,
                          c10::ArrayRef<double> lower, double voxel_size, int64_t reach) {
  check_draw_boxes(volume, boxes, levels, labels, lower, voxel_size, reach, kOp);
  at::Tensor out = volume.contiguous().clone();
  const at::Tensor b = boxes.contiguous(), lv = levels.contiguous(), lb = labels.contiguous();
  const int64_t B = out.size(0), M = b.size(1);
  const Grid g{out.size(1), out.size(2), out.size(3), lower[0], lower[1], voxel_size};
  const double* pb = b.data_ptr<double>();
  const int64_t* pv = lv.data_ptr<int64_t>();
  const uint8_t* pl = lb.data_ptr<uint8_t>();
  uint8_t* po = out.data_ptr<uint8_t>();
  const int64_t stride = lv.dim() == 3 ? M : 0;  // boxes of levels and labels per volume
  at::parallel_for(0, B, 1, [&](int64_t b0, int64_t b1) {
    for (int64_t n = b0; n < b1; ++n) {
      for (int64_t m = 0; m < M; ++m) {
        const int64_t k = n * stride + m;
        draw_box(pb + (n * M + m) * 6, pv[2 * k], pv[2 * k + 1], pl[k], g, reach,
                 po + n * g.X * g.Y * g.Z);
      }
    }
  });
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(t3fast, CPU, m) { m.impl("draw_boxes", &draw_boxes_cpu); }

}  // namespace t3fast
