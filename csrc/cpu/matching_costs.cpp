// CPU kernels of matching_costs: the local cost volume of two planes in one pass, and its
// backward. A task is one row i of one batch element (forward) or one row of one channel
// (backward); per shift the row's costs are summed over the channels in a row buffer, channel
// by channel in order (the reference's order: the same float32 results bit for bit), so
// neither the [B, C, H, 2r + 1, W] differences nor their absolute values are ever in memory.
#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

#include "checks.h"
#include "cpu/simd.h"

namespace t3fast {
namespace {

constexpr const char* kOp = "matching_costs";
constexpr const char* kOpBwd = "matching_costs_backward";

int64_t clamp_index(int64_t v, int64_t n) { return std::min(std::max(v, int64_t{0}), n - 1); }

// The columns j of a row whose shifted column j + shift lies inside [0, n): [lo, hi).
void inside_columns(int64_t shift, int64_t n, int64_t& lo, int64_t& hi) {
  lo = std::min(n, std::max(int64_t{0}, -shift));
  hi = std::max(lo, std::min(n, n - shift));
}

// The source indices s in [0, n) that a shift d - r (replicate padding) takes to target t:
// [from, to], empty when from > to. Inside the row only s = t - d + r; at an edge every
// source the clamp moves onto it.
void sources_of(int64_t t, int64_t n, int64_t d, int64_t r, int64_t& from, int64_t& to) {
  constexpr int64_t kFar = std::numeric_limits<int32_t>::max();
  const int64_t lo = t == 0 ? -kFar : t, hi = t == n - 1 ? kFar : t;
  from = std::max(int64_t{0}, lo - d + r);
  to = std::min(n - 1, hi - d + r);
}

template <typename T>
T sign_of(T v) {
  return static_cast<T>((v > T(0)) - (v < T(0)));
}

// acc[j] += |p[j] - q[clamp(j + shift)]| for the W columns of a row.
template <typename T>
T3FAST_SIMD_CLONES void add_abs_differences(T* acc, const T* p, const T* q, int64_t shift,
                                            int64_t W) {
  int64_t lo, hi;
  inside_columns(shift, W, lo, hi);
  for (int64_t j = 0; j < lo; ++j) acc[j] += std::abs(p[j] - q[0]);
  const T* qs = q + shift;
#pragma omp simd
  for (int64_t j = lo; j < hi; ++j) acc[j] += std::abs(p[j] - qs[j]);
  for (int64_t j = hi; j < W; ++j) acc[j] += std::abs(p[j] - q[W - 1]);
}

// acc[j] += g[j] * sign(p[j] - q[clamp(j + shift)]) for the W columns of a row.
template <typename T>
T3FAST_SIMD_CLONES void add_signed_grads(T* acc, const T* g, const T* p, const T* q,
                                         int64_t shift, int64_t W) {
  int64_t lo, hi;
  inside_columns(shift, W, lo, hi);
  for (int64_t j = 0; j < lo; ++j) acc[j] += g[j] * sign_of(p[j] - q[0]);
  const T* qs = q + shift;
#pragma omp simd
  for (int64_t j = lo; j < hi; ++j) acc[j] += g[j] * sign_of(p[j] - qs[j]);
  for (int64_t j = hi; j < W; ++j) acc[j] += g[j] * sign_of(p[j] - q[W - 1]);
}

template <typename T>
void forward(const T* p, const T* q, T* out, const MatchingCostsShape& s) {
  const int64_t C = s.C, H = s.H, W = s.W, r = s.radius, size = 2 * r + 1;
  at::parallel_for(0, s.B * H, 1, [&](int64_t row0, int64_t row1) {
    std::vector<T> acc(W);
    for (int64_t row = row0; row < row1; ++row) {
      const int64_t b = row / H, i = row % H;
      for (int64_t di = 0; di < size; ++di) {
        const int64_t qi = clamp_index(i + di - r, H);
        for (int64_t dj = 0; dj < size; ++dj) {
          std::fill(acc.begin(), acc.end(), T(0));
          for (int64_t c = 0; c < C; ++c) {
            const int64_t plane = (b * C + c) * H;
            add_abs_differences(acc.data(), p + (plane + i) * W, q + (plane + qi) * W, dj - r, W);
          }
          T* o = out + ((b * s.shifts + di * size + dj) * H + i) * W;
          for (int64_t j = 0; j < W; ++j) o[j] = acc[j] / static_cast<T>(-C);
        }
      }
    }
  });
}

// acc = sum over the shifts of grad * sign(present - shifted) along row i of plane bc: the row's
// grad_present times -C.
template <typename T>
void present_grad_row(T* acc, const T* g, const T* p, const T* q, int64_t bc, int64_t i,
                      const MatchingCostsShape& s) {
  const int64_t H = s.H, W = s.W, r = s.radius, size = 2 * r + 1, b = bc / s.C;
  const T* pr = p + (bc * H + i) * W;
  std::fill(acc, acc + W, T(0));
  for (int64_t di = 0; di < size; ++di) {
    const T* qr = q + (bc * H + clamp_index(i + di - r, H)) * W;
    for (int64_t dj = 0; dj < size; ++dj) {
      const T* gr = g + ((b * s.shifts + di * size + dj) * H + i) * W;
      add_signed_grads(acc, gr, pr, qr, dj - r, W);
    }
  }
}

// acc[j'] = sum over the (i, j, shift) whose shifted cell is (ti, j') of grad * sign(present -
// previous[ti, j']) along row ti of plane bc: the row's grad_previous times C. Gathered per
// target cell (no scatter, no atomics), the edge cells collecting every shift the replicate
// padding moves onto them.
template <typename T>
void previous_grad_row(T* acc, const T* g, const T* p, const T* q, int64_t bc, int64_t ti,
                       const MatchingCostsShape& s) {
  const int64_t H = s.H, W = s.W, r = s.radius, size = 2 * r + 1, b = bc / s.C;
  const T* qr = q + (bc * H + ti) * W;
  std::fill(acc, acc + W, T(0));
  for (int64_t di = 0; di < size; ++di) {
    int64_t i0, i1;
    sources_of(ti, H, di, r, i0, i1);
    for (int64_t i = i0; i <= i1; ++i) {
      const T* pr = p + (bc * H + i) * W;
      for (int64_t dj = 0; dj < size; ++dj) {
        const T* gr = g + ((b * s.shifts + di * size + dj) * H + i) * W;
        // inside the row: target j' = j + dj - r for one source j
        const int64_t t0 = std::max<int64_t>(1, dj - r);
        const int64_t t1 = std::min<int64_t>(W - 1, W + dj - r);
        for (int64_t t = t0; t < t1; ++t) {
          const int64_t j = t - dj + r;
          acc[t] += gr[j] * sign_of(pr[j] - qr[t]);
        }
        for (int64_t e = 0; e < std::min<int64_t>(W, 2); ++e) {  // the edge columns
          const int64_t t = e == 0 ? 0 : W - 1;
          int64_t j0, j1;
          sources_of(t, W, dj, r, j0, j1);
          for (int64_t j = j0; j <= j1; ++j) acc[t] += gr[j] * sign_of(pr[j] - qr[t]);
        }
      }
    }
  }
}

// Both planes' gradients, a task per row of one channel.
template <typename T>
void backward(const T* g, const T* p, const T* q, T* gp, T* gq, const MatchingCostsShape& s) {
  const int64_t H = s.H, W = s.W;
  const T scale = static_cast<T>(s.C);
  at::parallel_for(0, s.B * s.C * H, 1, [&](int64_t row0, int64_t row1) {
    std::vector<T> acc(W);
    for (int64_t row = row0; row < row1; ++row) {
      present_grad_row(acc.data(), g, p, q, row / H, row % H, s);
      for (int64_t j = 0; j < W; ++j) gp[row * W + j] = acc[j] / -scale;
      previous_grad_row(acc.data(), g, p, q, row / H, row % H, s);
      for (int64_t j = 0; j < W; ++j) gq[row * W + j] = acc[j] / scale;
    }
  });
}

at::Tensor matching_costs_cpu(const at::Tensor& present, const at::Tensor& previous,
                              int64_t radius) {
  const MatchingCostsShape s = check_matching_costs(present, previous, radius, kOp);
  const at::Tensor p = present.detach().contiguous();
  const at::Tensor q = previous.detach().contiguous();
  at::Tensor out = at::empty({s.B, s.shifts, s.H, s.W}, p.options());
  if (out.numel() == 0) return out;
  AT_DISPATCH_FLOATING_TYPES(p.scalar_type(), "matching_costs_cpu", [&] {
    forward(p.data_ptr<scalar_t>(), q.data_ptr<scalar_t>(), out.data_ptr<scalar_t>(), s);
  });
  return out;
}

std::tuple<at::Tensor, at::Tensor> matching_costs_backward_cpu(const at::Tensor& grad,
                                                                const at::Tensor& present,
                                                                const at::Tensor& previous,
                                                                int64_t radius) {
  const MatchingCostsShape s =
      check_matching_costs_backward(grad, present, previous, radius, kOpBwd);
  const at::Tensor g = grad.detach().contiguous();
  const at::Tensor p = present.detach().contiguous();
  const at::Tensor q = previous.detach().contiguous();
  at::Tensor grad_present = at::empty_like(p);
  at::Tensor grad_previous = at::empty_like(q);
  if (p.numel() == 0) return {grad_present, grad_previous};
  AT_DISPATCH_FLOATING_TYPES(p.scalar_type(), "matching_costs_backward_cpu", [&] {
    using T = scalar_t;
    backward(g.data_ptr<T>(), p.data_ptr<T>(), q.data_ptr<T>(), grad_present.data_ptr<T>(),
             grad_previous.data_ptr<T>(), s);
  });
  return {grad_present, grad_previous};
}

}  // namespace

TORCH_LIBRARY_IMPL(t3fast, CPU, m) {
  m.impl("matching_costs", &matching_costs_cpu);
  m.impl("matching_costs_backward", &matching_costs_backward_cpu);
}

}  // namespace t3fast
