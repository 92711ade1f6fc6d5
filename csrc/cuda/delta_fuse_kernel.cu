// delta_fuse on CUDA: next = delta + conv1x1(prev) + bias in one pass, and its backward.
//
// Forward design
// --------------
// One thread per pixel, a block per (batch element, 256 pixels, tile of O output channels)
// with O = 8 when C <= 8 (the triplane case: prev and delta are read exactly once) and 32
// otherwise. Each thread keeps its O outputs in registers; the weight streams through shared
// memory in chunks of 32 input channels (`w_tile` [32][O], read as broadcasts), and the
// thread reads its own pixel of prev straight from global memory (coalesced along pixels, no
// reuse across threads, so no staging). The epilogue adds delta and the bias and writes the
// O output rows, coalesced.
//
// Backward design
// ---------------
// A block per (batch element, tile of PT pixels) stages grad_out [C][PT] and prev [C_in][PT]
// in shared memory (rows of PT + 1: conflict-free column reads), reading both once. From
// there it computes grad_prev = W^T grad_out for its pixels (one thread per (c_in, pixel),
// W read through the cache as warp broadcasts) and its partial sums of grad_weight
// (sum_p grad_out[o, p] prev[c, p]) and grad_bias (sum_p grad_out[o, p]): work items (o, c,
// segment) sum every S-th pixel, S chosen so that small C * C_in still uses all threads, and
// add the partial into the fp32 (double) accumulators with atomicAdd. PT is the largest of
// 256, 128, 64, 32 whose tiles fit in 48 KB of shared memory (or the device's opt-in maximum
// for very many channels).
#include "cuda/kernels.h"

#include <climits>

namespace t3fast {
namespace cuda {
namespace {

constexpr int kThreads = 256;
constexpr int kInChunk = 32;  // input channels per staged weight chunk (forward)
constexpr size_t kDefaultShared = 48 * 1024;

template <typename T, int O>
__global__ void __launch_bounds__(kThreads)
    delta_fuse_kernel(const T* __restrict__ delta, const T* __restrict__ prev,
                      const T* __restrict__ weight, const T* __restrict__ bias, const int C,
                      const int Cin, const int64_t HW, const int64_t tiles_per_image,
                      T* __restrict__ out) {
  using A = acc_t<T>;
  __shared__ A w_tile[kInChunk][O];  // w_tile[c][j] = weight[o0 + j, c0 + c]

  const int64_t b = blockIdx.x / tiles_per_image;
  const int64_t pix = (blockIdx.x - b * tiles_per_image) * kThreads + threadIdx.x;
  const int o0 = blockIdx.y * O;
  const bool active = pix < HW;
  const T* src = prev + b * Cin * HW + pix;

  A acc[O];
#pragma unroll
  for (int j = 0; j < O; ++j) acc[j] = A(0);

  for (int c0 = 0; c0 < Cin; c0 += kInChunk) {
    const int cn = min(kInChunk, Cin - c0);
    __syncthreads();  // the previous chunk is no longer read
    for (int idx = threadIdx.x; idx < kInChunk * O; idx += kThreads) {
      const int j = idx / kInChunk;
      const int c = idx - j * kInChunk;
      const int o = o0 + j;
      w_tile[c][j] = (o < C && c < cn) ? to_acc(weight[static_cast<int64_t>(o) * Cin + c0 + c])
                                       : A(0);
    }
    __syncthreads();
    if (active) {
      for (int c = 0; c < cn; ++c) {
        const A v = to_acc(src[(c0 + c) * HW]);
#pragma unroll
        for (int j = 0; j < O; ++j) acc[j] += w_tile[c][j] * v;
      }
    }
  }

  if (!active) return;
#pragma unroll
  for (int j = 0; j < O; ++j) {
    const int o = o0 + j;
    if (o < C) {
      const int64_t i = (b * C + o) * HW + pix;
      A v = to_acc(delta[i]) + acc[j];
      if (bias != nullptr) v += to_acc(bias[o]);
      out[i] = from_acc<T>(v);
    }
  }
}

template <typename T>
__global__ void __launch_bounds__(kThreads)
    delta_fuse_backward_kernel(const T* __restrict__ grad_out, const T* __restrict__ prev,
                               const T* __restrict__ weight, const int C, const int Cin,
                               const int64_t HW, const int PT, const int64_t tiles_per_image,
                               const int S, T* __restrict__ grad_prev,
                               acc_t<T>* __restrict__ grad_weight,
                               acc_t<T>* __restrict__ grad_bias) {
  using A = acc_t<T>;
  extern __shared__ __align__(16) unsigned char smem[];
  const int row = PT + 1;
  A* gs = reinterpret_cast<A*>(smem);  // [C][row]
  A* ps = gs + C * row;                // [Cin][row]

  const int64_t b = blockIdx.x / tiles_per_image;
  const int64_t p0 = (blockIdx.x - b * tiles_per_image) * PT;
  const int pn = static_cast<int>(min(static_cast<int64_t>(PT), HW - p0));  // valid pixels

  // Stage both tiles (pixels past the end as zeros).
  for (int idx = threadIdx.x; idx < C * PT; idx += kThreads) {
    const int o = idx / PT;
    const int p = idx - o * PT;
    gs[o * row + p] = p < pn ? to_acc(grad_out[(b * C + o) * HW + p0 + p]) : A(0);
  }
  for (int idx = threadIdx.x; idx < Cin * PT; idx += kThreads) {
    const int c = idx / PT;
    const int p = idx - c * PT;
    ps[c * row + p] = p < pn ? to_acc(prev[(b * Cin + c) * HW + p0 + p]) : A(0);
  }
  __syncthreads();

  // grad_prev[b, c, p] = sum_o weight[o, c] grad_out[b, o, p]
  for (int idx = threadIdx.x; idx < Cin * PT; idx += kThreads) {
    const int c = idx / PT;
    const int p = idx - c * PT;
    if (p >= pn) continue;
    A sum = A(0);
    for (int o = 0; o < C; ++o) {
      sum += to_acc(weight[static_cast<int64_t>(o) * Cin + c]) * gs[o * row + p];
    }
    grad_prev[(b * Cin + c) * HW + p0 + p] = from_acc<T>(sum);
  }

  // Partial weight / bias gradients. Pair (o, c) with c == Cin stands for the bias (prev = 1).
  const int pairs = C * (Cin + 1);
  for (int idx = threadIdx.x; idx < pairs * S; idx += kThreads) {
    const int seg = idx / pairs;
    const int pair = idx - seg * pairs;
    const int o = pair / (Cin + 1);
    const int c = pair - o * (Cin + 1);
    const A* g = gs + o * row;
    A sum = A(0);
    if (c < Cin) {
      const A* x = ps + c * row;
      for (int p = seg; p < pn; p += S) sum += g[p] * x[p];
      atomicAdd(grad_weight + o * Cin + c, sum);
    } else {
      for (int p = seg; p < pn; p += S) sum += g[p];
      atomicAdd(grad_bias + o, sum);
    }
  }
}

int64_t ceil_div(int64_t a, int64_t b) { return (a + b - 1) / b; }

size_t backward_shared_bytes(int c_out, int c_in, int pt, bool double_precision) {
  return static_cast<size_t>(c_out + c_in) * (pt + 1) *
         (double_precision ? sizeof(double) : sizeof(float));
}

template <typename T, int O>
cudaError_t launch_forward(const T* delta, const T* prev, const T* weight, const T* bias,
                           int64_t batch, int c_out, int c_in, int64_t pixels, T* out,
                           cudaStream_t stream) {
  const int64_t tiles = ceil_div(pixels, kThreads);
  const int64_t blocks = batch * tiles;
  const int64_t out_tiles = ceil_div(c_out, O);
  if (blocks > INT_MAX || out_tiles > 65535) return cudaErrorInvalidValue;
  const dim3 grid(static_cast<unsigned>(blocks), static_cast<unsigned>(out_tiles));
  delta_fuse_kernel<T, O><<<grid, kThreads, 0, stream>>>(delta, prev, weight, bias, c_out, c_in,
                                                         pixels, tiles, out);
  return cudaGetLastError();
}

}  // namespace

template <typename T>
cudaError_t delta_fuse_forward(const T* delta, const T* prev, const T* weight, const T* bias,
                               int64_t batch, int c_out, int c_in, int64_t pixels, T* out,
                               cudaStream_t stream) {
  if (batch * c_out * pixels == 0) return cudaSuccess;
  if (c_out <= 8) {
    return launch_forward<T, 8>(delta, prev, weight, bias, batch, c_out, c_in, pixels, out,
                                stream);
  }
  return launch_forward<T, 32>(delta, prev, weight, bias, batch, c_out, c_in, pixels, out,
                               stream);
}

size_t delta_fuse_backward_min_shared_bytes(int c_out, int c_in, bool double_precision) {
  return backward_shared_bytes(c_out, c_in, 32, double_precision);
}

template <typename T>
cudaError_t delta_fuse_backward(const T* grad_out, const T* prev, const T* weight,
                                int64_t batch, int c_out, int c_in, int64_t pixels, T* grad_prev,
                                acc_t<T>* grad_weight, acc_t<T>* grad_bias,
                                cudaStream_t stream) {
  if (batch * pixels == 0) return cudaSuccess;
  const bool dbl = sizeof(acc_t<T>) == sizeof(double);
  int pt = 256;
  while (pt > 32 && backward_shared_bytes(c_out, c_in, pt, dbl) > kDefaultShared) pt /= 2;
  const size_t smem = backward_shared_bytes(c_out, c_in, pt, dbl);
  auto* kernel = delta_fuse_backward_kernel<T>;
  cudaError_t err = cudaFuncSetAttribute(kernel, cudaFuncAttributeMaxDynamicSharedMemorySize,
                                         static_cast<int>(smem));
  if (err != cudaSuccess) return err;
  const int64_t tiles = ceil_div(pixels, pt);
  const int64_t blocks = batch * tiles;
  if (blocks > INT_MAX) return cudaErrorInvalidValue;
  // Pixel segments per (o, c) pair: spread small C * (C_in + 1) over the block's threads.
  const int pairs = c_out * (c_in + 1);
  int segments = pairs > 0 ? kThreads / pairs : 1;
  segments = segments < 1 ? 1 : (segments > pt ? pt : segments);
  kernel<<<static_cast<unsigned>(blocks), kThreads, smem, stream>>>(
      grad_out, prev, weight, c_out, c_in, pixels, pt, tiles, segments, grad_prev, grad_weight,
      grad_bias);
  return cudaGetLastError();
}

#define T3FAST_INSTANTIATE(T)                                                                   \
  template cudaError_t delta_fuse_forward<T>(const T*, const T*, const T*, const T*, int64_t,   \
                                             int, int, int64_t, T*, cudaStream_t);              \
  template cudaError_t delta_fuse_backward<T>(const T*, const T*, const T*, int64_t, int, int,  \
                                              int64_t, T*, acc_t<T>*, acc_t<T>*, cudaStream_t);

T3FAST_INSTANTIATE(float)
T3FAST_INSTANTIATE(double)
T3FAST_INSTANTIATE(__half)
T3FAST_INSTANTIATE(__nv_bfloat16)

#undef T3FAST_INSTANTIATE

}  // namespace cuda
}  // namespace t3fast
