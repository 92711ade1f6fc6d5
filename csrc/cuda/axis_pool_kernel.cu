// axis_pool on CUDA: the three axis means of a volume [B, C, X, Y, Z] in one read, and the
// backward in one write.
//
// Forward design
// --------------
// Block (bc, chunk) reduces the x-slabs [x0, x0 + x_chunk) of one (b, c) volume. The work goes
// tile by tile: y_tile rows of Z values (about 2048 contiguous values, 8 per thread), and for
// each tile the block walks over its x-slabs:
//   * the tile is read once, coalesced, into shared memory (`tile` [y_tile][Z + 1]; the odd
//     row length keeps the row-wise reads below free of bank conflicts);
//   * xy (mean over z) is complete per row: one thread per row sums it and writes it;
//   * xz (mean over y) needs all rows: work items (segment, z) sum every S-th row of column z
//     into a per-block accumulator `xz_part` [x_chunk][S * Z] in shared memory, finished
//     (summed over the S segments, in order) after the last tile;
//   * yz (mean over x) is a running sum per tile element over the block's x-slabs; each
//     thread owns the same elements in every slab, so it lives in shared memory (`yz_part`)
//     without any synchronisation.
// With one chunk per (b, c) the block writes yz directly. Otherwise the volume's x range is
// split over several blocks (enough blocks for the GPU when B * C is small, and x_chunk <= 16
// x-slabs to bound `xz_part`): each block writes its partial yz sums to a workspace
// [B*C][chunks][Y*Z] and a second kernel adds the chunks in a fixed order. This keeps the
// result deterministic (no float atomics) at the cost of re-reading chunks/X of the volume's
// size; the number of chunks is capped at X / 8 for that reason.
//
// Backward: block (bc, x) writes the slab grad[b, c, x, :, :] from the row grad_xy[b, c, x, :],
// the row grad_xz[b, c, x, :] and the plane grad_yz[b, c, :, :] (all small and L2 resident):
// one coalesced write of the volume gradient, 32-bit index arithmetic inside the slab.
#include "cuda/kernels.h"

#include <climits>

namespace t3fast {
namespace cuda {
namespace {

constexpr int kThreads = 256;
constexpr int64_t kTileValues = 2048;   // values of a y-tile (8 per thread)
constexpr int64_t kMaxXzPart = 4096;    // bound of x_chunk * S * Z (16 KB of fp32)
constexpr int64_t kMinXChunk = 8;       // x-slabs per block at least, when x allows it
constexpr int64_t kBlocksPerSm = 8;     // blocks to aim for, per SM

int64_t ceil_div(int64_t a, int64_t b) { return (a + b - 1) / b; }

// Segments of the column sums: threads working on the same z (S * Z <= kThreads when Z does).
int64_t column_segments(int64_t z, int64_t y_tile) {
  int64_t s = kThreads / z;
  if (s < 1) s = 1;
  return s < y_tile ? s : y_tile;
}

template <typename T>
__global__ void __launch_bounds__(kThreads)
    axis_pool_kernel(const T* __restrict__ volume, const int X, const int Y, const int Z,
                     const int x_chunk, const int num_chunks, const int y_tile, const int S,
                     T* __restrict__ xy, T* __restrict__ xz, T* __restrict__ yz,
                     acc_t<T>* __restrict__ workspace) {
  using A = acc_t<T>;
  extern __shared__ __align__(16) unsigned char smem[];
  A* tile = reinterpret_cast<A*>(smem);        // [y_tile][Z + 1]
  A* yz_part = tile + y_tile * (Z + 1);        // [y_tile * Z]
  A* xz_part = yz_part + y_tile * Z;           // [x_chunk][S * Z]

  const int64_t bc = blockIdx.x / num_chunks;
  const int chunk = static_cast<int>(blockIdx.x - bc * num_chunks);
  const int x0 = chunk * x_chunk;
  const int xs = min(x_chunk, X - x0);  // x-slabs of this block
  const int YZ = Y * Z;
  const int SZ = S * Z;
  const T* vol = volume + (bc * X + x0) * static_cast<int64_t>(YZ);

  // Every thread zeroes the xz_part entries it accumulates below (same ownership).
  for (int xl = 0; xl < xs; ++xl) {
    for (int w = threadIdx.x; w < SZ; w += kThreads) xz_part[xl * SZ + w] = A(0);
  }

  for (int y0 = 0; y0 < Y; y0 += y_tile) {
    const int rows = min(y_tile, Y - y0);
    const int n = rows * Z;  // tile values, contiguous in every slab from y0 * Z on
    for (int e = threadIdx.x; e < n; e += kThreads) yz_part[e] = A(0);
    for (int xl = 0; xl < xs; ++xl) {
      const T* src = vol + static_cast<int64_t>(xl) * YZ + y0 * Z;
      __syncthreads();  // the previous tile is no longer read
      for (int e = threadIdx.x; e < n; e += kThreads) {
        const A v = to_acc(src[e]);
        const int r = e / Z;
        tile[r * (Z + 1) + (e - r * Z)] = v;
        yz_part[e] += v;
      }
      __syncthreads();
      const int64_t x = x0 + xl;
      for (int r = threadIdx.x; r < rows; r += kThreads) {
        A sum = A(0);
        for (int k = 0; k < Z; ++k) sum += tile[r * (Z + 1) + k];
        xy[(bc * X + x) * Y + y0 + r] = from_acc<T>(sum / static_cast<A>(Z));
      }
      for (int w = threadIdx.x; w < SZ; w += kThreads) {
        const int seg = w / Z;
        const int k = w - seg * Z;
        A sum = A(0);
        for (int r = seg; r < rows; r += S) sum += tile[r * (Z + 1) + k];
        xz_part[xl * SZ + w] += sum;
      }
    }
    // This tile's sums over the block's x-slabs (own elements: no barrier needed).
    if (num_chunks == 1) {
      T* dst = yz + bc * YZ + y0 * Z;
      for (int e = threadIdx.x; e < n; e += kThreads) {
        dst[e] = from_acc<T>(yz_part[e] / static_cast<A>(X));
      }
    } else {
      A* dst = workspace + (bc * num_chunks + chunk) * static_cast<int64_t>(YZ) + y0 * Z;
      for (int e = threadIdx.x; e < n; e += kThreads) dst[e] = yz_part[e];
    }
  }

  __syncthreads();  // xz_part complete
  for (int i = threadIdx.x; i < xs * Z; i += kThreads) {
    const int xl = i / Z;
    const int k = i - xl * Z;
    A sum = A(0);
    for (int seg = 0; seg < S; ++seg) sum += xz_part[xl * SZ + seg * Z + k];
    xz[(bc * X + x0 + xl) * Z + k] = from_acc<T>(sum / static_cast<A>(Y));
  }
}

// yz = (sum over chunks of the partial sums, in chunk order) / X.
template <typename T>
__global__ void __launch_bounds__(kThreads)
    axis_pool_finish_kernel(const acc_t<T>* __restrict__ workspace, const int64_t planes,
                            const int64_t YZ, const int num_chunks, const int X,
                            T* __restrict__ yz) {
  using A = acc_t<T>;
  const int64_t n = planes * YZ;
  for (int64_t i = static_cast<int64_t>(blockIdx.x) * kThreads + threadIdx.x; i < n;
       i += static_cast<int64_t>(gridDim.x) * kThreads) {
    const int64_t bc = i / YZ;
    const int64_t e = i - bc * YZ;
    const A* src = workspace + bc * num_chunks * YZ + e;
    A sum = A(0);
    for (int c = 0; c < num_chunks; ++c) sum += src[c * YZ];
    yz[i] = from_acc<T>(sum / static_cast<A>(X));
  }
}

template <typename T>
__global__ void __launch_bounds__(kThreads)
    axis_pool_backward_kernel(const T* __restrict__ gxy, const T* __restrict__ gxz,
                              const T* __restrict__ gyz, const int X, const int Y, const int Z,
                              T* __restrict__ grad) {
  using A = acc_t<T>;
  const int64_t slab = blockIdx.x;  // (b, c, x)
  const int64_t bc = slab / X;
  const int YZ = Y * Z;
  const T* row_xy = gxy + slab * Y;
  const T* row_xz = gxz + slab * Z;
  const T* plane_yz = gyz + bc * YZ;
  T* out = grad + slab * YZ;
  for (int e = threadIdx.x; e < YZ; e += kThreads) {
    const int y = e / Z;
    const int z = e - y * Z;
    const A v = to_acc(row_xy[y]) / static_cast<A>(Z) + to_acc(row_xz[z]) / static_cast<A>(Y) +
                to_acc(plane_yz[e]) / static_cast<A>(X);
    out[e] = from_acc<T>(v);
  }
}

}  // namespace

AxisPoolPlan axis_pool_plan(int64_t batch, int64_t channels, int64_t x, int64_t y, int64_t z,
                            int num_sms, bool double_precision) {
  AxisPoolPlan plan{};
  if (batch * channels * x * y * z == 0) return plan;
  const int64_t planes = batch * channels;
  plan.y_tile = kTileValues / z;
  if (plan.y_tile < 1) plan.y_tile = 1;
  if (plan.y_tile > y) plan.y_tile = y;
  const int64_t S = column_segments(z, plan.y_tile);

  // Chunks per (b, c): enough blocks to fill the GPU, at most x / kMinXChunk of them, and
  // x-slabs per block bounded by the size of xz_part.
  int64_t chunks = ceil_div(kBlocksPerSm * (num_sms > 0 ? num_sms : 1), planes);
  const int64_t max_chunks = x / kMinXChunk > 1 ? x / kMinXChunk : 1;
  if (chunks > max_chunks) chunks = max_chunks;
  plan.x_chunk = ceil_div(x, chunks);
  const int64_t max_x_chunk = kMaxXzPart / (S * z) > 1 ? kMaxXzPart / (S * z) : 1;
  if (plan.x_chunk > max_x_chunk) plan.x_chunk = max_x_chunk;
  plan.num_chunks = ceil_div(x, plan.x_chunk);
  plan.workspace_elems = plan.num_chunks > 1 ? planes * plan.num_chunks * y * z : 0;

  const size_t values = plan.y_tile * (z + 1) + plan.y_tile * z + plan.x_chunk * S * z;
  plan.shared_bytes = values * (double_precision ? sizeof(double) : sizeof(float));
  return plan;
}

template <typename T>
cudaError_t axis_pool_forward(const T* volume, int64_t batch, int64_t channels, int64_t x,
                              int64_t y, int64_t z, const AxisPoolPlan& plan, T* xy, T* xz,
                              T* yz, acc_t<T>* workspace, cudaStream_t stream) {
  const int64_t planes = batch * channels;
  if (planes * x * y * z == 0) return cudaSuccess;
  if (x > INT_MAX || y * z > INT_MAX || planes * plan.num_chunks > INT_MAX) {
    return cudaErrorInvalidValue;
  }
  auto* kernel = axis_pool_kernel<T>;
  cudaError_t err = cudaFuncSetAttribute(kernel, cudaFuncAttributeMaxDynamicSharedMemorySize,
                                         static_cast<int>(plan.shared_bytes));
  if (err != cudaSuccess) return err;
  const int S = static_cast<int>(column_segments(z, plan.y_tile));
  kernel<<<static_cast<unsigned>(planes * plan.num_chunks), kThreads, plan.shared_bytes,
           stream>>>(volume, static_cast<int>(x), static_cast<int>(y), static_cast<int>(z),
                     static_cast<int>(plan.x_chunk), static_cast<int>(plan.num_chunks),
                     static_cast<int>(plan.y_tile), S, xy, xz, yz, workspace);
  err = cudaGetLastError();
  if (err != cudaSuccess || plan.num_chunks == 1) return err;
  const int64_t n = planes * y * z;
  const int64_t blocks = ceil_div(n, kThreads) < 65536 ? ceil_div(n, kThreads) : 65536;
  axis_pool_finish_kernel<T><<<static_cast<unsigned>(blocks), kThreads, 0, stream>>>(
      workspace, planes, y * z, static_cast<int>(plan.num_chunks), static_cast<int>(x), yz);
  return cudaGetLastError();
}

template <typename T>
cudaError_t axis_pool_backward(const T* grad_xy, const T* grad_xz, const T* grad_yz,
                               int64_t batch, int64_t channels, int64_t x, int64_t y, int64_t z,
                               T* grad_volume, cudaStream_t stream) {
  const int64_t slabs = batch * channels * x;
  if (slabs * y * z == 0) return cudaSuccess;
  if (slabs > INT_MAX || y * z > INT_MAX) return cudaErrorInvalidValue;
  axis_pool_backward_kernel<T><<<static_cast<unsigned>(slabs), kThreads, 0, stream>>>(
      grad_xy, grad_xz, grad_yz, static_cast<int>(x), static_cast<int>(y), static_cast<int>(z),
      grad_volume);
  return cudaGetLastError();
}

#define T3FAST_INSTANTIATE(T)                                                                   \
  template cudaError_t axis_pool_forward<T>(const T*, int64_t, int64_t, int64_t, int64_t,       \
                                            int64_t, const AxisPoolPlan&, T*, T*, T*,           \
                                            acc_t<T>*, cudaStream_t);                            \
  template cudaError_t axis_pool_backward<T>(const T*, const T*, const T*, int64_t, int64_t,    \
                                             int64_t, int64_t, int64_t, T*, cudaStream_t);

T3FAST_INSTANTIATE(float)
T3FAST_INSTANTIATE(double)
T3FAST_INSTANTIATE(__half)
T3FAST_INSTANTIATE(__nv_bfloat16)

#undef T3FAST_INSTANTIATE

}  // namespace cuda
}  // namespace t3fast
