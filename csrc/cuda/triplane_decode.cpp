// CUDA glue of triplane_decode and its backward: CUDA's limits on the arguments, allocation,
// dtype dispatch and launches of the kernels in triplane_decode_kernel.cu.
//
// Precision (PyTorch's rules for a linear layer): under CUDA autocast the MLP computes in the
// autocast dtype; float16 / bfloat16 inputs compute in their dtype; float32 inputs in TF32
// when torch.backends.cuda.matmul.allow_tf32 is on, else in float32; float64 in float64.
// Products accumulate in fp32 (double for double) in every case.
//
// Forward: one fused kernel: on tensor cores for half, bfloat16 and TF32
// (triplane_decode_mma_kernel.cu, compute capability 8.0 and newer), on CUDA cores for
// float32, float64 and on older devices (triplane_decode_kernel.cu).
// Backward: the query points are processed in chunks of kBackwardChunk. For a chunk, a kernel
// writes the features [P, C + 6F] (fp32, double for double), the layers are recomputed with
// cuBLAS GEMMs in the precision above keeping each layer's input, and the gradient is
// propagated back through them (grad W_l += G^T A_l, grad b_l += sum_p G,
// G <- (G W_l) * (A_l > 0)); a second kernel scatters the feature gradient of the C plane
// channels into the three planes with atomics. The [all points, hidden] tensors are never
// materialised; the weight, bias and plane gradients accumulate in fp32 (or double) before
// the final cast to the input dtype.
#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <ATen/autocast_mode.h>
#include <c10/core/DeviceGuard.h>
#include <c10/core/impl/LocalDispatchKeySet.h>
#include <torch/library.h>

#include <algorithm>
#include <climits>
#include <tuple>
#include <type_traits>
#include <utility>
#include <vector>

#include "checks.h"
#include "cuda/kernels.h"
#include "cuda/runtime.h"
#include "cuda/scalar_types.h"
#include "cuda/stream.h"
#include "triplane_args.h"

namespace t3fast {
namespace {

constexpr const char* kOp = "triplane_decode";
constexpr const char* kOpBwd = "triplane_decode_backward";
// Points per backward chunk: the recomputed activations take 64 MiB per 256-wide layer.
constexpr int64_t kBackwardChunk = 65536;

// The checked sizes and the tensors, contiguous, on the device of xy.
struct Problem : TriplaneProblem {
  at::Tensor xy, xz, yz;
  at::Tensor points;  // [B, N, 3], undefined in grid mode
  at::Tensor live;    // [B] int64 counts of the points to decode, or undefined: all
  std::vector<at::Tensor> weights, biases;

  explicit Problem(TriplaneProblem sizes) : TriplaneProblem(std::move(sizes)) {}
};

Problem make_problem(TriplaneProblem sizes, const at::Tensor& xy, const at::Tensor& xz,
                     const at::Tensor& yz, at::TensorList weights, at::TensorList biases,
                     const c10::optional<at::Tensor>& points, const char* op) {
  Problem p(std::move(sizes));
  // The kernels index plane rows/columns, channels and grid cells with 32-bit integers.
  T3FAST_CHECK(p.C <= INT_MAX && p.PX <= INT_MAX && p.PY <= INT_MAX && p.PZ <= INT_MAX, op,
               "plane channels and sizes must be < 2^31 on CUDA, got xy ", xy.sizes(), ", xz ",
               xz.sizes(), ", yz ", yz.sizes());
  T3FAST_CHECK(p.GX <= INT_MAX && p.GY <= INT_MAX && p.GZ <= INT_MAX, op,
               "grid sizes must be < 2^31 on CUDA, got [", p.GX, ", ", p.GY, ", ", p.GZ, "]");
  p.xy = xy.detach().contiguous();
  p.xz = xz.detach().contiguous();
  p.yz = yz.detach().contiguous();
  for (size_t i = 0; i < weights.size(); ++i) {
    p.weights.push_back(weights[i].detach().contiguous());
    p.biases.push_back(biases[i].detach().contiguous());
  }
  if (points.has_value()) p.points = points->detach().contiguous();
  return p;
}

template <typename T>
cuda::Triplane<T> triplane_of(const Problem& p) {
  cuda::Triplane<T> t;
  t.xy = ptr<const T>(p.xy);
  t.xz = ptr<const T>(p.xz);
  t.yz = ptr<const T>(p.yz);
  t.batch = p.B;
  t.channels = static_cast<int>(p.C);
  t.sx = static_cast<int>(p.PX);
  t.sy = static_cast<int>(p.PY);
  t.sz = static_cast<int>(p.PZ);
  return t;
}

template <typename T>
cuda::Query<T> query_of(const Problem& p) {
  cuda::Query<T> q;
  q.points = p.points.defined() ? ptr<const T>(p.points) : nullptr;
  q.num_points = p.per_batch;
  q.gx = static_cast<int>(p.GX);
  q.gy = static_cast<int>(p.GY);
  q.gz = static_cast<int>(p.GZ);
  q.live = p.live.defined() ? p.live.data_ptr<int64_t>() : nullptr;
  return q;
}

// How the MLP of a call computes (see the top of this file).
enum class Precision { kCudaCores, kHalf, kBFloat16, kTf32 };

// The dtype the MLP computes in: the autocast dtype under CUDA autocast (float64 excepted),
// else the inputs' dtype.
at::ScalarType compute_dtype(at::ScalarType input) {
  if (input != at::kDouble && at::autocast::is_autocast_enabled(at::kCUDA)) {
    return at::autocast::get_autocast_dtype(at::kCUDA);
  }
  return input;
}

// The forward kernel's precision; tensor cores need compute capability 8.0.
Precision forward_precision(const at::Tensor& xy, const char* op) {
  const at::ScalarType dtype = compute_dtype(xy.scalar_type());
  const bool float32 = dtype == at::kFloat && xy.scalar_type() == at::kFloat;
  const bool tf32 = float32 && at::globalContext().allowTF32CuBLAS();
  if (dtype != at::kHalf && dtype != at::kBFloat16 && !tf32) return Precision::kCudaCores;
  if (device_attribute(cudaDevAttrComputeCapabilityMajor, xy.get_device(), op) < 8) {
    return Precision::kCudaCores;
  }
  return dtype == at::kHalf ? Precision::kHalf
         : dtype == at::kBFloat16 ? Precision::kBFloat16
                                  : Precision::kTf32;
}

// Bytes per MMA operand of a tensor-core precision.
int operand_bytes(Precision precision) { return precision == Precision::kTf32 ? 4 : 2; }

// Limits of the fused forward kernel, with errors that name them.
void check_fused_limits(const Problem& p, Precision precision, const char* op) {
  T3FAST_CHECK(p.layers() <= cuda::kTriplaneMaxLayers, op, "the CUDA kernel supports at most ",
               cuda::kTriplaneMaxLayers, " layers, got ", p.layers());
  T3FAST_CHECK(p.max_width() <= cuda::kTriplaneMaxWidth, op,
               "the CUDA kernel supports widths (C + 6 * pe_freqs and every layer's out "
               "features) up to ",
               cuda::kTriplaneMaxWidth, ", got widths ", at::IntArrayRef(p.widths));
  std::vector<int> widths(p.widths.begin(), p.widths.end());
  const int layers = static_cast<int>(p.layers());
  const bool dbl = p.xy.scalar_type() == at::kDouble;
  const size_t need =
      precision == Precision::kCudaCores
          ? cuda::triplane_decode_min_shared_bytes(widths.data(), layers, dbl)
          : cuda::triplane_decode_mma_shared_bytes(widths.data(), layers,
                                                   operand_bytes(precision));
  const int available =
      device_attribute(cudaDevAttrMaxSharedMemoryPerBlockOptin, p.xy.get_device(), op);
  T3FAST_CHECK(need <= static_cast<size_t>(available), op, "layer widths ",
               at::IntArrayRef(p.widths), " need ", need, " bytes of shared memory per block in ",
               p.xy.scalar_type(), " but the device offers ", available,
               "; use narrower layers", dbl ? " or float32" : "");
}

template <typename Mma>
constexpr at::ScalarType operand_dtype() {
  if constexpr (std::is_same_v<Mma, __half>) return at::kHalf;
  if constexpr (std::is_same_v<Mma, __nv_bfloat16>) return at::kBFloat16;
  return at::kFloat;  // TF32 operands are stored as float
}

// The fused forward on tensor cores: the weights zero-padded to multiples of kMmaPad in the
// operand type and the biases in float32 (the kernel reads whole 16 x 16 tiles), then one
// launch.
template <typename T, typename Mma>
cudaError_t forward_mma(const Problem& p, int64_t pe_freqs, T* logits, uint8_t* labels,
                        cudaStream_t stream) {
  using S = cuda::mma_storage_t<Mma>;
  const auto pad = [](int64_t v) { return (v + cuda::kMmaPad - 1) / cuda::kMmaPad * cuda::kMmaPad; };
  std::vector<at::Tensor> padded;  // alive until the launch is queued (stream-ordered frees)
  cuda::MmaMlp<S> mlp;
  mlp.num_layers = static_cast<int>(p.layers());
  for (int64_t l = 0; l < p.layers(); ++l) {
    const int64_t in = p.widths[l];
    const int64_t out = p.widths[l + 1];
    at::Tensor w = at::zeros({pad(out), pad(in)}, p.xy.options().dtype(operand_dtype<Mma>()));
    w.narrow(0, 0, out).narrow(1, 0, in).copy_(p.weights[l]);
    at::Tensor b = at::zeros({pad(out)}, p.xy.options().dtype(at::kFloat));
    // rounded to a 16-bit operand type first, as the backward's GEMMs (and autocast's
    // linear) see the bias
    b.narrow(0, 0, out).copy_(p.biases[l].to(operand_dtype<Mma>()));
    mlp.weight[l] = ptr<const S>(w);
    mlp.bias[l] = ptr<const float>(b);
    padded.push_back(std::move(w));
    padded.push_back(std::move(b));
  }
  for (size_t i = 0; i < p.widths.size(); ++i) mlp.width[i] = static_cast<int>(p.widths[i]);
  return cuda::triplane_decode_forward_mma<T, Mma>(
      triplane_of<T>(p), query_of<T>(p), static_cast<int>(pe_freqs), mlp, logits, labels, stream);
}

template <typename T>
cudaError_t forward_mma(const Problem& p, Precision precision, int64_t pe_freqs, T* logits,
                        uint8_t* labels, cudaStream_t stream) {
  if constexpr (std::is_same_v<T, double>) {
    return cudaErrorInvalidValue;  // float64 always runs on CUDA cores
  } else {
    if (precision == Precision::kHalf) {
      return forward_mma<T, __half>(p, pe_freqs, logits, labels, stream);
    }
    if (precision == Precision::kBFloat16) {
      return forward_mma<T, __nv_bfloat16>(p, pe_freqs, logits, labels, stream);
    }
    if constexpr (std::is_same_v<T, float>) {
      return forward_mma<T, cuda::Tf32>(p, pe_freqs, logits, labels, stream);
    }
    return cudaErrorInvalidValue;  // TF32 is chosen for float32 inputs only
  }
}

at::Tensor triplane_decode_cuda(const at::Tensor& xy, const at::Tensor& xz, const at::Tensor& yz,
                                at::TensorList weights, at::TensorList biases,
                                const c10::optional<at::Tensor>& points,
                                c10::OptionalIntArrayRef grid, int64_t pe_freqs, bool argmax,
                                const c10::optional<at::Tensor>& live) {
  Problem p = make_problem(
      parse_triplane_args(xy, xz, yz, weights, biases, points, grid, pe_freqs, argmax, kOp), xy,
      xz, yz, weights, biases, points, kOp);
  check_live(live, p, argmax, xy, kOp);
  if (live.has_value()) p.live = live->contiguous();
  const c10::DeviceGuard device_guard(xy.device());
  // The precision is read from the autocast state; the padding copies must not be cast.
  const Precision precision = forward_precision(xy, kOp);
  const c10::impl::ExcludeDispatchKeyGuard no_autocast(c10::autocast_dispatch_keyset);
  at::Tensor out = p.empty_output(xy, argmax);
  if (out.numel() == 0) return out;
  check_fused_limits(p, precision, kOp);
  const cudaStream_t stream = current_stream(xy.get_device());
  cudaError_t err = cudaSuccess;
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, xy.scalar_type(),
                                  "triplane_decode_cuda", [&] {
    using T = cuda_type_t<scalar_t>;
    T* logits = argmax ? nullptr : ptr<T>(out);
    uint8_t* labels = argmax ? ptr<uint8_t>(out) : nullptr;
    if (precision != Precision::kCudaCores) {
      err = forward_mma<T>(p, precision, pe_freqs, logits, labels, stream);
      return;
    }
    cuda::Mlp<T> mlp;
    mlp.num_layers = static_cast<int>(p.layers());
    for (int64_t l = 0; l < p.layers(); ++l) {
      mlp.weight[l] = ptr<const T>(p.weights[l]);
      mlp.bias[l] = ptr<const T>(p.biases[l]);
    }
    for (size_t i = 0; i < p.widths.size(); ++i) mlp.width[i] = static_cast<int>(p.widths[i]);
    err = cuda::triplane_decode_forward<T>(triplane_of<T>(p), query_of<T>(p),
                                           static_cast<int>(pe_freqs), mlp, logits, labels,
                                           stream);
  });
  check_launch(err, kOp);
  return out;
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, std::vector<at::Tensor>, std::vector<at::Tensor>>
triplane_decode_backward_cuda(const at::Tensor& grad_out, const at::Tensor& xy,
                              const at::Tensor& xz, const at::Tensor& yz, at::TensorList weights,
                              at::TensorList biases, const c10::optional<at::Tensor>& points,
                              c10::OptionalIntArrayRef grid, int64_t pe_freqs) {
  // The GEMMs below are ATen ops; they must not record autograd history.
  at::AutoDispatchBelowADInplaceOrView guard;
  const Problem p = make_problem(parse_triplane_backward_args(grad_out, xy, xz, yz, weights,
                                                              biases, points, grid, pe_freqs,
                                                              kOpBwd),
                                 xy, xz, yz, weights, biases, points, kOpBwd);
  const c10::DeviceGuard device_guard(xy.device());
  // The GEMMs compute in `gemm` (cuBLAS applies allow_tf32 to float32 itself); the casts
  // below are explicit, so autocast must not cast again.
  const at::ScalarType gemm = compute_dtype(xy.scalar_type());
  const c10::impl::ExcludeDispatchKeyGuard no_autocast(c10::autocast_dispatch_keyset);

  const at::ScalarType acc = accumulation_dtype(xy);
  const auto opts = xy.options().dtype(acc);
  const int64_t L = p.layers();
  const int64_t in0 = p.widths[0];
  const int64_t total = p.B * p.per_batch;
  const at::Tensor go = grad_out.detach().contiguous().view({total, p.classes()});
  // In float16 every GEMM whose result the backward rounds has a float32 result, rounded once
  // (bias and ReLU in float32), as the forward kernel rounds: cuBLAS may otherwise reduce a
  // float16 GEMM's partial sums in float16 (PyTorch allows it by default), which moves
  // recomputed pre-activations across their ReLU kinks.
  const bool float32_sums = gemm == at::kHalf;
  std::vector<at::Tensor> w, wt, b, gw, gb;
  for (int64_t l = 0; l < L; ++l) {
    w.push_back(p.weights[l].to(gemm));
    wt.push_back(w.back().t());
    b.push_back(p.biases[l].to(float32_sums ? acc : gemm));
    gw.push_back(at::zeros(p.weights[l].sizes(), opts));
    gb.push_back(at::zeros(p.biases[l].sizes(), opts));
  }
  at::Tensor gxy = at::zeros(xy.sizes(), opts);
  at::Tensor gxz = at::zeros(xz.sizes(), opts);
  at::Tensor gyz = at::zeros(yz.sizes(), opts);

  const cudaStream_t stream = current_stream(xy.get_device());
  at::Tensor features = at::empty({std::min(total, kBackwardChunk), in0}, opts);
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, xy.scalar_type(),
                                  "triplane_decode_backward_cuda", [&] {
    using T = cuda_type_t<scalar_t>;
    using A = cuda::acc_t<T>;
    const cuda::Triplane<T> planes = triplane_of<T>(p);
    const cuda::Query<T> query = query_of<T>(p);
    for (int64_t start = 0; start < total; start += kBackwardChunk) {
      const int64_t count = std::min(kBackwardChunk, total - start);
      const at::Tensor chunk_features = features.narrow(0, 0, count);
      check_launch(cuda::triplane_features<T>(planes, query, static_cast<int>(p.pe_freqs), start,
                                              count, ptr<A>(chunk_features), stream),
                   kOpBwd);
      std::vector<at::Tensor> acts{chunk_features.to(gemm)};  // input of each layer
      for (int64_t l = 0; l + 1 < L; ++l) {
        if (float32_sums) {
          acts.push_back(at::mm(acts[l], wt[l], acc).add_(b[l]).relu_().to(gemm));
        } else {
          // bias and ReLU in the GEMM's epilogue (cuBLASLt) where it can
          acts.push_back(at::_addmm_activation(b[l], acts[l], wt[l]));
        }
      }
      at::Tensor g = go.narrow(0, start, count).to(gemm);
      for (int64_t l = L - 1; l >= 0; --l) {
        // fp32 accumulation across chunks, whatever the GEMMs' dtype
        if (gemm == acc) {
          gw[l].addmm_(g.t(), acts[l]);
        } else {
          gw[l].add_(at::mm(g.t(), acts[l], acc));
        }
        gb[l].add_(at::sum(g, {0}, false, acc));
        g = float32_sums ? at::mm(g, w[l], acc).to(gemm) : at::mm(g, w[l]);
        // ReLU backward (one kernel): zero where the layer's output was not positive (NaN included).
        if (l > 0) g = at::threshold_backward(g, acts[l], 0);
      }
      // g = [count, in0] feature gradient; its first C columns belong to the planes.
      const at::Tensor g_features = g.to(acc).contiguous();
      check_launch(cuda::triplane_scatter_grad<T>(planes, query, start, count,
                                                  ptr<const A>(g_features), in0, ptr<A>(gxy),
                                                  ptr<A>(gxz), ptr<A>(gyz), stream),
                   kOpBwd);
    }
  });

  const auto dtype = xy.scalar_type();
  std::vector<at::Tensor> grad_w, grad_b;
  for (int64_t l = 0; l < L; ++l) {
    grad_w.push_back(gw[l].to(dtype));
    grad_b.push_back(gb[l].to(dtype));
  }
  return {gxy.to(dtype), gxz.to(dtype), gyz.to(dtype), grad_w, grad_b};
}

}  // namespace

TORCH_LIBRARY_IMPL(t3fast, CUDA, m) {
  m.impl("triplane_decode", &triplane_decode_cuda);
  m.impl("triplane_decode_backward", &triplane_decode_backward_cuda);
}

}  // namespace t3fast
