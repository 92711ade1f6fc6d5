// label_conv3d on CUDA: one thread per output voxel, its C-vector accumulated in registers
// kChunk channels at a time over the 27 taps (the 27 labels it reads are shared with its
// neighbours' threads through L1; the table is small and cached). Writes are coalesced: the
// threads of a warp hold consecutive voxels of one channel row.
#include "cuda/kernels.h"

namespace t3fast {
namespace cuda {
namespace {

constexpr int kThreads = 256;
constexpr int kChunk = 8;  // channels per pass: 8 accumulators per thread

template <typename T, typename L>
__global__ void __launch_bounds__(kThreads)
    label_conv3d_kernel(const L* __restrict__ labels, const T* __restrict__ table,
                        const int64_t voxels, const int X, const int Y, const int Z,
                        const int classes, const int channels, T* __restrict__ out) {
  using A = acc_t<T>;
  const int64_t v = static_cast<int64_t>(blockIdx.x) * kThreads + threadIdx.x;
  if (v >= voxels) return;
  const int64_t volume = static_cast<int64_t>(X) * Y * Z;
  const int64_t b = v / volume;
  const int64_t local = v - b * volume;
  const int k = static_cast<int>(local % Z);
  const int j = static_cast<int>((local / Z) % Y);
  const int i = static_cast<int>(local / (static_cast<int64_t>(Y) * Z));
  const L* slab = labels + b * volume;
  T* dst = out + b * channels * volume + local;
  for (int c0 = 0; c0 < channels; c0 += kChunk) {
    const int n = min(kChunk, channels - c0);
    A acc[kChunk];
#pragma unroll
    for (int c = 0; c < kChunk; ++c) acc[c] = A(0);
    for (int dx = -1; dx <= 1; ++dx) {
      if (i + dx < 0 || i + dx >= X) continue;
      for (int dy = -1; dy <= 1; ++dy) {
        if (j + dy < 0 || j + dy >= Y) continue;
        const L* row = slab + (static_cast<int64_t>(i + dx) * Y + (j + dy)) * Z;
        for (int dz = -1; dz <= 1; ++dz) {
          if (k + dz < 0 || k + dz >= Z) continue;
          const int64_t label = static_cast<int64_t>(row[k + dz]);
          if (label < 0 || label >= classes) continue;
          const int tap = ((dx + 1) * 3 + (dy + 1)) * 3 + (dz + 1);
          const T* entry = table + (static_cast<int64_t>(tap) * classes + label) * channels + c0;
#pragma unroll
          for (int c = 0; c < kChunk; ++c) {
            if (c < n) acc[c] += to_acc(entry[c]);
          }
        }
      }
    }
#pragma unroll
    for (int c = 0; c < kChunk; ++c) {
      if (c < n) dst[(c0 + c) * volume] = from_acc<T>(acc[c]);
    }
  }
}

}  // namespace

template <typename T, typename L>
cudaError_t label_conv3d_forward(const L* labels, const T* table, int64_t batch, int x, int y,
                                 int z, int classes, int channels, T* out, cudaStream_t stream) {
  const int64_t voxels = batch * x * y * z;
  if (voxels == 0 || channels == 0) return cudaSuccess;
  const int64_t blocks = (voxels + kThreads - 1) / kThreads;
  label_conv3d_kernel<T, L><<<static_cast<unsigned>(blocks), kThreads, 0, stream>>>(
      labels, table, voxels, x, y, z, classes, channels, out);
  return cudaGetLastError();
}

#define T3FAST_INSTANTIATE(T, L)                                                              \
  template cudaError_t label_conv3d_forward<T, L>(const L*, const T*, int64_t, int, int, int, \
                                                  int, int, T*, cudaStream_t);
#define T3FAST_INSTANTIATE_LABELS(T) \
  T3FAST_INSTANTIATE(T, uint8_t)     \
  T3FAST_INSTANTIATE(T, int32_t)     \
  T3FAST_INSTANTIATE(T, int64_t)
T3FAST_INSTANTIATE_LABELS(float)
T3FAST_INSTANTIATE_LABELS(double)
T3FAST_INSTANTIATE_LABELS(__half)
T3FAST_INSTANTIATE_LABELS(__nv_bfloat16)
#undef T3FAST_INSTANTIATE_LABELS
#undef T3FAST_INSTANTIATE

}  // namespace cuda
}  // namespace t3fast
