// Python bindings of the emulated triplane_decode kernels: the launchers of
// csrc/cuda/triplane_decode*_kernel.cu called as the CUDA glue calls them
// (csrc/cuda/triplane_decode.cpp), on CPU tensors. Inputs are assumed checked (the tests pass
// valid ones); only the kernel layer is under test.
#include <torch/extension.h>

#include <stdexcept>
#include <string>
#include <vector>

#include "cuda/kernels.h"

cudaError_t emulator_selftest(const std::string& name, const float* in, float* out, int blocks);

namespace {

namespace cuda = t3fast::cuda;

template <typename S>
struct Cuda {
  using type = S;
};
template <>
struct Cuda<c10::Half> {
  using type = __half;
};
template <>
struct Cuda<c10::BFloat16> {
  using type = __nv_bfloat16;
};

template <typename T>
T* data(const torch::Tensor& t) {
  return reinterpret_cast<T*>(t.data_ptr());
}

void check(cudaError_t err) {
  if (err == cudaSuccess) return;
  const std::string message = cudaGetErrorString(err);
  t3emu::launch_error().clear();
  throw std::runtime_error(message);
}

struct Problem {
  torch::Tensor xy, xz, yz, points, live;
  std::vector<torch::Tensor> weights, biases;
  std::vector<int64_t> grid;
  int64_t batch = 0, per_batch = 0;
  std::vector<int> widths;
};

Problem problem(const torch::Tensor& xy, const torch::Tensor& xz, const torch::Tensor& yz,
                const std::vector<torch::Tensor>& weights,
                const std::vector<torch::Tensor>& biases,
                const c10::optional<torch::Tensor>& points,
                const c10::optional<std::vector<int64_t>>& grid,
                const c10::optional<torch::Tensor>& live) {
  Problem p;
  p.xy = xy.contiguous();
  p.xz = xz.contiguous();
  p.yz = yz.contiguous();
  for (size_t i = 0; i < weights.size(); ++i) {
    p.weights.push_back(weights[i].contiguous());
    p.biases.push_back(biases[i].contiguous());
  }
  p.batch = xy.size(0);
  if (points.has_value()) {
    p.points = points->contiguous();
    p.per_batch = points->size(1);
  } else {
    p.grid = *grid;
    p.per_batch = p.grid[0] * p.grid[1] * p.grid[2];
  }
  if (live.has_value()) p.live = live->to(torch::kInt64).contiguous();
  p.widths.push_back(static_cast<int>(weights[0].size(1)));
  for (const auto& w : weights) p.widths.push_back(static_cast<int>(w.size(0)));
  return p;
}

template <typename T>
cuda::Triplane<T> triplane_of(const Problem& p) {
  cuda::Triplane<T> t;
  t.xy = data<const T>(p.xy);
  t.xz = data<const T>(p.xz);
  t.yz = data<const T>(p.yz);
  t.batch = p.batch;
  t.channels = static_cast<int>(p.xy.size(1));
  t.sx = static_cast<int>(p.xy.size(2));
  t.sy = static_cast<int>(p.xy.size(3));
  t.sz = static_cast<int>(p.xz.size(3));
  return t;
}

template <typename T>
cuda::Query<T> query_of(const Problem& p) {
  cuda::Query<T> q;
  q.points = p.points.defined() ? data<const T>(p.points) : nullptr;
  q.num_points = p.per_batch;
  q.gx = p.grid.empty() ? 0 : static_cast<int>(p.grid[0]);
  q.gy = p.grid.empty() ? 0 : static_cast<int>(p.grid[1]);
  q.gz = p.grid.empty() ? 0 : static_cast<int>(p.grid[2]);
  q.live = p.live.defined() ? p.live.data_ptr<int64_t>() : nullptr;
  return q;
}

template <typename Mma>
torch::ScalarType operand_dtype() {
  if constexpr (std::is_same_v<Mma, __half>) return torch::kHalf;
  if constexpr (std::is_same_v<Mma, __nv_bfloat16>) return torch::kBFloat16;
  return torch::kFloat;
}

// The tensor-core forward, with the glue's zero-padded weights and rounded biases.
template <typename T, typename Mma>
cudaError_t forward_mma(const Problem& p, int pe_freqs, T* logits, uint8_t* labels) {
  using S = cuda::mma_storage_t<Mma>;
  const auto pad = [](int64_t v) { return (v + cuda::kMmaPad - 1) / cuda::kMmaPad * cuda::kMmaPad; };
  std::vector<torch::Tensor> keep;
  cuda::MmaMlp<S> mlp;
  mlp.num_layers = static_cast<int>(p.weights.size());
  for (size_t l = 0; l < p.weights.size(); ++l) {
    const int64_t out = p.weights[l].size(0), in = p.weights[l].size(1);
    torch::Tensor w = torch::zeros({pad(out), pad(in)}, torch::dtype(operand_dtype<Mma>()));
    w.narrow(0, 0, out).narrow(1, 0, in).copy_(p.weights[l]);
    torch::Tensor b = torch::zeros({pad(out)}, torch::kFloat);
    b.narrow(0, 0, out).copy_(p.biases[l].to(operand_dtype<Mma>()));
    mlp.weight[l] = data<const S>(w);
    mlp.bias[l] = data<const float>(b);
    keep.push_back(w);
    keep.push_back(b);
  }
  for (size_t i = 0; i < p.widths.size(); ++i) mlp.width[i] = p.widths[i];
  return cuda::triplane_decode_forward_mma<T, Mma>(triplane_of<T>(p), query_of<T>(p), pe_freqs,
                                                   mlp, logits, labels, nullptr);
}

// triplane_decode's forward; precision: "cuda_cores" (the SIMT kernel) or the tensor-core
// kernel's "half", "bfloat16", "tf32".
torch::Tensor decode(const torch::Tensor& xy, const torch::Tensor& xz, const torch::Tensor& yz,
                     const std::vector<torch::Tensor>& weights,
                     const std::vector<torch::Tensor>& biases,
                     const c10::optional<torch::Tensor>& points,
                     const c10::optional<std::vector<int64_t>>& grid, int64_t pe_freqs,
                     bool argmax, const c10::optional<torch::Tensor>& live,
                     const std::string& precision) {
  const Problem p = problem(xy, xz, yz, weights, biases, points, grid, live);
  const int64_t total = p.batch * p.per_batch;
  torch::Tensor out = argmax ? torch::empty({total}, torch::kUInt8)
                             : torch::empty({total, p.widths.back()}, xy.options());
  AT_DISPATCH_FLOATING_TYPES_AND2(torch::kHalf, torch::kBFloat16, xy.scalar_type(), "decode", [&] {
    using T = typename Cuda<scalar_t>::type;
    T* logits = argmax ? nullptr : data<T>(out);
    uint8_t* labels = argmax ? data<uint8_t>(out) : nullptr;
    const int pe = static_cast<int>(pe_freqs);
    if (precision == "cuda_cores") {
      cuda::Mlp<T> mlp;
      mlp.num_layers = static_cast<int>(p.weights.size());
      for (size_t l = 0; l < p.weights.size(); ++l) {
        mlp.weight[l] = data<const T>(p.weights[l]);
        mlp.bias[l] = data<const T>(p.biases[l]);
      }
      for (size_t i = 0; i < p.widths.size(); ++i) mlp.width[i] = p.widths[i];
      check(cuda::triplane_decode_forward<T>(triplane_of<T>(p), query_of<T>(p), pe, mlp, logits,
                                             labels, nullptr));
      return;
    }
    if constexpr (std::is_same_v<T, double>) {
      throw std::invalid_argument("float64 has no tensor-core path");
    } else {
      if (precision == "half") {
        check(forward_mma<T, __half>(p, pe, logits, labels));
      } else if (precision == "bfloat16") {
        check(forward_mma<T, __nv_bfloat16>(p, pe, logits, labels));
      } else if (precision == "tf32") {
        if constexpr (std::is_same_v<T, float>) {
          check(forward_mma<T, cuda::Tf32>(p, pe, logits, labels));
        } else {
          throw std::invalid_argument("tf32 takes float32 inputs");
        }
      } else {
        throw std::invalid_argument("unknown precision " + precision);
      }
    }
  });
  if (argmax) return out.view({p.batch, p.per_batch});
  return out.view({p.batch, p.per_batch, p.widths.back()});
}

// The backward's feature kernel: [batch * N, C + 6 F] in float32 (float64 for float64).
torch::Tensor features(const torch::Tensor& xy, const torch::Tensor& xz, const torch::Tensor& yz,
                       const c10::optional<torch::Tensor>& points,
                       const c10::optional<std::vector<int64_t>>& grid, int64_t pe_freqs) {
  const torch::Tensor w = torch::empty({1, xy.size(1) + 6 * pe_freqs});
  const Problem p = problem(xy, xz, yz, {w}, {w}, points, grid, c10::nullopt);
  const auto acc = xy.scalar_type() == torch::kDouble ? torch::kDouble : torch::kFloat;
  const int64_t total = p.batch * p.per_batch;
  torch::Tensor out = torch::empty({total, p.widths[0]}, torch::dtype(acc));
  AT_DISPATCH_FLOATING_TYPES_AND2(torch::kHalf, torch::kBFloat16, xy.scalar_type(), "features", [&] {
    using T = typename Cuda<scalar_t>::type;
    check(cuda::triplane_features<T>(triplane_of<T>(p), query_of<T>(p), static_cast<int>(pe_freqs),
                                     0, total, data<cuda::acc_t<T>>(out), nullptr));
  });
  return out;
}

// The backward's scatter kernel: the planes' gradients (float32, float64 for float64) of the
// feature gradient grad [batch * N, ld >= C].
std::vector<torch::Tensor> scatter(const torch::Tensor& xy, const torch::Tensor& xz,
                                   const torch::Tensor& yz,
                                   const c10::optional<torch::Tensor>& points,
                                   const c10::optional<std::vector<int64_t>>& grid,
                                   const torch::Tensor& grad) {
  const torch::Tensor w = torch::empty({1, grad.size(1)});
  const Problem p = problem(xy, xz, yz, {w}, {w}, points, grid, c10::nullopt);
  const auto acc = xy.scalar_type() == torch::kDouble ? torch::kDouble : torch::kFloat;
  std::vector<torch::Tensor> out{torch::zeros(xy.sizes(), torch::dtype(acc)),
                                 torch::zeros(xz.sizes(), torch::dtype(acc)),
                                 torch::zeros(yz.sizes(), torch::dtype(acc))};
  const torch::Tensor g = grad.to(acc).contiguous();
  AT_DISPATCH_FLOATING_TYPES_AND2(torch::kHalf, torch::kBFloat16, xy.scalar_type(), "scatter", [&] {
    using T = typename Cuda<scalar_t>::type;
    using A = cuda::acc_t<T>;
    check(cuda::triplane_scatter_grad<T>(triplane_of<T>(p), query_of<T>(p), 0,
                                         p.batch * p.per_batch, data<const A>(g), g.size(1),
                                         data<A>(out[0]), data<A>(out[1]), data<A>(out[2]),
                                         nullptr));
  });
  return out;
}

// Runs one of selftest_kernel.cu's kernels on in (128 floats per block); returns out, or
// raises the launch's error.
torch::Tensor selftest(const std::string& name, const torch::Tensor& in) {
  const torch::Tensor x = in.to(torch::kFloat).contiguous();
  torch::Tensor out = torch::zeros_like(x);
  check(emulator_selftest(name, x.data_ptr<float>(), out.data_ptr<float>(),
                          static_cast<int>(x.numel() / 128)));
  return out;
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("decode", &decode);
  m.def("features", &features);
  m.def("scatter", &scatter);
  m.def("selftest", &selftest);
}
