// matching_costs on CUDA: the local cost volume of two planes [B, C, H, W] in one pass, and its
// backward, without atomics.
//
// Forward: one thread per output (b, n, i, j), j fastest, so a warp writes a row segment of one
// shift and reads a row segment of present and of the shifted previous per channel (the
// (2r + 1)^2 threads reading the same present value are served by L1/L2). The channel sum runs
// in order c = 0, 1, ... in acc_t, as the CPU kernel does: float32 results are the CPU's bit
// for bit.
//
// Backward: one thread per plane value writes both planes' gradients there. grad_present sums
// its (2r + 1)^2 shifts; grad_previous at (i', j') gathers every (i, j, shift) whose shifted cell
// is (i', j'): one at an inner cell, every shift the replicate padding moves onto an edge cell.
// Both in the CPU kernel's order, so no two threads write one value and the results are
// deterministic.
#include "cuda/kernels.h"

namespace t3fast {
namespace cuda {
namespace {

constexpr int kThreads = 256;
constexpr int64_t kMaxBlocks = int64_t{1} << 20;  // grid-stride loops beyond

__device__ __forceinline__ float absolute(float v) { return fabsf(v); }
__device__ __forceinline__ double absolute(double v) { return fabs(v); }

template <typename A>
__device__ __forceinline__ A sign_of(A v) {
  return static_cast<A>((v > A(0)) - (v < A(0)));
}

__device__ __forceinline__ int clamp_index(int v, int n) { return min(max(v, 0), n - 1); }

// The sources s in [0, n) that shift d - r (replicate padding) takes to target t: [from, to].
__device__ __forceinline__ void sources_of(int t, int n, int d, int r, int& from, int& to) {
  const int lo = t == 0 ? -(1 << 30) : t, hi = t == n - 1 ? (1 << 30) : t;
  from = max(0, lo - d + r);
  to = min(n - 1, hi - d + r);
}

unsigned blocks_for(int64_t total) {
  const int64_t blocks = (total + kThreads - 1) / kThreads;
  return static_cast<unsigned>(blocks < kMaxBlocks ? blocks : kMaxBlocks);
}

template <typename T>
__global__ void __launch_bounds__(kThreads)
    matching_costs_kernel(const T* __restrict__ present, const T* __restrict__ previous,
                          const int64_t total, const int C, const int H, const int W, const int r,
                          T* __restrict__ out) {
  using A = acc_t<T>;
  const int size = 2 * r + 1;
  const int shifts = size * size;
  const int64_t HW = static_cast<int64_t>(H) * W;
  for (int64_t e = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; e < total;
       e += static_cast<int64_t>(gridDim.x) * blockDim.x) {
    const int j = static_cast<int>(e % W);
    int64_t rest = e / W;
    const int i = static_cast<int>(rest % H);
    rest /= H;
    const int n = static_cast<int>(rest % shifts);
    const int64_t b = rest / shifts;
    const int qi = clamp_index(i + n / size - r, H), qj = clamp_index(j + n % size - r, W);
    const T* p = present + b * C * HW + static_cast<int64_t>(i) * W + j;
    const T* q = previous + b * C * HW + static_cast<int64_t>(qi) * W + qj;
    A acc = A(0);
    for (int c = 0; c < C; ++c) acc += absolute(to_acc(p[c * HW]) - to_acc(q[c * HW]));
    out[e] = from_acc<T>(acc / static_cast<A>(-C));
  }
}

// grad_present at one value: -(1/C) sum over the shifts of grad * sign(present - shifted).
template <typename T>
__device__ __forceinline__ acc_t<T> present_grad_at(const T* g, acc_t<T> p, const T* q, int i,
                                                    int j, int H, int W, int r, int64_t HW) {
  using A = acc_t<T>;
  const int size = 2 * r + 1;
  A acc = A(0);
  for (int di = 0; di < size; ++di) {
    const T* q_row = q + static_cast<int64_t>(clamp_index(i + di - r, H)) * W;
    for (int dj = 0; dj < size; ++dj) {
      const A v = to_acc(q_row[clamp_index(j + dj - r, W)]);
      acc += to_acc(g[(di * size + dj) * HW + static_cast<int64_t>(i) * W + j]) * sign_of(p - v);
    }
  }
  return acc;
}

// grad_previous at (ti, tj): (1/C) sum over every (i, j, shift) whose clamped shift lands there
// of grad * sign(present - previous[ti, tj]).
template <typename T>
__device__ __forceinline__ acc_t<T> previous_grad_at(const T* g, const T* p, acc_t<T> v, int ti,
                                                     int tj, int H, int W, int r, int64_t HW) {
  using A = acc_t<T>;
  const int size = 2 * r + 1;
  A acc = A(0);
  for (int di = 0; di < size; ++di) {
    int i0, i1;
    sources_of(ti, H, di, r, i0, i1);
    for (int i = i0; i <= i1; ++i) {
      for (int dj = 0; dj < size; ++dj) {
        int j0, j1;
        sources_of(tj, W, dj, r, j0, j1);
        const T* g_row = g + (di * size + dj) * HW + static_cast<int64_t>(i) * W;
#pragma unroll 1  // one source inside the plane: unrolled, the float32 kernel spilled
        for (int j = j0; j <= j1; ++j) {
          acc += to_acc(g_row[j]) * sign_of(to_acc(p[static_cast<int64_t>(i) * W + j]) - v);
        }
      }
    }
  }
  return acc;
}

// One thread per plane value (b, c, i, j): both planes' gradients there.
template <typename T>
__global__ void __launch_bounds__(kThreads)
    matching_costs_backward_kernel(const T* __restrict__ grad, const T* __restrict__ present,
                                   const T* __restrict__ previous, const int64_t total,
                                   const int C, const int H, const int W, const int r,
                                   T* __restrict__ grad_present, T* __restrict__ grad_previous) {
  using A = acc_t<T>;
  const int shifts = (2 * r + 1) * (2 * r + 1);
  const int64_t HW = static_cast<int64_t>(H) * W;
  for (int64_t e = blockIdx.x * static_cast<int64_t>(blockDim.x) + threadIdx.x; e < total;
       e += static_cast<int64_t>(gridDim.x) * blockDim.x) {
    const int j = static_cast<int>(e % W);
    const int i = static_cast<int>((e / W) % H);
    const int64_t bc = e / HW;
    const T* g = grad + bc / C * shifts * HW;
    const T* p = present + bc * HW;
    const T* q = previous + bc * HW;
    const A gp = present_grad_at(g, to_acc(present[e]), q, i, j, H, W, r, HW);
    const A gq = previous_grad_at(g, p, to_acc(previous[e]), i, j, H, W, r, HW);
    grad_present[e] = from_acc<T>(gp / static_cast<A>(-C));
    grad_previous[e] = from_acc<T>(gq / static_cast<A>(C));
  }
}

}  // namespace

template <typename T>
cudaError_t matching_costs_forward(const T* present, const T* previous, int64_t batch,
                                   int channels, int h, int w, int radius, T* out,
                                   cudaStream_t stream) {
  const int64_t total = batch * (2 * radius + 1) * (2 * radius + 1) * static_cast<int64_t>(h) * w;
  if (total == 0) return cudaSuccess;
  matching_costs_kernel<T><<<blocks_for(total), kThreads, 0, stream>>>(
      present, previous, total, channels, h, w, radius, out);
  return cudaGetLastError();
}

template <typename T>
cudaError_t matching_costs_backward(const T* grad, const T* present, const T* previous,
                                    int64_t batch, int channels, int h, int w, int radius,
                                    T* grad_present, T* grad_previous, cudaStream_t stream) {
  const int64_t total = batch * channels * static_cast<int64_t>(h) * w;
  if (total == 0) return cudaSuccess;
  matching_costs_backward_kernel<T><<<blocks_for(total), kThreads, 0, stream>>>(
      grad, present, previous, total, channels, h, w, radius, grad_present, grad_previous);
  return cudaGetLastError();
}

#define T3FAST_INSTANTIATE(T)                                                                  \
  template cudaError_t matching_costs_forward<T>(const T*, const T*, int64_t, int, int, int,  \
                                                 int, T*, cudaStream_t);                       \
  template cudaError_t matching_costs_backward<T>(const T*, const T*, const T*, int64_t, int, \
                                                  int, int, int, T*, T*, cudaStream_t);

T3FAST_INSTANTIATE(float)
T3FAST_INSTANTIATE(double)
T3FAST_INSTANTIATE(__half)
T3FAST_INSTANTIATE(__nv_bfloat16)

#undef T3FAST_INSTANTIATE

}  // namespace cuda
}  // namespace t3fast
