// triplane_decode on CUDA: the fused forward kernel and the two point-wise kernels of the
// backward pass (feature recomputation and the scatter of feature gradients to the planes).
//
// Forward design (after tiny-cuda-nn's fully fused MLP, SIMT version)
// -------------------------------------------------------------------
// A block of 256 threads owns a tile of P consecutive query points (P = 128, 64 or 32) and
// takes them from coordinates to logits without touching global memory in between:
//   1. the points' coordinates (read, or computed from the voxel index in grid mode) and
//      batch index go to shared memory;
//   2. the features (bilinear samples of the three planes, summed, then the positional
//      encoding) are computed into the activation buffer `act` [feature][P + 4] in shared
//      memory (point index contiguous);
//   3. every layer is a small GEMM out[P, n_out] = act[P, n_in] W^T + b: each thread keeps a
//      register tile of TP points x 8 outputs in fp32 (double for double), the weights
//      stream through shared memory in chunks of 8 input features (converted to the
//      accumulation type on the way), and the activations are read from shared memory. Once
//      the whole layer is in registers (after a barrier) the threads overwrite `act` in place,
//      so one buffer of P x max-width values is enough;
//   4. the last layer's values are written as logits (coalesced, one row per point) or
//      reduced to the first-maximum class per point (uint8 labels; no logits anywhere).
// The block holds 256 x 64 = 16384 accumulators per layer at most, hence P = 128 points for
// widths up to 128, 64 up to 256, 32 up to 512 (kTriplaneMaxWidth); the launcher takes the
// largest P that covers the widest layer and whose shared memory fits the device. Narrow
// layers (e.g. the class layer) use a thinner register tile (TP = 2 or 1 points per thread,
// and 4 in float64) so that most threads still have work; each thread's 8 outputs are
// consecutive and the weight chunk is stored transposed, `wsm` [8][outputs + 4], so its
// weights are two 128-bit loads. The wide layers (TP = 8 or 4: the hidden layers of the
// decoders) in float use mlp_layer_wide: every shared-memory read is a 128-bit load without
// bank conflicts (4 loads per 64 FMAs at TP = 8; one value per load, 16 loads per 64 FMAs,
// left the SIMT pipes waiting on shared memory), and the weights are double-buffered: the
// next chunk is fetched into registers while the current one is multiplied, one barrier per
// chunk. Shared memory per block is ((P + 4) x padded widest width + 2 x 8 x (rows + 4) +
// 3 P) x 4 + 8 P bytes for a widest pass of rows outputs, e.g. about 87 KB for hidden width
// 256 (P = 64): two blocks per SM on H100 (the kernel is built for at most 128 registers per
// thread there for that reason; see fused_min_blocks). The weights are re-read from L2 once
// per tile and layer. Tensor cores are not used.
//
// Backward: see triplane_decode.cpp (chunked recomputation with cuBLAS GEMMs); the kernels
// here compute a chunk's features and scatter the feature gradient into the planes.
#include "cuda/kernels.h"
#include "cuda/triplane_sample.cuh"

#include <climits>
#include <type_traits>

namespace t3fast {
namespace cuda {
namespace {

constexpr int kThreads = 256;  // threads per block, all kernels of this file
constexpr int kTileOut = 8;    // outputs per thread in a layer's register tile
constexpr int kMaxTileRows = 8;  // points per thread at the widest layout
constexpr int kMaxGridBlocks = 1 << 16;  // cap of grid-stride launches

// Input features per staged weight chunk. 8 keeps the two chunk buffers small (16 KB at 256
// outputs): two blocks of the 256-wide configuration per SM on H100 / H200 (228 KB per SM);
// an A100 (164 KB) holds one.
constexpr int kChunk = 8;

__host__ __device__ constexpr int round_up(int v, int m) { return (v + m - 1) / m * m; }

// Row length of the activation buffer act [features][P + 4]: the point index is contiguous,
// rows stay 16-byte aligned for the wide tile's 128-bit loads, and the 4 extra values spread
// a column's rows over the banks.
template <int P>
__host__ __device__ constexpr int act_row() {
  return P + 4;
}

// Outputs one pass of a layer covers with a tile of P points and tp points per thread.
__host__ __device__ constexpr int outputs_covered(int P, int tp) {
  return kThreads * tp / P * kTileOut;
}

// Thinnest register tile (points per thread) whose pass covers `out` outputs.
__host__ __device__ inline int rows_per_thread(int P, int out) {
  for (int tp = 1; tp < kMaxTileRows; tp *= 2) {
    if (outputs_covered(P, tp) >= out) return tp;
  }
  return kMaxTileRows;
}

// Rows of the staged weight chunk: the widest pass over the layers' outputs, since threads
// read (and drop) rows up to the end of their pass.
__host__ __device__ inline int mlp_weight_rows(int P, const int* widths, int num_layers) {
  int rows = 0;
  for (int i = 1; i <= num_layers; ++i) {
    const int covered = outputs_covered(P, rows_per_thread(P, widths[i]));
    rows = covered > rows ? covered : rows;
  }
  return rows;
}

// Values of the weight buffer for the widest pass of `rows` outputs: two chunks
// [kChunk][rows + 4] (the wide tile double-buffers; a narrow tile uses one).
__host__ __device__ inline int weight_buffer_values(int rows) { return 2 * kChunk * (rows + 4); }

// One linear layer of the fused kernel on the activations of the tile, in place:
// act[p, o] <- act[p, :in] . weight[o, :in] + bias[o] (ReLU if relu) for o < out, and 0 for
// out <= o < round_up(out, chunk) so that the next layer's last chunk reads zeros.
// Thread (pg, og) owns points pg + (P / TP) * i (i < TP) and the 8 consecutive outputs
// 8 og + j (j < kTileOut): the weight chunk is stored transposed, wsm [kChunk][outputs + 4]
// (the 4 extra columns make the transposing stores conflict-free), so a thread reads its 8
// weights with two 128-bit loads in float (the class layer: 3 loads per 8 FMAs instead of 9).
// Starts and ends with a barrier, so act may be rewritten freely around it.
template <int TP, int P, typename T, typename A>
__device__ __forceinline__ void mlp_layer(const T* __restrict__ weight,
                                          const T* __restrict__ bias, int in, int out,
                                          bool relu, A* act, A* wsm) {
  constexpr int kRow = act_row<P>();
  constexpr int kGroupsP = P / TP;
  constexpr int kGroupsO = kThreads / kGroupsP;
  constexpr int kWRow = outputs_covered(P, TP) + 4;
  static_assert(kGroupsP * TP == P && kGroupsO * kGroupsP == kThreads, "bad register tile");
  const int og = threadIdx.x % kGroupsO;
  const int pg = threadIdx.x / kGroupsO;
  const int o0 = og * kTileOut;

  A acc[TP][kTileOut];
#pragma unroll
  for (int j = 0; j < kTileOut; ++j) {
    const int o = o0 + j;
    const A b = o < out ? to_acc(bias[o]) : A(0);
#pragma unroll
    for (int i = 0; i < TP; ++i) acc[i][j] = b;
  }

  for (int k0 = 0; k0 < in; k0 += kChunk) {
    __syncthreads();  // act is complete, and nobody reads the previous weight chunk any more
    // wsm[kk][o] = weight[o, k0 + kk]; rows >= out are never loaded (their results are dropped)
    for (int idx = threadIdx.x; idx < out * kChunk; idx += kThreads) {
      const int o = idx / kChunk;
      const int kk = idx - o * kChunk;
      const int k = k0 + kk;
      wsm[kk * kWRow + o] = k < in ? to_acc(weight[static_cast<int64_t>(o) * in + k]) : A(0);
    }
    __syncthreads();
// half unrolled: a full unroll hoists every load and spills at 128 registers
#pragma unroll 4
    for (int kk = 0; kk < kChunk; ++kk) {
      A a[TP];
      A w[kTileOut];
#pragma unroll
      for (int i = 0; i < TP; ++i) a[i] = act[(k0 + kk) * kRow + pg + kGroupsP * i];
      const A* w_row = wsm + kk * kWRow + o0;
      if constexpr (std::is_same_v<A, float>) {
        const float4 lo = *reinterpret_cast<const float4*>(w_row);
        const float4 hi = *reinterpret_cast<const float4*>(w_row + 4);
        w[0] = lo.x, w[1] = lo.y, w[2] = lo.z, w[3] = lo.w;
        w[4] = hi.x, w[5] = hi.y, w[6] = hi.z, w[7] = hi.w;
      } else {
#pragma unroll
        for (int j = 0; j < kTileOut; ++j) w[j] = w_row[j];
      }
#pragma unroll
      for (int i = 0; i < TP; ++i) {
#pragma unroll
        for (int j = 0; j < kTileOut; ++j) acc[i][j] += a[i] * w[j];
      }
    }
  }

  __syncthreads();  // all reads of this layer's inputs are done: overwrite them
  const int out_pad = round_up(out, kChunk);
#pragma unroll
  for (int j = 0; j < kTileOut; ++j) {
    const int o = o0 + j;
    if (o < out_pad) {
#pragma unroll
      for (int i = 0; i < TP; ++i) {
        A v = acc[i][j];
        if (relu && v < A(0)) v = A(0);  // keeps NaN, like torch.relu
        act[o * kRow + pg + kGroupsP * i] = o < out ? v : A(0);
      }
    }
  }
  __syncthreads();
}

// The wide register tiles (TP = 4 or 8 points x 8 outputs per thread) in float: the layer
// of mlp_layer<TP, P> with every shared-memory read a 128-bit load. A warp covers 4 TP
// points x 64 outputs as 4 x 8 threads: a thread owns TP consecutive points and two runs of 4
// outputs 32 apart, so a warp's loads of activations (4 distinct runs of 16 bytes) and of
// weights (two 128-byte rows) are free of bank conflicts: 2 + TP / 4 loads per 8 TP FMAs
// instead of 8 + TP. The weights stream through two chunk buffers wbuf [2][kChunk][rows + 4]
// (the 4 extra columns make the transposing stores conflict-free): the next chunk is fetched
// from global memory into registers while the current one is used, stored after it, and one
// barrier per chunk separates the two.
template <int TP, int P, typename T>
__device__ __forceinline__ void mlp_layer_wide(const T* __restrict__ weight,
                                               const T* __restrict__ bias, int in, int out,
                                               bool relu, float* act, float* wbuf) {
  static_assert(TP == 4 || TP == 8, "the wide tiles hold 4 or 8 points per thread");
  constexpr int kRow = act_row<P>();
  constexpr int kWarpPoints = 4 * TP;
  constexpr int kWarpOutputs = 64;
  constexpr int kWarpRows = P / kWarpPoints;
  constexpr int kWarpCols = kThreads / 32 / kWarpRows;
  constexpr int kRows = kWarpCols * kWarpOutputs;  // outputs covered
  constexpr int kWRow = kRows + 4;
  constexpr int kLoads = kRows * kChunk / kThreads;  // weight values each thread fetches
  static_assert(kRows == outputs_covered(P, TP) && kLoads * kThreads == kRows * kChunk,
                "bad wide tile");
  const int warp = threadIdx.x / 32;
  const int lane = threadIdx.x % 32;
  const int p0 = (warp / kWarpCols) * kWarpPoints + (lane / 8) * TP;
  const int o0 = (warp % kWarpCols) * kWarpOutputs + (lane % 8) * 4;

  float acc[TP][kTileOut];  // [point p0 + i][output o0 + j (+ 28 for j >= 4)]
#pragma unroll
  for (int j = 0; j < kTileOut; ++j) {
    const int o = o0 + j + (j >= 4 ? 28 : 0);
    const float b = o < out ? to_acc(bias[o]) : 0.f;
#pragma unroll
    for (int i = 0; i < TP; ++i) acc[i][j] = b;
  }

  // Thread t fetches input t % kChunk of the weight rows t / kChunk + kRowStep * l: with
  // consecutive threads on 8 consecutive inputs of a row, a warp reads whole 32-byte sectors.
  constexpr int kRowStep = kThreads / kChunk;
  static_assert(kThreads % kChunk == 0, "bad chunk");
  const int kk_t = threadIdx.x % kChunk;
  const int o_t = threadIdx.x / kChunk;
  const T* w_t = weight + static_cast<int64_t>(o_t) * in + kk_t;
  float next[kLoads];
  const auto fetch = [&](int k0) {
    const bool k_ok = k0 + kk_t < in;
#pragma unroll
    for (int l = 0; l < kLoads; ++l) {
      const bool ok = k_ok && o_t + kRowStep * l < out;
      next[l] = ok ? to_acc(w_t[static_cast<int64_t>(kRowStep) * l * in + k0]) : 0.f;
    }
  };
  const auto stash = [&](float* chunk) {
#pragma unroll
    for (int l = 0; l < kLoads; ++l) chunk[kk_t * kWRow + o_t + kRowStep * l] = next[l];
  };

  const int chunks = (in + kChunk - 1) / kChunk;
  fetch(0);
  __syncthreads();  // act is complete, and nobody reads wbuf any more
  stash(wbuf);
  __syncthreads();
  for (int c = 0; c < chunks; ++c) {
    const float* chunk = wbuf + (c % 2) * kChunk * kWRow;
    if (c + 1 < chunks) fetch((c + 1) * kChunk);
#pragma unroll
    for (int kk = 0; kk < kChunk; ++kk) {
      const float* a_row = act + (c * kChunk + kk) * kRow + p0;
      const float* w_row = chunk + kk * kWRow + o0;
      float a[TP];
#pragma unroll
      for (int q = 0; q < TP / 4; ++q) {
        const float4 v = *reinterpret_cast<const float4*>(a_row + 4 * q);
        a[4 * q] = v.x, a[4 * q + 1] = v.y, a[4 * q + 2] = v.z, a[4 * q + 3] = v.w;
      }
      const float4 w_lo = *reinterpret_cast<const float4*>(w_row);
      const float4 w_hi = *reinterpret_cast<const float4*>(w_row + 32);
      const float w[kTileOut] = {w_lo.x, w_lo.y, w_lo.z, w_lo.w, w_hi.x, w_hi.y, w_hi.z, w_hi.w};
#pragma unroll
      for (int i = 0; i < TP; ++i) {
#pragma unroll
        for (int j = 0; j < kTileOut; ++j) acc[i][j] += a[i] * w[j];
      }
    }
    // the other buffer was last read before the previous barrier
    if (c + 1 < chunks) stash(wbuf + ((c + 1) % 2) * kChunk * kWRow);
    __syncthreads();  // after the last chunk: all reads of this layer's inputs are done
  }

  const int out_pad = round_up(out, kChunk);
#pragma unroll
  for (int j = 0; j < kTileOut; ++j) {
    const int o = o0 + j + (j >= 4 ? 28 : 0);
    if (o < out_pad) {
#pragma unroll
      for (int i = 0; i < TP; ++i) {
        float v = acc[i][j];
        if (relu && v < 0.f) v = 0.f;  // keeps NaN, like torch.relu
        act[o * kRow + p0 + i] = o < out ? v : 0.f;
      }
    }
  }
  __syncthreads();
}

// Blocks per SM the fused kernel is built for (each thread gets 64K / (256 x blocks) registers
// at most): two where two blocks' shared memory fits an SM (every point tile on sm_90's
// 228 KB; only the 128-point tile, about 77 KB, on sm_80's 164 KB), else one, which lifts the
// cap of 128 registers that made the 64- and 32-point tiles spill on sm_80.
template <typename T, int P>
__host__ __device__ constexpr int fused_min_blocks() {
  if (sizeof(acc_t<T>) == 8) return 1;
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ < 900
  return P == 128 ? 2 : 1;
#else
  return 2;
#endif
}

template <typename T, int P>
__global__ void __launch_bounds__(kThreads, fused_min_blocks<T, P>())
    fused_decode_kernel(const Triplane<T> planes, const Query<T> query, const int pe_freqs,
                        const Mlp<T> mlp, T* __restrict__ logits,
                        uint8_t* __restrict__ labels) {
  using A = acc_t<T>;
  constexpr int kRow = act_row<P>();
  extern __shared__ __align__(16) unsigned char smem[];
  int64_t* batch_of = reinterpret_cast<int64_t*>(smem);  // [P]
  A* coord = reinterpret_cast<A*>(batch_of + P);         // [P][3]
  A* wsm = coord + 3 * P;  // the weight buffer (weight_buffer_values)
  A* act = wsm + weight_buffer_values(mlp_weight_rows(P, mlp.width, mlp.num_layers));  // [width][kRow]

  const int64_t total = planes.batch * query.num_points;
  const int64_t first = static_cast<int64_t>(blockIdx.x) * P;
  if (skip_dead_block(query, first, total, P, labels)) return;

  stage_points(query, first, total, P, kThreads, batch_of, coord);
  __syncthreads();

  const int in0 = mlp.width[0];
  const int in0_pad = round_up(in0, kChunk);
  for (int idx = threadIdx.x; idx < P * in0_pad; idx += kThreads) {
    const int p = idx % P;
    const int j = idx / P;
    const A v = mlp_input(planes, batch_of[p], j, in0, coord[3 * p], coord[3 * p + 1], coord[3 * p + 2]);
    act[j * kRow + p] = v;
  }
  // (mlp_layer starts with a barrier)

  for (int l = 0; l < mlp.num_layers; ++l) {
    const int in = mlp.width[l];
    const int out = mlp.width[l + 1];
    const bool relu = l + 1 < mlp.num_layers;
    switch (rows_per_thread(P, out)) {
      case 1:
        mlp_layer<1, P>(mlp.weight[l], mlp.bias[l], in, out, relu, act, wsm);
        break;
      case 2:
        mlp_layer<2, P>(mlp.weight[l], mlp.bias[l], in, out, relu, act, wsm);
        break;
      case 4:
        if constexpr (std::is_same_v<A, float>) {
          mlp_layer_wide<4, P>(mlp.weight[l], mlp.bias[l], in, out, relu, act, wsm);
        } else {
          mlp_layer<4, P>(mlp.weight[l], mlp.bias[l], in, out, relu, act, wsm);
        }
        break;
      default:
        if constexpr (std::is_same_v<A, float>) {
          mlp_layer_wide<kMaxTileRows, P>(mlp.weight[l], mlp.bias[l], in, out, relu, act, wsm);
        } else {
          mlp_layer<kMaxTileRows, P>(mlp.weight[l], mlp.bias[l], in, out, relu, act, wsm);
        }
        break;
    }
  }

  const int classes = mlp.width[mlp.num_layers];
  if (logits != nullptr) {
    for (int idx = threadIdx.x; idx < P * classes; idx += kThreads) {
      const int p = idx / classes;
      const int o = idx - p * classes;
      const int64_t g = first + p;
      if (g < total) logits[g * classes + o] = from_acc<T>(act[o * kRow + p]);
    }
  } else {
    for (int p = threadIdx.x; p < P; p += kThreads) {
      const int64_t g = first + p;
      if (g >= total) continue;
      // Compare the values rounded to T, so that the labels are exactly the argmax of the
      // logits this kernel would write; first maximum wins, NaN counts as the maximum.
      A best = to_acc(from_acc<T>(act[p]));
      int best_o = 0;
      for (int o = 1; o < classes; ++o) {
        const A v = to_acc(from_acc<T>(act[o * kRow + p]));
        if (v > best || (v != v && best == best)) {
          best = v;
          best_o = o;
        }
      }
      labels[g] = query_live(query, g) ? static_cast<uint8_t>(best_o) : uint8_t{0};
    }
  }
}

// Shared memory of fused_decode_kernel<T, P> for these widths.
template <typename A, int P>
size_t fused_shared_bytes(const int* widths, int num_layers) {
  int widest = 1;  // at least one row: the argmax epilogue reads row 0 even with no classes
  for (int i = 0; i <= num_layers; ++i) widest = widths[i] > widest ? widths[i] : widest;
  const size_t values = 3 * P +
                        static_cast<size_t>(weight_buffer_values(mlp_weight_rows(P, widths, num_layers))) +
                        static_cast<size_t>(round_up(widest, kChunk)) * act_row<P>();
  return P * sizeof(int64_t) + values * sizeof(A);
}

template <typename T, int P>
bool fused_fits(const Mlp<T>& mlp, int widest_out, int max_shared_bytes) {
  return widest_out <= outputs_covered(P, kMaxTileRows) &&
         fused_shared_bytes<acc_t<T>, P>(mlp.width, mlp.num_layers) <=
             static_cast<size_t>(max_shared_bytes);
}

template <typename T, int P>
cudaError_t launch_fused(const Triplane<T>& planes, const Query<T>& query, int pe_freqs,
                         const Mlp<T>& mlp, T* logits, uint8_t* labels, cudaStream_t stream) {
  const size_t smem = fused_shared_bytes<acc_t<T>, P>(mlp.width, mlp.num_layers);
  const int64_t total = planes.batch * query.num_points;
  const int64_t blocks = (total + P - 1) / P;
  if (blocks > INT_MAX) return cudaErrorInvalidConfiguration;
  auto* kernel = fused_decode_kernel<T, P>;
  const cudaError_t err = cudaFuncSetAttribute(
      kernel, cudaFuncAttributeMaxDynamicSharedMemorySize, static_cast<int>(smem));
  if (err != cudaSuccess) return err;
  kernel<<<static_cast<unsigned>(blocks), kThreads, smem, stream>>>(planes, query, pe_freqs, mlp,
                                                                    logits, labels);
  return cudaGetLastError();
}

template <typename T>
__global__ void __launch_bounds__(kThreads)
    features_kernel(const Triplane<T> planes, const Query<T> query, const int pe_freqs,
                    const int64_t start, const int64_t count, acc_t<T>* __restrict__ out) {
  using A = acc_t<T>;
  const int in0 = planes.channels + 6 * pe_freqs;
  const int64_t n = count * in0;
  for (int64_t idx = static_cast<int64_t>(blockIdx.x) * kThreads + threadIdx.x; idx < n;
       idx += static_cast<int64_t>(gridDim.x) * kThreads) {
    const int64_t p = idx / in0;
    const int j = static_cast<int>(idx - p * in0);
    A x, y, z;
    const int64_t b = query_point(query, start + p, x, y, z);
    out[idx] = j < planes.channels ? plane_feature(planes, b, j, x, y, z)
                                   : pe_value(j - planes.channels, x, y, z);
  }
}

// grad[rows, cols] += weights of the bilinear sample at (r, c) times g.
template <typename A>
__device__ __forceinline__ void scatter_bilinear(A* grad, int cols, const Lerp<A>& r,
                                                 const Lerp<A>& c, A g) {
  A* row0 = grad + static_cast<int64_t>(r.i0) * cols;
  A* row1 = grad + static_cast<int64_t>(r.i1) * cols;
  const A g0 = (A(1) - r.w) * g;
  const A g1 = r.w * g;
  atomicAdd(row0 + c.i0, (A(1) - c.w) * g0);
  atomicAdd(row0 + c.i1, c.w * g0);
  atomicAdd(row1 + c.i0, (A(1) - c.w) * g1);
  atomicAdd(row1 + c.i1, c.w * g1);
}

// One thread per (point, channel), channels fastest: coalesced reads of the feature gradient,
// and the atomics of a warp spread over several plane channels.
template <typename T>
__global__ void __launch_bounds__(kThreads)
    scatter_kernel(const Triplane<T> planes, const Query<T> query, const int64_t start,
                   const int64_t count, const acc_t<T>* __restrict__ grad, const int64_t ld,
                   acc_t<T>* gxy, acc_t<T>* gxz, acc_t<T>* gyz) {
  using A = acc_t<T>;
  const int channels = planes.channels;
  const int64_t n = count * channels;
  for (int64_t idx = static_cast<int64_t>(blockIdx.x) * kThreads + threadIdx.x; idx < n;
       idx += static_cast<int64_t>(gridDim.x) * kThreads) {
    const int64_t p = idx / channels;
    const int c = static_cast<int>(idx - p * channels);
    const A g = grad[p * ld + c];
    A x, y, z;
    const int64_t b = query_point(query, start + p, x, y, z);
    const Lerp<A> lx = axis_lerp(x, planes.sx);
    const Lerp<A> ly = axis_lerp(y, planes.sy);
    const Lerp<A> lz = axis_lerp(z, planes.sz);
    const int64_t bc = b * channels + c;
    scatter_bilinear(gxy + bc * planes.sx * planes.sy, planes.sy, lx, ly, g);
    scatter_bilinear(gxz + bc * planes.sx * planes.sz, planes.sz, lx, lz, g);
    scatter_bilinear(gyz + bc * planes.sy * planes.sz, planes.sz, ly, lz, g);
  }
}

unsigned grid_stride_blocks(int64_t n) {
  const int64_t blocks = (n + kThreads - 1) / kThreads;
  return static_cast<unsigned>(blocks < kMaxGridBlocks ? blocks : kMaxGridBlocks);
}

}  // namespace

size_t triplane_decode_min_shared_bytes(const int* widths, int num_layers,
                                        bool double_precision) {
  for (int i = 0; i <= num_layers; ++i) {
    if (widths[i] > kTriplaneMaxWidth) return 0;
  }
  constexpr int kSmallestTile = 32;
  return double_precision ? fused_shared_bytes<double, kSmallestTile>(widths, num_layers)
                          : fused_shared_bytes<float, kSmallestTile>(widths, num_layers);
}

template <typename T>
cudaError_t triplane_decode_forward(const Triplane<T>& planes, const Query<T>& query,
                                    int pe_freqs, const Mlp<T>& mlp, T* logits, uint8_t* labels,
                                    cudaStream_t stream) {
  if (planes.batch * query.num_points == 0) return cudaSuccess;
  int device = 0;
  int optin = 0;
  cudaError_t err = cudaGetDevice(&device);
  if (err != cudaSuccess) return err;
  err = cudaDeviceGetAttribute(&optin, cudaDevAttrMaxSharedMemoryPerBlockOptin, device);
  if (err != cudaSuccess) return err;
  int widest_out = 0;
  for (int i = 1; i <= mlp.num_layers; ++i) {
    widest_out = mlp.width[i] > widest_out ? mlp.width[i] : widest_out;
  }
  // The largest point tile whose register tiles cover the widest layer and whose buffers
  // fit the device: more points per tile means fewer passes of the weights through L2.
  if (fused_fits<T, 128>(mlp, widest_out, optin)) {
    return launch_fused<T, 128>(planes, query, pe_freqs, mlp, logits, labels, stream);
  }
  if (fused_fits<T, 64>(mlp, widest_out, optin)) {
    return launch_fused<T, 64>(planes, query, pe_freqs, mlp, logits, labels, stream);
  }
  if (fused_fits<T, 32>(mlp, widest_out, optin)) {
    return launch_fused<T, 32>(planes, query, pe_freqs, mlp, logits, labels, stream);
  }
  return cudaErrorInvalidValue;
}

template <typename T>
cudaError_t triplane_features(const Triplane<T>& planes, const Query<T>& query, int pe_freqs,
                              int64_t start, int64_t count, acc_t<T>* features,
                              cudaStream_t stream) {
  const int64_t n = count * (planes.channels + 6 * pe_freqs);
  if (n == 0) return cudaSuccess;
  features_kernel<T><<<grid_stride_blocks(n), kThreads, 0, stream>>>(planes, query, pe_freqs,
                                                                     start, count, features);
  return cudaGetLastError();
}

template <typename T>
cudaError_t triplane_scatter_grad(const Triplane<T>& planes, const Query<T>& query,
                                  int64_t start, int64_t count, const acc_t<T>* grad_features,
                                  int64_t ld, acc_t<T>* grad_xy, acc_t<T>* grad_xz,
                                  acc_t<T>* grad_yz, cudaStream_t stream) {
  const int64_t n = count * planes.channels;
  if (n == 0) return cudaSuccess;
  scatter_kernel<T><<<grid_stride_blocks(n), kThreads, 0, stream>>>(
      planes, query, start, count, grad_features, ld, grad_xy, grad_xz, grad_yz);
  return cudaGetLastError();
}

#define T3FAST_INSTANTIATE(T)                                                                  \
  template cudaError_t triplane_decode_forward<T>(const Triplane<T>&, const Query<T>&, int,    \
                                                  const Mlp<T>&, T*, uint8_t*, cudaStream_t);  \
  template cudaError_t triplane_features<T>(const Triplane<T>&, const Query<T>&, int, int64_t, \
                                            int64_t, acc_t<T>*, cudaStream_t);                 \
  template cudaError_t triplane_scatter_grad<T>(const Triplane<T>&, const Query<T>&, int64_t,  \
                                                int64_t, const acc_t<T>*, int64_t, acc_t<T>*,  \
                                                acc_t<T>*, acc_t<T>*, cudaStream_t);

T3FAST_INSTANTIATE(float)
T3FAST_INSTANTIATE(double)
T3FAST_INSTANTIATE(__half)
T3FAST_INSTANTIATE(__nv_bfloat16)

#undef T3FAST_INSTANTIATE

}  // namespace cuda
}  // namespace t3fast
