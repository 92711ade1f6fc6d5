// CPU kernels of delta_fuse: next = delta + weight @ prev + bias per pixel, and its backward.
// The pixels of each batch element are cut into cache-sized blocks; per block the output is
// initialised from delta + bias and the 1x1 convolution is accumulated into it by one GEMM
// (beta = 1), so delta, prev and the output each cross memory once.
#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include "checks.h"
#include "cpu/simd.h"

namespace t3fast {
namespace {

constexpr const char* kOp = "delta_fuse";
constexpr const char* kOpBwd = "delta_fuse_backward";
constexpr int64_t kBlock = 2048;  // pixels per block: 64 channels x 2048 floats = 512 KiB

// Pixel blocks of at most kBlock pixels, as many per batch element as keeps every thread
// busy (a multiple of the thread count when the batch alone cannot).
struct Blocks {
  int64_t HW, per_batch, size, total;
  Blocks(int64_t B, int64_t hw) : HW(hw) {
    const int64_t threads = at::get_num_threads();
    per_batch = std::max<int64_t>(1, (hw + kBlock - 1) / kBlock);
    if (B > 0 && B < threads) {
      const int64_t share = (threads + B - 1) / B;
      per_batch = (per_batch + share - 1) / share * share;
    }
    per_batch = std::min(per_batch, std::max<int64_t>(1, hw));
    size = (hw + per_batch - 1) / per_batch;
    total = B * per_batch;
  }
  // (batch, first pixel, pixel count) of block i; the last blocks may be short or empty
  void get(int64_t i, int64_t& b, int64_t& p0, int64_t& n) const {
    b = i / per_batch;
    p0 = std::min(HW, (i % per_batch) * size);
    n = std::min(size, HW - p0);
  }
};

// dst[c, 0:n] = src[c, 0:n] + bias[c] for the C rows (stride HW) of a pixel block.
template <typename T>
T3FAST_SIMD_CLONES void add_bias_block(T* dst, const T* src, const T* bias, int64_t C,
                                       int64_t HW, int64_t n) {
  for (int64_t c = 0; c < C; ++c) {
    const T add = bias != nullptr ? bias[c] : T(0);
    for (int64_t k = 0; k < n; ++k) dst[c * HW + k] = src[c * HW + k] + add;
  }
}

// acc[c] += sum of src[c, 0:n] for the C rows (stride HW) of a pixel block.
template <typename T>
T3FAST_SIMD_CLONES void add_row_sums(T* acc, const T* src, int64_t C, int64_t HW, int64_t n) {
  for (int64_t c = 0; c < C; ++c) {
    T sum = T(0);
#pragma omp simd reduction(+ : sum)
    for (int64_t k = 0; k < n; ++k) sum += src[c * HW + k];
    acc[c] += sum;
  }
}

at::Tensor delta_fuse_cpu(const at::Tensor& delta, const at::Tensor& prev,
                          const at::Tensor& weight, const c10::optional<at::Tensor>& bias) {
  // The kernel uses ATen ops internally (also on worker threads, which do not inherit this
  // guard; they only see detached tensors); they must not record autograd history.
  at::AutoDispatchBelowADInplaceOrView guard;
  const DeltaFuseShape s = check_delta_fuse(delta, prev, weight, bias, kOp);
  const int64_t B = s.B, C = s.C, Cin = s.C_in, HW = s.H * s.W;
  const at::Tensor d = delta.detach().contiguous().view({B, C, HW});
  const at::Tensor pv = prev.detach().contiguous().view({B, Cin, HW});
  const at::Tensor w = weight.detach().contiguous();
  at::Tensor out = at::empty_like(d);
  if (out.numel() == 0) return out.view(delta.sizes());
  const Blocks blocks(B, HW);
  const at::Tensor bias_c = bias.has_value() ? bias->contiguous() : at::Tensor();
  AT_DISPATCH_FLOATING_TYPES(d.scalar_type(), "delta_fuse_cpu", [&] {
    using T = scalar_t;
    const T* pd = d.data_ptr<T>();
    const T* pb = bias_c.defined() ? bias_c.data_ptr<T>() : nullptr;
    T* po = out.data_ptr<T>();
    at::parallel_for(0, blocks.total, 1, [&](int64_t i0, int64_t i1) {
      for (int64_t i = i0; i < i1; ++i) {
        int64_t b, p0, n;
        blocks.get(i, b, p0, n);
        if (n == 0) continue;
        add_bias_block(po + b * C * HW + p0, pd + b * C * HW + p0, pb, C, HW, n);
        at::Tensor dst = out[b].narrow(1, p0, n);
        dst.addmm_(w, pv[b].narrow(1, p0, n));
      }
    });
  });
  return out.view(delta.sizes());
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> delta_fuse_backward_cpu(
    const at::Tensor& grad_out, const at::Tensor& prev, const at::Tensor& weight) {
  // The kernel uses ATen ops internally; they must not record autograd history.
  at::AutoDispatchBelowADInplaceOrView guard;
  const DeltaFuseShape s = check_delta_fuse_backward(grad_out, prev, weight, kOpBwd);
  const int64_t B = s.B, C = s.C, Cin = s.C_in, HW = s.H * s.W;
  const at::Tensor g = grad_out.detach().contiguous().view({B, C, HW});
  const at::Tensor pv = prev.detach().contiguous().view({B, Cin, HW});
  const at::Tensor w = weight.detach().contiguous();
  at::Tensor grad_prev = at::empty({B, Cin, HW}, pv.options());
  const Blocks blocks(B, HW);
  // Per-thread partial sums of the weight and bias gradients.
  const int64_t threads = at::get_num_threads();
  at::Tensor gw = at::zeros({threads, C, Cin}, pv.options());
  at::Tensor gb = at::zeros({threads, C}, pv.options());
  at::parallel_for(0, blocks.total, 1, [&](int64_t i0, int64_t i1) {
    const int64_t tid = at::get_thread_num();
    TORCH_INTERNAL_ASSERT(tid < threads);
    at::Tensor gw_t = gw[tid], gb_t = gb[tid];
    for (int64_t i = i0; i < i1; ++i) {
      int64_t b, p0, n;
      blocks.get(i, b, p0, n);
      if (n == 0) continue;
      const at::Tensor g_blk = g[b].narrow(1, p0, n);
      const at::Tensor p_blk = pv[b].narrow(1, p0, n);
      at::Tensor gp_blk = grad_prev[b].narrow(1, p0, n);
      at::mm_out(gp_blk, w.t(), g_blk);
      gw_t.addmm_(g_blk, p_blk.t());
      AT_DISPATCH_FLOATING_TYPES(g.scalar_type(), "delta_fuse_backward_cpu", [&] {
        add_row_sums(gb_t.data_ptr<scalar_t>(), g_blk.data_ptr<scalar_t>(), C, HW, n);
      });
    }
  });
  return {grad_prev.view(prev.sizes()), gw.sum(0), gb.sum(0)};
}

}  // namespace

TORCH_LIBRARY_IMPL(t3fast, CPU, m) {
  m.impl("delta_fuse", &delta_fuse_cpu);
  m.impl("delta_fuse_backward", &delta_fuse_backward_cpu);
}

}  // namespace t3fast
