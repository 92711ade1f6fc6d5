// CUDA kernels of draw_boxes: one thread per (volume, box, window column) marks the voxels its
// box covers with the box's number (an atomic maximum, so the last box wins, as on the CPU),
// then one thread per voxel writes the winning box's label. The footprint test rounds every
// product and sum on its own (no fused multiply-add), as the CPU and the reference do.
#include <cuda_runtime.h>

#include <cstdint>

#include "cuda/kernels.h"

namespace t3fast {
namespace cuda {
namespace {

constexpr int kThreads = 256;

__global__ void cover_kernel(const double* boxes, const int64_t* levels, bool per_volume,
                             int64_t batch, int count, int x, int y, int z, double lower_x,
                             double lower_y, double voxel, int reach, int* winner) {
  const int side = 2 * reach + 1;
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i >= batch * count * side * side) return;
  const int cell = static_cast<int>(i % (side * side));
  const int64_t nm = i / (side * side);
  const int m = static_cast<int>(nm % count);
  const int64_t n = nm / count;
  const int dr = cell / side - reach, dc = cell % side - reach;
  const double* box = boxes + nm * 6;
  const int64_t k = per_volume ? nm : m;  // the box's levels
  const int z0 = static_cast<int>(max(levels[2 * k], int64_t{0}));
  const int z1 = static_cast<int>(min(levels[2 * k + 1], static_cast<int64_t>(z)));
  if (z0 >= z1) return;
  const double bx = box[0], by = box[1], c = box[2], s = box[3];
  const int64_t r = static_cast<int64_t>(floor(__ddiv_rn(__dsub_rn(bx, lower_x), voxel))) + dr;
  const int64_t col = static_cast<int64_t>(floor(__ddiv_rn(__dsub_rn(by, lower_y), voxel))) + dc;
  if (r < 0 || r >= x || col < 0 || col >= y) return;
  const double dx =
      __dsub_rn(__dadd_rn(lower_x, __dmul_rn(voxel, __dadd_rn(static_cast<double>(r), 0.5))), bx);
  const double dy =
      __dsub_rn(__dadd_rn(lower_y, __dmul_rn(voxel, __dadd_rn(static_cast<double>(col), 0.5))), by);
  const double along = __dadd_rn(__dmul_rn(c, dx), __dmul_rn(s, dy));
  const double across = __dadd_rn(__dmul_rn(-s, dx), __dmul_rn(c, dy));
  const bool inside = (dr == 0 && dc == 0) || (fabs(along) <= box[4] && fabs(across) <= box[5]);
  if (!inside) return;
  int* column = winner + ((n * x + r) * y + col) * z;
  for (int level = z0; level < z1; ++level) atomicMax(column + level, m + 1);
}

__global__ void paint_kernel(const int* winner, const uint8_t* labels, int64_t labels_stride,
                             int64_t volume_voxels, int64_t voxels, uint8_t* out) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i < voxels && winner[i] > 0) out[i] = labels[i / volume_voxels * labels_stride + winner[i] - 1];
}

}  // namespace

cudaError_t draw_boxes(const double* boxes, const int64_t* levels, const uint8_t* labels,
                       bool per_volume, int64_t batch, int count, int x, int y, int z,
                       double lower_x, double lower_y, double voxel, int reach, int* winner,
                       uint8_t* out, cudaStream_t stream) {
  const int64_t side = 2 * static_cast<int64_t>(reach) + 1;
  const int64_t threads = batch * count * side * side, voxels = batch * x * y * z;
  if (threads == 0 || voxels == 0) return cudaSuccess;
  cover_kernel<<<static_cast<unsigned>((threads + kThreads - 1) / kThreads), kThreads, 0,
                 stream>>>(boxes, levels, per_volume, batch, count, x, y, z, lower_x, lower_y,
                           voxel, reach, winner);
  paint_kernel<<<static_cast<unsigned>((voxels + kThreads - 1) / kThreads), kThreads, 0,
                 stream>>>(winner, labels, per_volume ? count : 0,
                           static_cast<int64_t>(x) * y * z, voxels, out);
  return cudaGetLastError();
}

}  // namespace cuda
}  // namespace t3fast
