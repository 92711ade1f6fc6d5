// CPU kernels of group_norm_silu: silu(group_norm(x) * weight + bias [+ residual]) in two
// passes over the input (the groups' sums, then the output) where group_norm, the residual add
// and silu run one after another take four to seven; and its backward in two passes.
//
// The work is cut into chunks of at most kChunk values of one (batch, channel) row, so that a
// batch of one with few groups still keeps every thread busy. Each chunk's sums go to a slot of
// a buffer and are added per group (forward) or per channel (backward) in chunk order:
// deterministic for any thread count. Sums are kept in double: a group holds up to millions of
// values, and the variance comes from sums of values shifted by the group's first value (so
// that a large mean does not cancel away the variance's digits).
#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <tuple>
#include <vector>

#include "checks.h"
#include "cpu/simd.h"

namespace t3fast {
namespace {

constexpr const char* kOp = "group_norm_silu";
constexpr const char* kOpBwd = "group_norm_silu_backward";
constexpr int64_t kChunk = 16384;  // values of a task: 64 KiB of float32

// exp(v) for float32 within 2 ulp (Cephes' expf) where it is a normal float, 0 below, at most
// 2^127 * 1.5 above; NaN stays NaN; for |v| < 2^21. Built from additions, multiplications and
// integer operations only, so that the loops below vectorise: std::exp stays one scalar libm
// call per value, and GCC's default trapping-math rules keep floor and float comparisons (a
// clamp of v) scalar. n is v / ln 2 rounded by the 1.5 * 2^23 trick; the power of two is clamped
// as an integer, the reduced argument uses the unclamped n.
inline float exp_of(float v) {
  const float n = (v * 1.44269504088896341f + 12582912.0f) - 12582912.0f;
  const float r = (v - n * 0.693359375f) + n * 2.12194440e-4f;  // v - n ln 2 in two parts
  float p = 1.9875691500e-4f;
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  p = p * r * r + r + 1.0f;
  int32_t k = static_cast<int32_t>(n);
  const int32_t keep = k > -127 ? -1 : 0;  // 2^k below the normal floats: 0
  k = k < 127 ? k : 127;
  const int32_t bits = ((k + 127) << 23) & keep;
  return p * __builtin_bit_cast(float, bits);
}
inline double exp_of(double v) { return std::exp(v); }

// The chunks of a (batch, channel) row of S values; chunk k of row (b, c) is task
// (b * C + c) * chunks_per_row(S) + k.
int64_t chunks_per_row(int64_t S) { return std::max<int64_t>(1, (S + kChunk - 1) / kChunk); }

// fn(task, row, begin, n) for every chunk [begin, begin + n) of the rows, in parallel.
template <typename F>
void for_each_chunk(int64_t rows, int64_t S, const F& fn) {
  const int64_t per_row = chunks_per_row(S);
  at::parallel_for(0, rows * per_row, 1, [&](int64_t t0, int64_t t1) {
    for (int64_t t = t0; t < t1; ++t) {
      const int64_t row = t / per_row, begin = t % per_row * kChunk;
      fn(t, row, begin, std::min(kChunk, S - begin));
    }
  });
}

// A row's normalisation and affine transform as one: (x - mean) * rstd * w + bias = x * a + shift.
template <typename T>
struct RowAffine {
  T a, shift;
};
template <typename T>
RowAffine<T> row_affine(const T* w, const T* bias, const T* mean, const T* rstd, int64_t row,
                        const GroupNormShape& s) {
  const int64_t c = row % s.C, bg = row / s.Cg;
  const T a = rstd[bg] * w[c];
  return {a, bias[c] - mean[bg] * a};
}

// (sum of d, sum of d^2) of d = x - shift over n values.
template <typename T>
T3FAST_SIMD_CLONES void shifted_sums(const T* x, int64_t n, double shift, double* out) {
  double s1 = 0.0, s2 = 0.0;
#pragma omp simd reduction(+ : s1, s2)
  for (int64_t i = 0; i < n; ++i) {
    const double d = static_cast<double>(x[i]) - shift;
    s1 += d;
    s2 += d * d;
  }
  out[0] = s1;
  out[1] = s2;
}

// y = silu(x * a + c [+ r]) over n values.
template <typename T>
T3FAST_SIMD_CLONES void scale_shift_silu(const T* x, const T* r, T a, T c, int64_t n, T* y) {
  if (r != nullptr) {
#pragma omp simd
    for (int64_t i = 0; i < n; ++i) {
      const T z = x[i] * a + c + r[i];
      y[i] = z / (T(1) + exp_of(-z));
    }
  } else {
#pragma omp simd
    for (int64_t i = 0; i < n; ++i) {
      const T z = x[i] * a + c;
      y[i] = z / (T(1) + exp_of(-z));
    }
  }
}

// dy * silu'(z) for z = x * a + c [+ r]: written to g (n values).
template <typename T>
inline T silu_grad(T dy, T z) {
  const T s = T(1) / (T(1) + exp_of(-z));
  return dy * s * (T(1) + z * (T(1) - s));
}
template <typename T>
T3FAST_SIMD_CLONES void silu_grads(const T* dy, const T* x, const T* r, T a, T c, int64_t n,
                                   T* g) {
  if (r != nullptr) {  // two loops: a conditional load would keep the loop scalar
#pragma omp simd
    for (int64_t i = 0; i < n; ++i) g[i] = silu_grad(dy[i], x[i] * a + c + r[i]);
  } else {
#pragma omp simd
    for (int64_t i = 0; i < n; ++i) g[i] = silu_grad(dy[i], x[i] * a + c);
  }
}

// (sum of g, sum of g * (x - mean) * rstd) over n values.
template <typename T>
T3FAST_SIMD_CLONES void grad_sums(const T* g, const T* x, double mean, double rstd, int64_t n,
                                  double* out) {
  double s1 = 0.0, s2 = 0.0;
#pragma omp simd reduction(+ : s1, s2)
  for (int64_t i = 0; i < n; ++i) {
    const double gi = static_cast<double>(g[i]);
    s1 += gi;
    s2 += gi * (static_cast<double>(x[i]) - mean) * rstd;
  }
  out[0] = s1;
  out[1] = s2;
}

// dx = rstd * (g * w - m1 - (x - mean) * rstd * m2) over n values.
template <typename T>
T3FAST_SIMD_CLONES void input_grads(const T* g, const T* x, T w, T mean, T rstd, T m1, T m2,
                                    int64_t n, T* dx) {
#pragma omp simd
  for (int64_t i = 0; i < n; ++i) dx[i] = rstd * (g[i] * w - m1 - (x[i] - mean) * rstd * m2);
}

template <typename T>
void forward(const T* x, const T* w, const T* bias, const T* r, T* y, T* mean, T* rstd,
             const GroupNormShape& s, double eps) {
  const int64_t rows = s.B * s.C, per_row = chunks_per_row(s.S), group_size = s.Cg * s.S;
  std::vector<double> sums(rows * per_row * 2);  // per chunk: (sum of d, sum of d^2)
  for_each_chunk(rows, s.S, [&](int64_t t, int64_t row, int64_t begin, int64_t n) {
    const double first = static_cast<double>(x[row / s.Cg * group_size]);  // the group's first value
    shifted_sums(x + row * s.S + begin, n, first, &sums[t * 2]);
  });
  for (int64_t bg = 0; bg < s.B * s.G; ++bg) {  // the group's rows, hence chunks, are consecutive
    double s1 = 0.0, s2 = 0.0;
    for (int64_t t = bg * s.Cg * per_row; t < (bg + 1) * s.Cg * per_row; ++t) {
      s1 += sums[t * 2];
      s2 += sums[t * 2 + 1];
    }
    const double m = s1 / group_size;
    const double var = std::max(s2 / group_size - m * m, 0.0);
    mean[bg] = static_cast<T>(static_cast<double>(x[bg * group_size]) + m);
    rstd[bg] = static_cast<T>(1.0 / std::sqrt(var + eps));
  }
  for_each_chunk(rows, s.S, [&](int64_t, int64_t row, int64_t begin, int64_t n) {
    const RowAffine<T> f = row_affine(w, bias, mean, rstd, row, s);
    const int64_t off = row * s.S + begin;
    scale_shift_silu(x + off, r != nullptr ? r + off : nullptr, f.a, f.shift, n, y + off);
  });
}

template <typename T>
void backward(const T* dy, const T* x, const T* w, const T* bias, const T* r, const T* mean,
              const T* rstd, T* dx, T* dw, T* db, T* dr, const GroupNormShape& s) {
  const int64_t rows = s.B * s.C, per_row = chunks_per_row(s.S);
  // silu's gradient g of a chunk, written to dr (the residual's gradient) or, without a
  // residual, to the thread's scratch row
  std::vector<T> scratch(dr == nullptr ? static_cast<size_t>(at::get_num_threads() * kChunk) : 0);
  auto chunk_silu_grads = [&](int64_t row, int64_t begin, int64_t n) -> T* {
    const int64_t off = row * s.S + begin;
    T* g = dr != nullptr ? dr + off : scratch.data() + at::get_thread_num() * kChunk;
    const RowAffine<T> f = row_affine(w, bias, mean, rstd, row, s);
    silu_grads(dy + off, x + off, r != nullptr ? r + off : nullptr, f.a, f.shift, n, g);
    return g;
  };
  std::vector<double> sums(rows * per_row * 2);  // per chunk: sum of g, sum of g * xhat
  for_each_chunk(rows, s.S, [&](int64_t t, int64_t row, int64_t begin, int64_t n) {
    const int64_t bg = row / s.Cg;
    grad_sums(chunk_silu_grads(row, begin, n), x + row * s.S + begin, static_cast<double>(mean[bg]),
              static_cast<double>(rstd[bg]), n, &sums[t * 2]);
  });
  std::vector<double> row_sums(rows * 2, 0.0);  // per (b, c), chunks added in order
  for (int64_t t = 0; t < rows * per_row; ++t) {
    row_sums[t / per_row * 2] += sums[t * 2];
    row_sums[t / per_row * 2 + 1] += sums[t * 2 + 1];
  }
  for (int64_t c = 0; c < s.C; ++c) {
    double sw = 0.0, sb = 0.0;
    for (int64_t b = 0; b < s.B; ++b) {
      sb += row_sums[(b * s.C + c) * 2];
      sw += row_sums[(b * s.C + c) * 2 + 1];
    }
    dw[c] = static_cast<T>(sw);
    db[c] = static_cast<T>(sb);
  }
  // per group: the means of dxhat = g * w and of dxhat * xhat
  std::vector<T> m1(s.B * s.G), m2(s.B * s.G);
  const double group_size = static_cast<double>(s.Cg * s.S);
  for (int64_t bg = 0; bg < s.B * s.G; ++bg) {
    double a1 = 0.0, a2 = 0.0;
    for (int64_t row = bg * s.Cg; row < (bg + 1) * s.Cg; ++row) {
      a1 += static_cast<double>(w[row % s.C]) * row_sums[row * 2];
      a2 += static_cast<double>(w[row % s.C]) * row_sums[row * 2 + 1];
    }
    m1[bg] = static_cast<T>(a1 / group_size);
    m2[bg] = static_cast<T>(a2 / group_size);
  }
  for_each_chunk(rows, s.S, [&](int64_t, int64_t row, int64_t begin, int64_t n) {
    const int64_t c = row % s.C, bg = row / s.Cg, off = row * s.S + begin;
    // with a residual, g is still in dr; the scratch rows were reused by other chunks
    const T* g = dr != nullptr ? dr + off : chunk_silu_grads(row, begin, n);
    input_grads(g, x + off, w[c], mean[bg], rstd[bg], m1[bg], m2[bg], n, dx + off);
  });
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> group_norm_silu_cpu(
    const at::Tensor& input, const at::Tensor& weight, const at::Tensor& bias, int64_t groups,
    double eps, const c10::optional<at::Tensor>& residual) {
  const GroupNormShape s = check_group_norm_silu(input, weight, bias, residual, groups, eps, kOp);
  const at::Tensor x = input.detach().contiguous();
  const at::Tensor w = weight.detach().contiguous(), b = bias.detach().contiguous();
  const at::Tensor r = residual.has_value() ? residual->detach().contiguous() : at::Tensor();
  at::Tensor out = at::empty_like(x);
  at::Tensor mean = at::empty({s.B, s.G}, x.options());
  at::Tensor rstd = at::empty({s.B, s.G}, x.options());
  if (s.S == 0) {  // an empty group: its mean is undefined (as group_norm's)
    mean.fill_(NAN);
    rstd.fill_(NAN);
    return {out, mean, rstd};
  }
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "group_norm_silu_cpu", [&] {
    using T = scalar_t;
    forward(x.data_ptr<T>(), w.data_ptr<T>(), b.data_ptr<T>(), r.defined() ? r.data_ptr<T>() : nullptr,
            out.data_ptr<T>(), mean.data_ptr<T>(), rstd.data_ptr<T>(), s, eps);
  });
  return {out, mean, rstd};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> group_norm_silu_backward_cpu(
    const at::Tensor& grad, const at::Tensor& input, const at::Tensor& weight,
    const at::Tensor& bias, const c10::optional<at::Tensor>& residual, const at::Tensor& mean,
    const at::Tensor& rstd, int64_t groups) {
  const GroupNormShape s = check_group_norm_silu_backward(grad, input, weight, bias, residual, mean,
                                                          rstd, groups, kOpBwd);
  const at::Tensor g = grad.detach().contiguous(), x = input.detach().contiguous();
  const at::Tensor w = weight.detach().contiguous(), b = bias.detach().contiguous();
  const at::Tensor r = residual.has_value() ? residual->detach().contiguous() : at::Tensor();
  const at::Tensor m = mean.detach().contiguous(), rs = rstd.detach().contiguous();
  at::Tensor grad_input = at::empty_like(x);
  at::Tensor grad_weight = at::zeros_like(w), grad_bias = at::zeros_like(b);
  at::Tensor grad_residual = r.defined() ? at::empty_like(r) : at::empty({0}, x.options());
  if (s.S == 0 || s.B == 0) return {grad_input, grad_weight, grad_bias, grad_residual};
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "group_norm_silu_backward_cpu", [&] {
    using T = scalar_t;
    backward(g.data_ptr<T>(), x.data_ptr<T>(), w.data_ptr<T>(), b.data_ptr<T>(),
             r.defined() ? r.data_ptr<T>() : nullptr, m.data_ptr<T>(), rs.data_ptr<T>(),
             grad_input.data_ptr<T>(), grad_weight.data_ptr<T>(), grad_bias.data_ptr<T>(),
             r.defined() ? grad_residual.data_ptr<T>() : nullptr, s);
  });
  return {grad_input, grad_weight, grad_bias, grad_residual};
}

}  // namespace

TORCH_LIBRARY_IMPL(t3fast, CPU, m) {
  m.impl("group_norm_silu", &group_norm_silu_cpu);
  m.impl("group_norm_silu_backward", &group_norm_silu_backward_cpu);
}

}  // namespace t3fast
