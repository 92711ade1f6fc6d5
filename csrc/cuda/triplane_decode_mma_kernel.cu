// triplane_decode's fused forward with the MLP on tensor cores (WMMA: mma.sync on sm_80 and
// sm_90), in half, bfloat16 or TF32 operands with fp32 accumulation.
//
// Design
// ------
// A block of 8 warps owns a tile of P = 16 * MT consecutive query points and takes them from
// coordinates to logits or labels without touching global memory in between:
//   1. the points' coordinates and batch index go to shared memory (fp32);
//   2. the features (the three planes' bilinear samples summed, then the encoding) are
//      computed in fp32 and stored, rounded to the operand type, in the activation tile
//      `act` [P][row] (row-major per point, the A operand of the products; columns up to
//      the padded width are zeros);
//   3. every layer is out[P, N] = act[P, K] W^T with both operands in shared memory: the
//      layer's zero-padded weights W [N, K] (prepared once per call by the host glue) stream
//      from L2 through STAGES buffers holding 64 bytes of every row each (asynchronous copies,
//      cp.async, issued STAGES - 1 chunks ahead of the products, so that the L2 latency hides
//      behind them; the next layer's first chunks are issued before this layer's epilogue),
//      and all 8 warps read them. The warps form a WM x WN grid over the output tiles (WN =
//      the column tiles, up to 8; the remaining warps split the rows), each warp keeps up to
//      4 x 4 accumulator tiles of 16 x 16 in registers. After a barrier every warp moves its
//      tiles through a per-warp scratch tile, adds the bias and applies the ReLU in fp32 and
//      writes them back into `act`, rounded to the operand type, 16 bytes at a time (in place:
//      all reads of the layer's input are done);
//   4. the last layer's values stay fp32 (in a float view of the same buffer) and are
//      written as logits or reduced to the first-maximum class per point.
// Row tiles (mma_plan): 8, so that every weight byte read from L2 serves 128 points, while the
// widest layer fits 16 accumulator tiles per warp (256 outputs) and the block's shared memory
// an A100's 163 KB, else 4 (TF32 operands beyond 128 outputs, inputs wider than about 400);
// beyond 256 outputs 2, with two weight stages instead of three.
#include <cuda_pipeline.h>
#include <mma.h>

#include <climits>

#include "cuda/kernels.h"
#include "cuda/triplane_sample.cuh"

namespace t3fast {
namespace cuda {
namespace {

constexpr int kThreads = 256;
constexpr int kWarps = kThreads / 32;
constexpr int kTile = 16;  // rows and columns of an MMA tile
// Bytes of every weight row a pipeline stage holds, and their pitch in the stage buffer: a
// 16-byte skew puts the 8 rows a fragment load reads at once in different banks.
constexpr int kChunkBytes = 64;
constexpr int kStageRowBytes = kChunkBytes + 16;
constexpr int kCopiesPerRow = kChunkBytes / 16;  // 16-byte asynchronous copies

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

// How a block tiles the work (see the design).
struct MmaPlan {
  int row_tiles;  // MT: the block's points / 16
  int stages;     // weight chunks in flight
};

// Where the block's buffers lie in shared memory.
struct MmaLayout {
  int row;             // elements per point row of `act` (padded widest width + skew)
  int logit_row;       // floats per point row of the logits view (odd: conflict-free columns)
  size_t act_bytes;    // the activation tile, or its float logits view, whichever is larger
  size_t stage_bytes;  // one weight stage: the widest padded layer output x kStageRowBytes
  size_t total;        // act, weight stages, per-warp scratch tiles, batch indices, coordinates
};

__host__ __device__ inline MmaLayout mma_layout(const int* widths, int num_layers, int operand_bytes,
                                                MmaPlan plan) {
  const int points = plan.row_tiles * kTile;
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
  l.stage_bytes = static_cast<size_t>(widest_col_tiles(widths, num_layers)) * kTile * kStageRowBytes;
  l.total = l.act_bytes + plan.stages * l.stage_bytes + kWarps * kTile * kTile * sizeof(float) +
            static_cast<size_t>(points) * (sizeof(int64_t) + 3 * sizeof(float));
  return l;
}

// Shared memory a plan may take: an A100's opt-in limit per block (an H100 offers 227 KB).
constexpr size_t kPlanSmem = 163 * 1024;

// 8 row tiles (every weight byte read from L2 serves 128 points) while the widest layer fits
// 4 x 4 accumulator tiles per warp (256 outputs) and the buffers fit kPlanSmem, else 4; wider
// layers 2, with two weight stages.
__host__ __device__ inline MmaPlan mma_plan(const int* widths, int num_layers, int operand_bytes) {
  if (widest_col_tiles(widths, num_layers) <= 16) {
    for (int mt = 8; mt >= 4; mt /= 2) {
      const MmaPlan plan{mt, 3};
      if (mma_layout(widths, num_layers, operand_bytes, plan).total <= kPlanSmem) return plan;
    }
  }
  return {2, 2};
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
  static __device__ __forceinline__ unsigned bits(float v) { return __half_as_ushort(store(v)); }
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
  static __device__ __forceinline__ unsigned bits(float v) { return __bfloat16_as_ushort(store(v)); }
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

// Streams one layer's weights W [out_pad, in_pad] (row-major and zero-padded by the glue: W^T,
// the B operand, column-major) through the weight stages: chunk c holds the depths
// c * kDepth .. c * kDepth + kDepth - 1 of every row, in stage c % STAGES, one row every
// kStageRowBytes.
template <typename S, int STAGES>
struct WeightStream {
  static constexpr int kDepth = kChunkBytes / static_cast<int>(sizeof(S));
  const S* weight;
  int in_pad;
  int out_pad;
  unsigned char* stages;
  size_t stage_bytes;

  __device__ __forceinline__ int chunks() const { return (in_pad + kDepth - 1) / kDepth; }

  __device__ __forceinline__ const S* stage(int c) const {
    return reinterpret_cast<const S*>(stages + (c % STAGES) * stage_bytes);
  }

  // Every thread issues its share of chunk c's copies (none past the last chunk) and commits
  // them as one group, empty or not: all threads count the same groups.
  __device__ __forceinline__ void issue(int c) const {
    if (c < chunks()) {
      const int k0 = c * kDepth;
      // 4 copies per row, or 2 in the 16-deep last chunk of an in_pad that is an odd multiple of 16
      const int copies = min(kDepth, in_pad - k0) * static_cast<int>(sizeof(S)) / 16;
      unsigned char* dst = stages + (c % STAGES) * stage_bytes;
      const unsigned char* src = reinterpret_cast<const unsigned char*>(weight + k0);
      const int64_t src_row = static_cast<int64_t>(in_pad) * sizeof(S);
      for (int i = threadIdx.x; i < out_pad * kCopiesPerRow; i += kThreads) {
        const int n = i / kCopiesPerRow;
        const int piece = i % kCopiesPerRow;
        if (piece < copies) {
          __pipeline_memcpy_async(dst + n * kStageRowBytes + piece * 16, src + n * src_row + piece * 16, 16);
        }
      }
    }
    __pipeline_commit();
  }

  // The first STAGES - 1 chunks, issued ahead of the layer's products.
  __device__ __forceinline__ void prologue() const {
#pragma unroll
    for (int c = 0; c < STAGES - 1; ++c) issue(c);
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

// Eight fp32 values rounded to the operand type, stored in 16-byte words (dst 16-byte aligned).
template <typename Ops, typename S>
__device__ __forceinline__ void store_operands(S* dst, const float (&v)[8]) {
  if constexpr (sizeof(S) == 4) {  // TF32: stored as float, rounded when loaded
    float4 lo, hi;
    lo.x = v[0], lo.y = v[1], lo.z = v[2], lo.w = v[3];
    hi.x = v[4], hi.y = v[5], hi.z = v[6], hi.w = v[7];
    reinterpret_cast<float4*>(dst)[0] = lo;
    reinterpret_cast<float4*>(dst)[1] = hi;
  } else {
    uint4 word;
    word.x = Ops::bits(v[0]) | Ops::bits(v[1]) << 16;
    word.y = Ops::bits(v[2]) | Ops::bits(v[3]) << 16;
    word.z = Ops::bits(v[4]) | Ops::bits(v[5]) << 16;
    word.w = Ops::bits(v[6]) | Ops::bits(v[7]) << 16;
    *reinterpret_cast<uint4*>(dst) = word;
  }
}

// One layer: products over the streamed weights, then the epilogue; the next layer's first
// chunks (`next`, unless this is the last layer) are issued once this layer's weights are read.
template <typename Mma, int MT, int MTW, int NTW, int STAGES>
__device__ __forceinline__ void mma_layer(const WeightStream<mma_storage_t<Mma>, STAGES>& w,
                                          const WeightStream<mma_storage_t<Mma>, STAGES>& next,
                                          const float* __restrict__ bias, const LayerShape& s,
                                          mma_storage_t<Mma>* act, int row, float* logits,
                                          int logit_row, float* scratch) {
  using Ops = MmaOps<Mma>;
  using Operand = typename Ops::Operand;
  using S = mma_storage_t<Mma>;
  constexpr int kK = Ops::kK;
  constexpr int kDepth = WeightStream<S, STAGES>::kDepth;
  constexpr int kLdb = kStageRowBytes / static_cast<int>(sizeof(S));
  constexpr int WN = kWarps * MTW / MT;
  static_assert(MT % MTW == 0 && WN * (MT / MTW) == kWarps && MTW * NTW <= 16, "bad warp grid");
  const int warp = threadIdx.x / 32;
  const int lane = threadIdx.x % 32;
  const int wn_index = warp % WN;
  const int first_tile = (warp / WN) * MTW;

  wmma::fragment<wmma::accumulator, kTile, kTile, kK, float> acc[MTW][NTW];
#pragma unroll
  for (int i = 0; i < MTW; ++i) {
#pragma unroll
    for (int j = 0; j < NTW; ++j) wmma::fill_fragment(acc[i][j], 0.f);
  }
  const int chunks = w.chunks();
  for (int c = 0; c < chunks; ++c) {
    __pipeline_wait_prior(STAGES - 2);  // this thread's copies of chunk c have landed
    __syncthreads();  // everyone's have, and every warp is done with chunk c - 1's stage
    w.issue(c + STAGES - 1);            // into that stage
    const S* stage = w.stage(c);
    const int k_base = c * kDepth;
    const int depth = min(kDepth, s.in_pad - k_base);
    for (int kk = 0; kk < depth; kk += kK) {
      // Column n of W^T is row n of the stage.
      wmma::fragment<wmma::matrix_b, kTile, kTile, kK, Operand, wmma::col_major> b[NTW];
#pragma unroll
      for (int j = 0; j < NTW; ++j) {
        const int n = wn_index + WN * j;
        if (n < s.col_tiles) {
          wmma::load_matrix_sync(b[j], stage + n * kTile * kLdb + kk, kLdb);
          Ops::round(b[j]);
        }
      }
#pragma unroll
      for (int i = 0; i < MTW; ++i) {
        wmma::fragment<wmma::matrix_a, kTile, kTile, kK, Operand, wmma::row_major> a;
        wmma::load_matrix_sync(a, act + (first_tile + i) * kTile * row + k_base + kk, row);
        Ops::round(a);
#pragma unroll
        for (int j = 0; j < NTW; ++j) {
          if (wn_index + WN * j < s.col_tiles) wmma::mma_sync(acc[i][j], a, b[j], acc[i][j]);
        }
      }
    }
  }
  __syncthreads();  // every warp has read the layer's input and weights: overwrite them
  if (!s.last) next.prologue();

  float* tile = scratch + warp * kTile * kTile;
  const int r = lane / 2;
  const int c0 = (lane % 2) * 8;
#pragma unroll
  for (int i = 0; i < MTW; ++i) {
#pragma unroll
    for (int j = 0; j < NTW; ++j) {
      const int n = wn_index + WN * j;
      if (n >= s.col_tiles) continue;
      wmma::store_matrix_sync(tile, acc[i][j], kTile, wmma::mem_row_major);
      __syncwarp();
      const int p = (first_tile + i) * kTile + r;
      const int o0 = n * kTile + c0;
      const float4* t4 = reinterpret_cast<const float4*>(tile + r * kTile + c0);
      const float4* b4 = reinterpret_cast<const float4*>(bias + o0);
      const float4 t_lo = t4[0], t_hi = t4[1], b_lo = b4[0], b_hi = b4[1];
      float v[8] = {t_lo.x + b_lo.x, t_lo.y + b_lo.y, t_lo.z + b_lo.z, t_lo.w + b_lo.w,
                    t_hi.x + b_hi.x, t_hi.y + b_hi.y, t_hi.z + b_hi.z, t_hi.w + b_hi.w};
#pragma unroll
      for (int c = 0; c < 8; ++c) {
        if (s.relu && v[c] < 0.f) v[c] = 0.f;  // keeps NaN, like torch.relu
        if (o0 + c >= s.out) v[c] = 0.f;        // padded outputs: zeros, whatever the inputs held
      }
      if (s.last) {
#pragma unroll
        for (int c = 0; c < 8; ++c) logits[p * logit_row + o0 + c] = v[c];
      } else {
        store_operands<Ops>(act + p * row + o0, v);
      }
      __syncwarp();  // the tile is read before the next store_matrix_sync
    }
  }
  __syncthreads();
}

template <typename T, typename Mma, int MT, int MTW, int NTW, int STAGES>
__device__ __forceinline__ void decode_tile(const Triplane<T>& planes, const Query<T>& query,
                                            const MmaMlp<mma_storage_t<Mma>>& mlp, T* logits,
                                            uint8_t* labels) {
  using S = mma_storage_t<Mma>;
  constexpr int P = MT * kTile;
  extern __shared__ __align__(128) unsigned char smem[];
  const MmaLayout lay = mma_layout(mlp.width, mlp.num_layers, sizeof(S), MmaPlan{MT, STAGES});
  S* act = reinterpret_cast<S*>(smem);
  float* lg = reinterpret_cast<float*>(smem);  // the last layer's fp32 view of the same bytes
  unsigned char* stages = smem + lay.act_bytes;
  float* scratch = reinterpret_cast<float*>(stages + STAGES * lay.stage_bytes);
  int64_t* batch_of = reinterpret_cast<int64_t*>(scratch + kWarps * kTile * kTile);
  float* coord = reinterpret_cast<float*>(batch_of + P);

  const int64_t total = planes.batch * query.num_points;
  const int64_t first = static_cast<int64_t>(blockIdx.x) * P;
  if (skip_dead_block(query, first, total, P, labels)) return;

  const auto weights_of = [&](int l) {
    return WeightStream<S, STAGES>{mlp.weight[l], round_up(mlp.width[l], kTile),
                                   round_up(mlp.width[l + 1], kTile), stages, lay.stage_bytes};
  };
  weights_of(0).prologue();  // the first layer's weights arrive while the features are computed

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
  // (the first layer's first barrier makes the features visible)

  for (int l = 0; l < mlp.num_layers; ++l) {
    LayerShape s;
    s.in_pad = round_up(mlp.width[l], kTile);
    s.out = mlp.width[l + 1];
    s.col_tiles = round_up(s.out, kTile) / kTile;
    s.relu = l + 1 < mlp.num_layers;
    s.last = !s.relu;
    const WeightStream<S, STAGES> w = weights_of(l);
    const WeightStream<S, STAGES> next = weights_of(s.last ? l : l + 1);
    mma_layer<Mma, MT, MTW, NTW, STAGES>(w, next, mlp.bias[l], s, act, lay.row, lg,
                                         lay.logit_row, scratch);
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

// Up to 8 accumulator tiles per warp two blocks share an SM (at most 128 registers per
// thread); with 16 one block has it (the accumulators alone take 128).
template <typename T, typename Mma, int MT, int MTW, int NTW, int STAGES>
__global__ void __launch_bounds__(kThreads, MTW * NTW > 8 ? 1 : 2)
    mma_decode_kernel(const __grid_constant__ Triplane<T> planes,
                      const __grid_constant__ Query<T> query,
                      // read in place (indexed by layer), never copied to local memory
                      const __grid_constant__ MmaMlp<mma_storage_t<Mma>> mlp,
                      T* __restrict__ logits, uint8_t* __restrict__ labels) {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ < 800
  __trap();  // never launched: the glue checks the compute capability
#else
  decode_tile<T, Mma, MT, MTW, NTW, STAGES>(planes, query, mlp, logits, labels);
#endif
}

template <typename T, typename Mma, int MT, int MTW, int NTW, int STAGES>
cudaError_t launch_mma(const Triplane<T>& planes, const Query<T>& query,
                       const MmaMlp<mma_storage_t<Mma>>& mlp, T* logits, uint8_t* labels,
                       size_t smem, cudaStream_t stream) {
  const int64_t total = planes.batch * query.num_points;
  const int64_t blocks = (total + MT * kTile - 1) / (MT * kTile);
  if (blocks > INT_MAX) return cudaErrorInvalidConfiguration;
  auto* kernel = mma_decode_kernel<T, Mma, MT, MTW, NTW, STAGES>;
  const cudaError_t err = cudaFuncSetAttribute(
      kernel, cudaFuncAttributeMaxDynamicSharedMemorySize, static_cast<int>(smem));
  if (err != cudaSuccess) return err;
  kernel<<<static_cast<unsigned>(blocks), kThreads, smem, stream>>>(planes, query, mlp, logits,
                                                                    labels);
  return cudaGetLastError();
}

}  // namespace

size_t triplane_decode_mma_shared_bytes(const int* widths, int num_layers, int operand_bytes) {
  return mma_layout(widths, num_layers, operand_bytes, mma_plan(widths, num_layers, operand_bytes)).total;
}

template <typename T, typename Mma>
cudaError_t triplane_decode_forward_mma(const Triplane<T>& planes, const Query<T>& query,
                                        int pe_freqs, const MmaMlp<mma_storage_t<Mma>>& mlp,
                                        T* logits, uint8_t* labels, cudaStream_t stream) {
  (void)pe_freqs;  // the encoding's width is mlp.width[0] - planes.channels
  if (planes.batch * query.num_points == 0) return cudaSuccess;
  const int operand_bytes = sizeof(mma_storage_t<Mma>);
  const MmaPlan plan = mma_plan(mlp.width, mlp.num_layers, operand_bytes);
  const size_t smem = triplane_decode_mma_shared_bytes(mlp.width, mlp.num_layers, operand_bytes);
  int device = 0;
  int optin = 0;
  cudaError_t err = cudaGetDevice(&device);
  if (err != cudaSuccess) return err;
  err = cudaDeviceGetAttribute(&optin, cudaDevAttrMaxSharedMemoryPerBlockOptin, device);
  if (err != cudaSuccess) return err;
  if (smem > static_cast<size_t>(optin)) return cudaErrorInvalidValue;
  // The warp grid of the widest layer (narrower layers leave warps idle). With 8 row tiles:
  // 4 x 4 tiles per warp up to 16 column tiles (each A tile read by 4 warps, each B tile by
  // 2), 4 x 2 up to 8, 4 x 1 up to 4, then fewer rows per warp; with 4 and 2 row tiles
  // (TF32 up to 256 outputs, anything wider) 4 x 2 and 2 x 4.
  const int col_tiles = widest_col_tiles(mlp.width, mlp.num_layers);
  if (plan.row_tiles == 4) return launch_mma<T, Mma, 4, 4, 2, 3>(planes, query, mlp, logits, labels, smem, stream);
  if (plan.row_tiles == 2) return launch_mma<T, Mma, 2, 2, 4, 2>(planes, query, mlp, logits, labels, smem, stream);
  if (col_tiles > 8) return launch_mma<T, Mma, 8, 4, 4, 3>(planes, query, mlp, logits, labels, smem, stream);
  if (col_tiles > 4) return launch_mma<T, Mma, 8, 4, 2, 3>(planes, query, mlp, logits, labels, smem, stream);
  if (col_tiles > 2) return launch_mma<T, Mma, 8, 4, 1, 3>(planes, query, mlp, logits, labels, smem, stream);
  if (col_tiles > 1) return launch_mma<T, Mma, 8, 2, 1, 3>(planes, query, mlp, logits, labels, smem, stream);
  return launch_mma<T, Mma, 8, 1, 1, 3>(planes, query, mlp, logits, labels, smem, stream);
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
