// group_norm_silu on CUDA: silu(group_norm(x) * weight + bias [+ residual]) in three launches
// that read the input twice and write the output once (group_norm, the add and silu one after
// another read four to seven times), and its backward in three launches.
//
// A block owns a chunk of kChunk values of one (batch, channel) row: enough blocks for the GPU
// even at batch 1 with a few groups, and each block's loads are coalesced. Partial sums go to
// a workspace slot per chunk and are added in a fixed order by the next kernel: no atomics,
// deterministic.
//   forward:  stats (per chunk: sums of x - the group's first value, and of their squares)
//             -> finish (per group: mean and rstd) -> apply (y, per chunk).
//   backward: grads (per chunk: g = dy * silu'(z), written as the residual's gradient, and the
//             sums of g and g * xhat) -> rows (per (batch, channel): the chunks' sums) ->
//             inputs (dx per chunk, from its group's means of g * w and g * w * xhat).
#include "cuda/kernels.h"

#include <climits>

namespace t3fast {
namespace cuda {
namespace {

constexpr int kThreads = 256;
constexpr int kWarps = kThreads / 32;
constexpr int64_t kChunk = 8192;  // values of a block: 32 per thread

int64_t ceil_div(int64_t a, int64_t b) { return (a + b - 1) / b; }

__device__ __forceinline__ float exp_acc(float v) { return expf(v); }
__device__ __forceinline__ double exp_acc(double v) { return exp(v); }

// Sum of (v0, v1) over the block into thread 0 (others get garbage), in a fixed order.
template <typename A>
__device__ void block_sum2(A& v0, A& v1, A (*scratch)[2]) {
  const int lane = threadIdx.x % 32, warp = threadIdx.x / 32;
  for (int offset = 16; offset > 0; offset /= 2) {
    v0 += __shfl_down_sync(0xffffffffu, v0, offset);
    v1 += __shfl_down_sync(0xffffffffu, v1, offset);
  }
  if (lane == 0) {
    scratch[warp][0] = v0;
    scratch[warp][1] = v1;
  }
  __syncthreads();
  if (threadIdx.x == 0) {
    v0 = scratch[0][0];
    v1 = scratch[0][1];
    for (int w = 1; w < kWarps; ++w) {
      v0 += scratch[w][0];
      v1 += scratch[w][1];
    }
  }
}

// Where block t works: row (b * C + c) and the chunk [begin, begin + n) of its S values.
struct Place {
  int64_t row, begin;
  int n;
  __device__ Place(int64_t S, int64_t chunks) {
    row = blockIdx.x / chunks;
    begin = (blockIdx.x - row * chunks) * kChunk;
    n = static_cast<int>(S - begin < kChunk ? S - begin : kChunk);
  }
};

// A Place with its row's channel c, group bg, statistics and weight, the normalisation and
// affine transform as one, (x - mean) * rstd * w + bias = x * a + shift, and the chunk's first
// value's index base.
template <typename T>
struct NormPlace : Place {
  using A = acc_t<T>;
  int c;
  int64_t bg, base;
  A mean, rstd, w, a, shift;
  __device__ NormPlace(int64_t S, int64_t chunks, int C, int Cg, const T* weight, const T* bias,
                       const A* means, const A* rstds)
      : Place(S, chunks) {
    c = static_cast<int>(row % C);
    bg = row / Cg;
    mean = means[bg];
    rstd = rstds[bg];
    w = to_acc(weight[c]);
    a = rstd * w;
    shift = to_acc(bias[c]) - mean * a;
    base = row * S + begin;
  }
};

template <typename T>
__global__ void __launch_bounds__(kThreads)
    stats_kernel(const T* __restrict__ x, const int64_t S, const int64_t chunks, const int Cg,
                 acc_t<T>* __restrict__ workspace) {
  using A = acc_t<T>;
  __shared__ A scratch[kWarps][2];
  const Place p(S, chunks);
  const A shift = to_acc(x[p.row / Cg * Cg * S]);  // the group's first value
  const T* src = x + p.row * S + p.begin;
  A s1 = A(0), s2 = A(0);
  for (int i = threadIdx.x; i < p.n; i += kThreads) {
    const A d = to_acc(src[i]) - shift;
    s1 += d;
    s2 += d * d;
  }
  block_sum2(s1, s2, scratch);
  if (threadIdx.x == 0) {
    workspace[blockIdx.x * 2] = s1;
    workspace[blockIdx.x * 2 + 1] = s2;
  }
}

template <typename T>
__global__ void __launch_bounds__(kThreads)
    finish_kernel(const T* __restrict__ x, const acc_t<T>* __restrict__ workspace,
                  const int64_t S, const int64_t chunks, const int Cg, const double eps,
                  acc_t<T>* __restrict__ mean, acc_t<T>* __restrict__ rstd) {
  using A = acc_t<T>;
  __shared__ A scratch[kWarps][2];
  const int64_t bg = blockIdx.x;
  const int64_t entries = Cg * chunks;  // the group's rows are consecutive
  const A* part = workspace + bg * entries * 2;
  A s1 = A(0), s2 = A(0);
  for (int64_t e = threadIdx.x; e < entries; e += kThreads) {
    s1 += part[e * 2];
    s2 += part[e * 2 + 1];
  }
  block_sum2(s1, s2, scratch);
  if (threadIdx.x == 0) {
    const A count = static_cast<A>(Cg * S);
    const A m = s1 / count;
    A var = s2 / count - m * m;
    var = var > A(0) ? var : A(0);
    mean[bg] = to_acc(x[bg * Cg * S]) + m;
    rstd[bg] = A(1) / sqrt(var + static_cast<A>(eps));
  }
}

template <typename T>
__global__ void __launch_bounds__(kThreads)
    apply_kernel(const T* __restrict__ x, const T* __restrict__ w, const T* __restrict__ bias,
                 const T* __restrict__ r, const acc_t<T>* __restrict__ mean,
                 const acc_t<T>* __restrict__ rstd, const int64_t S, const int64_t chunks,
                 const int C, const int Cg, T* __restrict__ y) {
  using A = acc_t<T>;
  const NormPlace<T> p(S, chunks, C, Cg, w, bias, mean, rstd);
  for (int i = threadIdx.x; i < p.n; i += kThreads) {
    A z = to_acc(x[p.base + i]) * p.a + p.shift;
    if (r != nullptr) z += to_acc(r[p.base + i]);
    y[p.base + i] = from_acc<T>(z / (A(1) + exp_acc(-z)));
  }
}

// g = dy * silu'(z) at value i of a chunk, z = x * a + shift [+ r].
template <typename T>
__device__ __forceinline__ acc_t<T> silu_grad(const T* dy, const T* x, const T* r, int64_t i,
                                              acc_t<T> a, acc_t<T> shift) {
  using A = acc_t<T>;
  A z = to_acc(x[i]) * a + shift;
  if (r != nullptr) z += to_acc(r[i]);
  const A s = A(1) / (A(1) + exp_acc(-z));
  return to_acc(dy[i]) * s * (A(1) + z * (A(1) - s));
}

template <typename T>
__global__ void __launch_bounds__(kThreads)
    grads_kernel(const T* __restrict__ dy, const T* __restrict__ x, const T* __restrict__ w,
                 const T* __restrict__ bias, const T* __restrict__ r,
                 const acc_t<T>* __restrict__ mean, const acc_t<T>* __restrict__ rstd,
                 const int64_t S, const int64_t chunks, const int C, const int Cg,
                 T* __restrict__ dr, acc_t<T>* __restrict__ workspace) {
  using A = acc_t<T>;
  __shared__ A scratch[kWarps][2];
  const NormPlace<T> p(S, chunks, C, Cg, w, bias, mean, rstd);
  A s1 = A(0), s2 = A(0);
  for (int i = threadIdx.x; i < p.n; i += kThreads) {
    const A g = silu_grad(dy, x, r, p.base + i, p.a, p.shift);
    if (dr != nullptr) dr[p.base + i] = from_acc<T>(g);
    s1 += g;
    s2 += g * (to_acc(x[p.base + i]) - p.mean) * p.rstd;
  }
  block_sum2(s1, s2, scratch);
  if (threadIdx.x == 0) {
    workspace[blockIdx.x * 2] = s1;
    workspace[blockIdx.x * 2 + 1] = s2;
  }
}

// row_sums[row] = the sums of its chunks, in chunk order.
template <typename A>
__global__ void __launch_bounds__(kThreads)
    rows_kernel(const A* __restrict__ workspace, const int64_t rows, const int64_t chunks,
                A* __restrict__ row_sums) {
  for (int64_t row = static_cast<int64_t>(blockIdx.x) * kThreads + threadIdx.x; row < rows;
       row += static_cast<int64_t>(gridDim.x) * kThreads) {
    A s1 = A(0), s2 = A(0);
    for (int64_t k = 0; k < chunks; ++k) {
      s1 += workspace[(row * chunks + k) * 2];
      s2 += workspace[(row * chunks + k) * 2 + 1];
    }
    row_sums[row * 2] = s1;
    row_sums[row * 2 + 1] = s2;
  }
}

template <typename T>
__global__ void __launch_bounds__(kThreads)
    inputs_kernel(const T* __restrict__ dy, const T* __restrict__ x, const T* __restrict__ w,
                  const T* __restrict__ bias, const T* __restrict__ r,
                  const acc_t<T>* __restrict__ mean, const acc_t<T>* __restrict__ rstd,
                  const acc_t<T>* __restrict__ row_sums, const int64_t S, const int64_t chunks,
                  const int C, const int Cg, T* __restrict__ dx) {
  using A = acc_t<T>;
  const NormPlace<T> p(S, chunks, C, Cg, w, bias, mean, rstd);
  // the group's means of dxhat = g * w and of dxhat * xhat (every thread: Cg broadcast reads)
  A m1 = A(0), m2 = A(0);
  for (int k = 0; k < Cg; ++k) {
    const int64_t row = p.bg * Cg + k;
    const A wk = to_acc(w[row % C]);
    m1 += wk * row_sums[row * 2];
    m2 += wk * row_sums[row * 2 + 1];
  }
  const A count = static_cast<A>(Cg * S);
  m1 /= count;
  m2 /= count;
  for (int i = threadIdx.x; i < p.n; i += kThreads) {
    const A g = silu_grad(dy, x, r, p.base + i, p.a, p.shift);
    const A xhat = (to_acc(x[p.base + i]) - p.mean) * p.rstd;
    dx[p.base + i] = from_acc<T>(p.rstd * (g * p.w - m1 - xhat * m2));
  }
}

bool fits(int64_t batch, int64_t channels, int64_t spatial, int64_t chunks) {
  return batch * channels * chunks <= INT_MAX && channels <= INT_MAX;
}

}  // namespace

int64_t group_norm_silu_chunks(int64_t spatial) { return spatial > 0 ? ceil_div(spatial, kChunk) : 0; }

template <typename T>
cudaError_t group_norm_silu_forward(const T* x, const T* weight, const T* bias, const T* residual,
                                    int64_t batch, int64_t channels, int64_t spatial,
                                    int64_t groups, double eps, T* y, acc_t<T>* mean,
                                    acc_t<T>* rstd, acc_t<T>* workspace, cudaStream_t stream) {
  const int64_t chunks = group_norm_silu_chunks(spatial);
  if (batch * channels * chunks == 0) return cudaSuccess;
  if (!fits(batch, channels, spatial, chunks)) return cudaErrorInvalidValue;
  const int Cg = static_cast<int>(channels / groups);
  const unsigned blocks = static_cast<unsigned>(batch * channels * chunks);
  stats_kernel<T><<<blocks, kThreads, 0, stream>>>(x, spatial, chunks, Cg, workspace);
  cudaError_t err = cudaGetLastError();
  if (err != cudaSuccess) return err;
  finish_kernel<T><<<static_cast<unsigned>(batch * groups), kThreads, 0, stream>>>(
      x, workspace, spatial, chunks, Cg, eps, mean, rstd);
  err = cudaGetLastError();
  if (err != cudaSuccess) return err;
  apply_kernel<T><<<blocks, kThreads, 0, stream>>>(x, weight, bias, residual, mean, rstd, spatial,
                                                   chunks, static_cast<int>(channels), Cg, y);
  return cudaGetLastError();
}

template <typename T>
cudaError_t group_norm_silu_backward(const T* grad, const T* x, const T* weight, const T* bias,
                                     const T* residual, const acc_t<T>* mean,
                                     const acc_t<T>* rstd, int64_t batch, int64_t channels,
                                     int64_t spatial, int64_t groups, T* grad_input,
                                     T* grad_residual, acc_t<T>* row_sums, acc_t<T>* workspace,
                                     cudaStream_t stream) {
  const int64_t chunks = group_norm_silu_chunks(spatial);
  if (batch * channels * chunks == 0) return cudaSuccess;
  if (!fits(batch, channels, spatial, chunks)) return cudaErrorInvalidValue;
  const int C = static_cast<int>(channels), Cg = static_cast<int>(channels / groups);
  const int64_t rows = batch * channels;
  const unsigned blocks = static_cast<unsigned>(rows * chunks);
  grads_kernel<T><<<blocks, kThreads, 0, stream>>>(grad, x, weight, bias, residual, mean, rstd,
                                                   spatial, chunks, C, Cg, grad_residual,
                                                   workspace);
  cudaError_t err = cudaGetLastError();
  if (err != cudaSuccess) return err;
  using A = acc_t<T>;
  const int64_t row_blocks = ceil_div(rows, kThreads) < 65536 ? ceil_div(rows, kThreads) : 65536;
  rows_kernel<A><<<static_cast<unsigned>(row_blocks), kThreads, 0, stream>>>(
      workspace, rows, chunks, row_sums);
  err = cudaGetLastError();
  if (err != cudaSuccess) return err;
  inputs_kernel<T><<<blocks, kThreads, 0, stream>>>(grad, x, weight, bias, residual, mean, rstd,
                                                    row_sums, spatial, chunks, C, Cg, grad_input);
  return cudaGetLastError();
}

#define T3FAST_INSTANTIATE(T)                                                                   \
  template cudaError_t group_norm_silu_forward<T>(const T*, const T*, const T*, const T*,       \
                                                  int64_t, int64_t, int64_t, int64_t, double,   \
                                                  T*, acc_t<T>*, acc_t<T>*, acc_t<T>*,          \
                                                  cudaStream_t);                                \
  template cudaError_t group_norm_silu_backward<T>(                                             \
      const T*, const T*, const T*, const T*, const T*, const acc_t<T>*, const acc_t<T>*,       \
      int64_t, int64_t, int64_t, int64_t, T*, T*, acc_t<T>*, acc_t<T>*, cudaStream_t);

T3FAST_INSTANTIATE(float)
T3FAST_INSTANTIATE(double)
T3FAST_INSTANTIATE(__half)
T3FAST_INSTANTIATE(__nv_bfloat16)

#undef T3FAST_INSTANTIATE

}  // namespace cuda
}  // namespace t3fast
