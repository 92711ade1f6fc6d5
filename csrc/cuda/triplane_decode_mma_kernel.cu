// triplane_decode's fused forward with the MLP on tensor cores (WMMA: mma.sync on sm_80 and
// sm_90), in half, bfloat16 or TF32 operands with fp32 accumulation.
//
// Design
// ------
// A block of 8 warps owns a tile of P = 16 * MT consecutive query points (MT = 8, 4 or 2
// row tiles of 16 points) and takes them from coordinates to logits or labels without
// touching global memory in between:
//   1. the points' coordinates and batch index go to shared memory (fp32);
//   2. the features (the three planes' bilinear samples summed, then the encoding) are
//      computed in fp32 and stored, rounded to the operand type, in the activation tile
//      `act` [P][row] (row-major per point, the A operand of the products; columns up to
//      the padded width are zeros);
//   3. every layer is out[P, N] = act[P, K] W^T: the warps form a WM x WN grid over the
//      output tiles (WN = the column tiles, up to 8; the remaining warps split the rows),
//      each warp keeps at most 8 accumulator tiles of 16 x 16 in registers, reads A from
//      shared memory and B (the zero-padded weights, prepared once per call by the host
//      glue) straight from global memory, where every block re-reads them from L2; with up
//      to 2 column tiles per warp the B tiles of the next depth are loaded while the current
//      ones multiply (two register sets), hiding the L2 latency. After a
//      barrier every warp moves its tiles through a per-warp scratch tile, adds the bias and
//      applies the ReLU in fp32 and writes them back into `act`, rounded to the operand type
//      (in place: all reads of the layer's input are done);
//   4. the last layer's values stay fp32 (in a float view of the same buffer) and are
//      written as logits or reduced to the first-maximum class per point.
// MT is the largest of 8, 4, 2 for which the widest layer fits in 8 warps x 8 tiles, as the
// SIMT kernel's point tiles (128 points up to width 128, 64 up to 256, 32 up to 512).
#include <mma.h>

#include <climits>

#include "cuda/kernels.h"
#include "cuda/triplane_sample.cuh"

namespace t3fast {
namespace cuda {
namespace {

constexpr int kThreads = 256;
constexpr int kWarps = kThreads / 32;
constexpr int kTile = 16;         // rows and columns of an MMA tile
constexpr int kWarpTiles = 8;     // accumulator tiles per warp and layer at most
constexpr int kMaxRowTiles = 8;   // row tiles per block (MT) at most

__host__ __device__ constexpr int round_up(int v, int m) { return (v + m - 1) / m * m; }

// Column tiles of the widest layer output.
__host__ __device__ inline int widest_col_tiles(const int* widths, int num_layers) {
  int col_tiles = 1;
  for (int i = 1; i <= num_layers; ++i) {
    const int t = round_up(widths[i], kTile) / kTile;
    col_tiles = t > col_tiles ? t : col_tiles;
  }
  return col_tiles;
}

// Row tiles per block for these widths: the most whose widest layer fits in kWarps x
// kWarpTiles accumulator tiles.
__host__ __device__ inline int row_tiles_for(const int* widths, int num_layers) {
  const int col_tiles = widest_col_tiles(widths, num_layers);
  int mt = kMaxRowTiles;
  while (mt > 2 && mt * col_tiles > kWarps * kWarpTiles) mt /= 2;
  return mt;
}

// Where the block's buffers lie in shared memory.
struct MmaLayout {
  int row;           // elements per point row of `act` (padded widest width + skew)
  int logit_row;     // floats per point row of the logits view (odd: conflict-free columns)
  size_t act_bytes;  // the activation tile, or its float logits view, whichever is larger
  size_t total;      // act, per-warp scratch tiles, batch indices, coordinates
};

__host__ __device__ inline MmaLayout mma_layout(const int* widths, int num_layers, int points,
                                                int operand_bytes) {
  int widest = kTile;
  for (int i = 0; i <= num_layers; ++i) widest = widths[i] > widest ? widths[i] : widest;
  MmaLayout l;
  // A skew of 16 bytes per row: the 16 rows of an A tile start in different bank groups,
  // and every tile stays 32-byte aligned as the WMMA loads require.
  l.row = round_up(widest, kTile) + 16 / operand_bytes;
  l.logit_row = round_up(widths[num_layers], kTile) + 1;
  const size_t act = static_cast<size_t>(points) * l.row * operand_bytes;
  const size_t logits = static_cast<size_t>(points) * l.logit_row * sizeof(float);
  l.act_bytes = static_cast<size_t>(round_up(static_cast<int>(act > logits ? act : logits), 128));
  l.total = l.act_bytes + kWarps * kTile * kTile * sizeof(float) +
            static_cast<size_t>(points) * (sizeof(int64_t) + 3 * sizeof(float));
  return l;
}

// The device code uses WMMA types that exist from sm_80 on; the launcher never runs it on
// an older device (the glue picks the SIMT kernel there).
#if !defined(__CUDA_ARCH__) || __CUDA_ARCH__ >= 800
namespace wmma = nvcuda::wmma;

// Operand type of the fragments, their k depth, and the rounding of fp32 values to operands.
template <typename Mma>
struct MmaOps;

template <>
struct MmaOps<__half> {
  using Operand = __half;
  static constexpr int kK = 16;
  static __device__ __forceinline__ __half store(float v) { return __float2half_rn(v); }
  template <typename F>
  static __device__ __forceinline__ void round(F&) {}
};

template <>
struct MmaOps<__nv_bfloat16> {
  using Operand = __nv_bfloat16;
  static constexpr int kK = 16;
  static __device__ __forceinline__ __nv_bfloat16 store(float v) {
    return __float2bfloat16_rn(v);
  }
  template <typename F>
  static __device__ __forceinline__ void round(F&) {}
};

template <>
struct MmaOps<Tf32> {
  using Operand = wmma::precision::tf32;
  static constexpr int kK = 8;
  static __device__ __forceinline__ float store(float v) { return v; }
  // TF32 fragments are loaded as float and must be rounded before the product.
  template <typename F>
  static __device__ __forceinline__ void round(F& f) {
#pragma unroll
    for (int i = 0; i < f.num_elements; ++i) f.x[i] = wmma::__float_to_tf32(f.x[i]);
  }
};

// One layer's sizes. The warps form a grid of WM x WN (WN = kWarps * MTW / MT); warp
// (wm, wn) owns the row tiles wm * MTW + i (i < MTW) and the column tiles wn + WN * j
// (j < NTW, those below col_tiles: narrower layers leave some warps idle).
struct LayerShape {
  int in_pad;     // K, a multiple of kTile
  int out;        // real outputs; the padded ones are written as zeros
  int col_tiles;  // padded outputs / kTile
  bool relu;
  bool last;      // write fp32 logits instead of operands
};

template <typename Mma, int MT, int MTW, int NTW>
__device__ __forceinline__ void mma_layer(const mma_storage_t<Mma>* __restrict__ weight,
                                          const float* __restrict__ bias, const LayerShape& s,
                                          mma_storage_t<Mma>* act, int row, float* logits,
                                          int logit_row, float* scratch) {
  using Ops = MmaOps<Mma>;
  using Operand = typename Ops::Operand;
  constexpr int kK = Ops::kK;
  constexpr int WN = kWarps * MTW / MT;
  static_assert(MT % MTW == 0 && WN * (MT / MTW) == kWarps && MTW * NTW <= kWarpTiles,
                "bad warp grid");
  const int warp = threadIdx.x / 32;
  const int lane = threadIdx.x % 32;
  const int wn_index = warp % WN;
  const int first_tile = (warp / WN) * MTW;

  wmma::fragment<wmma::accumulator, kTile, kTile, kK, float> acc[MTW][NTW];
  {
#pragma unroll
    for (int i = 0; i < MTW; ++i) {
#pragma unroll
      for (int j = 0; j < NTW; ++j) wmma::fill_fragment(acc[i][j], 0.f);
    }
    using BFragment = wmma::fragment<wmma::matrix_b, kTile, kTile, kK, Operand, wmma::col_major>;
    // The warp's B tiles of depth k0 (from L2): column n of W^T is row n of W, and W
    // [out_pad, in_pad] row-major is W^T column-major.
    const auto load_b = [&](BFragment (&b)[NTW], int k0) {
#pragma unroll
      for (int j = 0; j < NTW; ++j) {
        const int n = wn_index + WN * j;
        if (n < s.col_tiles) {
          wmma::load_matrix_sync(b[j], weight + static_cast<int64_t>(n) * kTile * s.in_pad + k0,
                                 s.in_pad);
          Ops::round(b[j]);
        }
      }
    };
    const auto multiply = [&](const BFragment (&b)[NTW], int k0) {
#pragma unroll
      for (int i = 0; i < MTW; ++i) {
        wmma::fragment<wmma::matrix_a, kTile, kTile, kK, Operand, wmma::row_major> a;
        wmma::load_matrix_sync(a, act + (first_tile + i) * kTile * row + k0, row);
        Ops::round(a);
#pragma unroll
        for (int j = 0; j < NTW; ++j) {
          if (wn_index + WN * j < s.col_tiles) wmma::mma_sync(acc[i][j], a, b[j], acc[i][j]);
        }
      }
    };
    if constexpr (NTW <= 2) {
      // Two sets of B tiles: the next depth's are loaded while the current ones multiply, so
      // the L2 latency hides behind the products.
      BFragment b0[NTW], b1[NTW];
      load_b(b0, 0);
      for (int k0 = 0; k0 < s.in_pad; k0 += 2 * kK) {
        const bool second = k0 + kK < s.in_pad;  // in_pad / kK may be odd
        if (second) load_b(b1, k0 + kK);
        multiply(b0, k0);
        if (!second) break;
        if (k0 + 2 * kK < s.in_pad) load_b(b0, k0 + 2 * kK);
        multiply(b1, k0 + kK);
      }
    } else {
      // 4 column tiles per warp (layers wider than 256): a second set would spill
      BFragment b[NTW];
      for (int k0 = 0; k0 < s.in_pad; k0 += kK) {
        load_b(b, k0);
        multiply(b, k0);
      }
    }
  }
  __syncthreads();  // every warp has read the layer's input: overwrite it

  {
    float* tile = scratch + warp * kTile * kTile;
    const int r = lane / 2;
    const int c0 = (lane % 2) * (kTile / 2);
#pragma unroll
    for (int i = 0; i < MTW; ++i) {
#pragma unroll
      for (int j = 0; j < NTW; ++j) {
        const int n = wn_index + WN * j;
        if (n >= s.col_tiles) continue;
        wmma::store_matrix_sync(tile, acc[i][j], kTile, wmma::mem_row_major);
        __syncwarp();
        const int p = (first_tile + i) * kTile + r;
#pragma unroll
        for (int c = 0; c < kTile / 2; ++c) {
          const int o = n * kTile + c0 + c;
          float v = tile[r * kTile + c0 + c] + bias[o];
          if (s.relu && v < 0.f) v = 0.f;  // keeps NaN, like torch.relu
          if (o >= s.out) v = 0.f;          // padded outputs: zeros, whatever the inputs held
          if (s.last) {
            logits[p * logit_row + o] = v;
          } else {
            act[p * row + o] = Ops::store(v);
          }
        }
        __syncwarp();  // the tile is read before the next store_matrix_sync
      }
    }
  }
  __syncthreads();
}

template <typename T, typename Mma, int MT, int MTW, int NTW>
__device__ __forceinline__ void decode_tile(const Triplane<T>& planes, const Query<T>& query,
                                            const MmaMlp<mma_storage_t<Mma>>& mlp, T* logits,
                                            uint8_t* labels) {
  using S = mma_storage_t<Mma>;
  constexpr int P = MT * kTile;
  extern __shared__ __align__(128) unsigned char smem[];
  const MmaLayout lay = mma_layout(mlp.width, mlp.num_layers, P, sizeof(S));
  S* act = reinterpret_cast<S*>(smem);
  float* lg = reinterpret_cast<float*>(smem);  // the last layer's fp32 view of the same bytes
  float* scratch = reinterpret_cast<float*>(smem + lay.act_bytes);
  int64_t* batch_of = reinterpret_cast<int64_t*>(scratch + kWarps * kTile * kTile);
  float* coord = reinterpret_cast<float*>(batch_of + P);

  const int64_t total = planes.batch * query.num_points;
  const int64_t first = static_cast<int64_t>(blockIdx.x) * P;
  if (skip_dead_block(query, first, total, P, labels)) return;

  stage_points(query, first, total, P, kThreads, batch_of, coord);
  __syncthreads();

  // Consecutive threads take consecutive points of one feature: neighbouring plane taps.
  const int in0 = mlp.width[0];
  const int in0_pad = round_up(in0, kTile);
  for (int idx = threadIdx.x; idx < P * in0_pad; idx += kThreads) {
    const int p = idx % P;
    const int j = idx / P;
    const float v = mlp_input(planes, batch_of[p], j, in0, coord[3 * p], coord[3 * p + 1], coord[3 * p + 2]);
    act[p * lay.row + j] = MmaOps<Mma>::store(v);
  }
  __syncthreads();

  for (int l = 0; l < mlp.num_layers; ++l) {
    LayerShape s;
    s.in_pad = round_up(mlp.width[l], kTile);
    s.out = mlp.width[l + 1];
    s.col_tiles = round_up(s.out, kTile) / kTile;
    s.relu = l + 1 < mlp.num_layers;
    s.last = !s.relu;
    mma_layer<Mma, MT, MTW, NTW>(mlp.weight[l], mlp.bias[l], s, act, lay.row, lg, lay.logit_row,
                                 scratch);
  }

  const int classes = mlp.width[mlp.num_layers];
  if (logits != nullptr) {
    for (int idx = threadIdx.x; idx < P * classes; idx += kThreads) {
      const int p = idx / classes;
      const int o = idx - p * classes;
      const int64_t g = first + p;
      if (g < total) logits[g * classes + o] = from_acc<T>(lg[p * lay.logit_row + o]);
    }
  } else {
    for (int p = threadIdx.x; p < P; p += kThreads) {
      const int64_t g = first + p;
      if (g >= total) continue;
      // The argmax of the logits this kernel would write (rounded to T); first maximum
      // wins, NaN counts as the maximum.
      const float* row = lg + p * lay.logit_row;
      float best = to_acc(from_acc<T>(row[0]));
      int best_o = 0;
      for (int o = 1; o < classes; ++o) {
        const float v = to_acc(from_acc<T>(row[o]));
        if (v > best || (v != v && best == best)) {
          best = v;
          best_o = o;
        }
      }
      labels[g] = query_live(query, g) ? static_cast<uint8_t>(best_o) : uint8_t{0};
    }
  }
}
#endif  // !defined(__CUDA_ARCH__) || __CUDA_ARCH__ >= 800

template <typename T, typename Mma, int MT, int MTW, int NTW>
__global__ void __launch_bounds__(kThreads, 2)
    mma_decode_kernel(const __grid_constant__ Triplane<T> planes,
                      const __grid_constant__ Query<T> query,
                      // read in place (indexed by layer), never copied to local memory
                      const __grid_constant__ MmaMlp<mma_storage_t<Mma>> mlp,
                      T* __restrict__ logits, uint8_t* __restrict__ labels) {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ < 800
  __trap();  // never launched: the glue checks the compute capability
#else
  decode_tile<T, Mma, MT, MTW, NTW>(planes, query, mlp, logits, labels);
#endif
}

template <typename T, typename Mma, int MT, int MTW, int NTW>
cudaError_t launch_mma(const Triplane<T>& planes, const Query<T>& query,
                       const MmaMlp<mma_storage_t<Mma>>& mlp, T* logits, uint8_t* labels,
                       size_t smem, cudaStream_t stream) {
  const int64_t total = planes.batch * query.num_points;
  const int64_t blocks = (total + MT * kTile - 1) / (MT * kTile);
  if (blocks > INT_MAX) return cudaErrorInvalidConfiguration;
  auto* kernel = mma_decode_kernel<T, Mma, MT, MTW, NTW>;
  const cudaError_t err = cudaFuncSetAttribute(
      kernel, cudaFuncAttributeMaxDynamicSharedMemorySize, static_cast<int>(smem));
  if (err != cudaSuccess) return err;
  kernel<<<static_cast<unsigned>(blocks), kThreads, smem, stream>>>(planes, query, mlp, logits,
                                                                    labels);
  return cudaGetLastError();
}

}  // namespace

size_t triplane_decode_mma_shared_bytes(const int* widths, int num_layers, int operand_bytes) {
  const int points = row_tiles_for(widths, num_layers) * kTile;
  return mma_layout(widths, num_layers, points, operand_bytes).total;
}

template <typename T, typename Mma>
cudaError_t triplane_decode_forward_mma(const Triplane<T>& planes, const Query<T>& query,
                                        int pe_freqs, const MmaMlp<mma_storage_t<Mma>>& mlp,
                                        T* logits, uint8_t* labels, cudaStream_t stream) {
  (void)pe_freqs;  // the encoding's width is mlp.width[0] - planes.channels
  if (planes.batch * query.num_points == 0) return cudaSuccess;
  const int mt = row_tiles_for(mlp.width, mlp.num_layers);
  const size_t smem = triplane_decode_mma_shared_bytes(mlp.width, mlp.num_layers,
                                                       sizeof(mma_storage_t<Mma>));
  int device = 0;
  int optin = 0;
  cudaError_t err = cudaGetDevice(&device);
  if (err != cudaSuccess) return err;
  err = cudaDeviceGetAttribute(&optin, cudaDevAttrMaxSharedMemoryPerBlockOptin, device);
  if (err != cudaSuccess) return err;
  if (smem > static_cast<size_t>(optin)) return cudaErrorInvalidValue;
  // The warp grid of the widest layer (narrower layers leave warps idle). With 8 row tiles:
  // 4 x 2 tiles per warp up to 8 column tiles (each A tile read by 4 warps, each B tile by 2:
  // 48 fragment loads per depth instead of 72 with 8 x 1), 4 x 1 up to 4, then fewer rows per
  // warp; with 4 and 2 row tiles (wider layers) 4 x 2 and 2 x 4.
  const int col_tiles = widest_col_tiles(mlp.width, mlp.num_layers);
  if (mt == 4) return launch_mma<T, Mma, 4, 4, 2>(planes, query, mlp, logits, labels, smem, stream);
  if (mt == 2) return launch_mma<T, Mma, 2, 2, 4>(planes, query, mlp, logits, labels, smem, stream);
  if (col_tiles > 4) return launch_mma<T, Mma, 8, 4, 2>(planes, query, mlp, logits, labels, smem, stream);
  if (col_tiles > 2) return launch_mma<T, Mma, 8, 4, 1>(planes, query, mlp, logits, labels, smem, stream);
  if (col_tiles > 1) return launch_mma<T, Mma, 8, 2, 1>(planes, query, mlp, logits, labels, smem, stream);
  return launch_mma<T, Mma, 8, 1, 1>(planes, query, mlp, logits, labels, smem, stream);
}

#define T3FAST_INSTANTIATE(T, Mma)                                                       \
  template cudaError_t triplane_decode_forward_mma<T, Mma>(                              \
      const Triplane<T>&, const Query<T>&, int, const MmaMlp<mma_storage_t<Mma>>&, T*, \
      uint8_t*, cudaStream_t);

T3FAST_INSTANTIATE(float, Tf32)
T3FAST_INSTANTIATE(float, __half)
T3FAST_INSTANTIATE(float, __nv_bfloat16)
T3FAST_INSTANTIATE(__half, __half)
T3FAST_INSTANTIATE(__half, __nv_bfloat16)
T3FAST_INSTANTIATE(__nv_bfloat16, __half)
T3FAST_INSTANTIATE(__nv_bfloat16, __nv_bfloat16)

#undef T3FAST_INSTANTIATE

}  // namespace cuda
}  // namespace t3fast
