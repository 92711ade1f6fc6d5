// Argument checks shared by the CPU and CUDA glue. Every message names the op, the argument,
// and what was expected versus what was passed, e.g.
//   "t3fast.triplane_decode: xz must have 4 dims [B, C, X', Z'], got 3 dims [2, 8, 16]"
#pragma once

#include <ATen/ATen.h>

#include <string>
#include <vector>

namespace t3fast {

#define T3FAST_CHECK(cond, op, ...) TORCH_CHECK(cond, "t3fast.", op, ": ", __VA_ARGS__)

inline void check_dim(const at::Tensor& t, const char* op, const char* name, int64_t dim,
                      const char* layout) {
  T3FAST_CHECK(t.dim() == dim, op, name, " must have ", dim, " dims ", layout, ", got ",
               t.dim(), " dims ", t.sizes());
}

inline void check_size(const at::Tensor& t, const char* op, const char* name, int64_t d,
                       int64_t expected, const char* what) {
  T3FAST_CHECK(t.size(d) == expected, op, name, ".shape[", d, "] (", what, ") must be ",
               expected, ", got ", t.size(d), " (shape ", t.sizes(), ")");
}

inline void check_same_device(const at::Tensor& t, const at::Tensor& ref, const char* op,
                              const char* name, const char* ref_name) {
  T3FAST_CHECK(t.device() == ref.device(), op, name, " must be on the same device as ",
               ref_name, " (", ref.device(), "), got ", t.device());
}

inline void check_same_dtype(const at::Tensor& t, const at::Tensor& ref, const char* op,
                             const char* name, const char* ref_name) {
  T3FAST_CHECK(t.scalar_type() == ref.scalar_type(), op, name, " must have the dtype of ",
               ref_name, " (", ref.scalar_type(), "), got ", t.scalar_type());
}

// Floating dtypes a backend accepts: CPU takes float32/float64, CUDA also float16/bfloat16.
inline void check_float_dtype(const at::Tensor& t, const char* op, const char* name) {
  const auto st = t.scalar_type();
  if (t.is_cuda()) {
    T3FAST_CHECK(st == at::kFloat || st == at::kDouble || st == at::kHalf || st == at::kBFloat16,
                 op, name, " must be float32, float64, float16 or bfloat16 on CUDA, got ", st);
  } else {
    T3FAST_CHECK(st == at::kFloat || st == at::kDouble, op, name,
                 " must be float32 or float64 on CPU, got ", st);
  }
}

// Shapes of the MLP of triplane_decode: weights[i] [out_i, in_i], biases[i] [out_i],
// in_0 == in_features, in_{i+1} == out_i. Returns the layer widths [in_0, out_0, out_1, ...].
inline std::vector<int64_t> check_mlp(at::TensorList weights, at::TensorList biases,
                                      const at::Tensor& ref, int64_t in_features,
                                      const char* op) {
  T3FAST_CHECK(!weights.empty(), op, "weights must hold at least one layer, got none");
  T3FAST_CHECK(weights.size() == biases.size(), op, "weights and biases must have the same ",
               "number of layers, got ", weights.size(), " weights and ", biases.size(),
               " biases");
  std::vector<int64_t> widths{in_features};
  for (size_t i = 0; i < weights.size(); ++i) {
    const std::string w = "weights[" + std::to_string(i) + "]";
    const std::string b = "biases[" + std::to_string(i) + "]";
    check_same_device(weights[i], ref, op, w.c_str(), "xy");
    check_same_device(biases[i], ref, op, b.c_str(), "xy");
    check_same_dtype(weights[i], ref, op, w.c_str(), "xy");
    check_same_dtype(biases[i], ref, op, b.c_str(), "xy");
    check_dim(weights[i], op, w.c_str(), 2, "[out, in]");
    check_dim(biases[i], op, b.c_str(), 1, "[out]");
    T3FAST_CHECK(weights[i].size(1) == widths.back(), op, w, ".shape[1] (in features) must be ",
                 widths.back(),
                 i == 0 ? " (C + 6 * pe_freqs)" : " (the previous layer's out features)",
                 ", got ", weights[i].size(1), " (shape ", weights[i].sizes(), ")");
    T3FAST_CHECK(biases[i].size(0) == weights[i].size(0), op, b, ".shape[0] must be ",
                 weights[i].size(0), " (", w, ".shape[0]), got ", biases[i].size(0));
    widths.push_back(weights[i].size(0));
  }
  return widths;
}

// The three planes: xy [B, C, X', Y'], xz [B, C, X', Z'], yz [B, C, Y', Z'].
inline void check_planes(const at::Tensor& xy, const at::Tensor& xz, const at::Tensor& yz,
                         const char* op) {
  check_dim(xy, op, "xy", 4, "[B, C, X', Y']");
  check_dim(xz, op, "xz", 4, "[B, C, X', Z']");
  check_dim(yz, op, "yz", 4, "[B, C, Y', Z']");
  check_float_dtype(xy, op, "xy");
  check_same_dtype(xz, xy, op, "xz", "xy");
  check_same_dtype(yz, xy, op, "yz", "xy");
  check_same_device(xz, xy, op, "xz", "xy");
  check_same_device(yz, xy, op, "yz", "xy");
  check_size(xz, op, "xz", 0, xy.size(0), "batch, as xy");
  check_size(yz, op, "yz", 0, xy.size(0), "batch, as xy");
  check_size(xz, op, "xz", 1, xy.size(1), "channels, as xy");
  check_size(yz, op, "yz", 1, xy.size(1), "channels, as xy");
  check_size(xz, op, "xz", 2, xy.size(2), "X', as xy.shape[2]");
  check_size(yz, op, "yz", 2, xy.size(3), "Y', as xy.shape[3]");
  check_size(yz, op, "yz", 3, xz.size(3), "Z', as xz.shape[3]");
  T3FAST_CHECK(xy.size(1) > 0, op, "planes must have at least one channel, got xy ",
               xy.sizes());
  for (const auto* p : {&xy, &xz, &yz}) {
    T3FAST_CHECK(p->size(2) > 0 && p->size(3) > 0, op, "planes must have non-empty spatial ",
                 "dims, got xy ", xy.sizes(), ", xz ", xz.sizes(), ", yz ", yz.sizes());
  }
}

// Query arguments: exactly one of points [B, N, 3] / grid (X, Y, Z).
inline void check_query(const at::Tensor& xy, const c10::optional<at::Tensor>& points,
                        c10::OptionalIntArrayRef grid, int64_t pe_freqs, const char* op) {
  T3FAST_CHECK(points.has_value() != grid.has_value(), op,
               "exactly one of grid and points must be given, got ",
               points.has_value() ? "both" : "neither");
  T3FAST_CHECK(pe_freqs >= 0 && pe_freqs <= 30, op, "pe_freqs must be in [0, 30], got ",
               pe_freqs);
  if (points.has_value()) {
    const auto& p = *points;
    check_dim(p, op, "points", 3, "[B, N, 3]");
    check_size(p, op, "points", 0, xy.size(0), "batch, as xy");
    check_size(p, op, "points", 2, 3, "coordinates (x, y, z)");
    check_same_device(p, xy, op, "points", "xy");
    check_same_dtype(p, xy, op, "points", "xy");
  } else {
    T3FAST_CHECK(grid->size() == 3, op, "grid must be (X, Y, Z), got ", grid->size(),
                 " values ", *grid);
    for (auto n : *grid) {
      T3FAST_CHECK(n >= 0, op, "grid sizes must be >= 0, got ", *grid);
    }
  }
}

// axis_pool: volume [B, C, X, Y, Z] with non-empty X, Y, Z.
inline void check_volume(const at::Tensor& volume, const char* op) {
  check_dim(volume, op, "volume", 5, "[B, C, X, Y, Z]");
  check_float_dtype(volume, op, "volume");
  T3FAST_CHECK(volume.size(2) > 0 && volume.size(3) > 0 && volume.size(4) > 0, op,
               "volume must have non-empty X, Y, Z, got ", volume.sizes());
}

// axis_pool_backward: grad_xy [B, C, X, Y], grad_xz [B, C, X, Z], grad_yz [B, C, Y, Z].
inline void check_plane_grads(const at::Tensor& grad_xy, const at::Tensor& grad_xz,
                              const at::Tensor& grad_yz, const char* op) {
  check_dim(grad_xy, op, "grad_xy", 4, "[B, C, X, Y]");
  check_dim(grad_xz, op, "grad_xz", 4, "[B, C, X, Z]");
  check_dim(grad_yz, op, "grad_yz", 4, "[B, C, Y, Z]");
  check_float_dtype(grad_xy, op, "grad_xy");
  check_same_dtype(grad_xz, grad_xy, op, "grad_xz", "grad_xy");
  check_same_dtype(grad_yz, grad_xy, op, "grad_yz", "grad_xy");
  check_same_device(grad_xz, grad_xy, op, "grad_xz", "grad_xy");
  check_same_device(grad_yz, grad_xy, op, "grad_yz", "grad_xy");
  check_size(grad_xz, op, "grad_xz", 0, grad_xy.size(0), "batch, as grad_xy");
  check_size(grad_xz, op, "grad_xz", 1, grad_xy.size(1), "channels, as grad_xy");
  check_size(grad_xz, op, "grad_xz", 2, grad_xy.size(2), "X, as grad_xy.shape[2]");
  check_size(grad_yz, op, "grad_yz", 0, grad_xy.size(0), "batch, as grad_xy");
  check_size(grad_yz, op, "grad_yz", 1, grad_xy.size(1), "channels, as grad_xy");
  check_size(grad_yz, op, "grad_yz", 2, grad_xy.size(3), "Y, as grad_xy.shape[3]");
  check_size(grad_yz, op, "grad_yz", 3, grad_xz.size(3), "Z, as grad_xz.shape[3]");
}

// delta_fuse (and its backward): prev [B, C_in, H, W], weight [C, C_in].
inline void check_prev_weight(const at::Tensor& prev, const at::Tensor& weight, const char* op) {
  check_dim(prev, op, "prev", 4, "[B, C_in, H, W]");
  check_dim(weight, op, "weight", 2, "[C, C_in]");
  check_float_dtype(prev, op, "prev");
  check_same_dtype(weight, prev, op, "weight", "prev");
  check_same_device(weight, prev, op, "weight", "prev");
  check_size(weight, op, "weight", 1, prev.size(1), "C_in, as prev.shape[1]");
}

// delta_fuse: delta [B, C, H, W], prev [B, C_in, H, W], weight [C, C_in], bias [C] or none.
inline void check_delta_fuse(const at::Tensor& delta, const at::Tensor& prev,
                             const at::Tensor& weight, const c10::optional<at::Tensor>& bias,
                             const char* op) {
  check_dim(delta, op, "delta", 4, "[B, C, H, W]");
  check_float_dtype(delta, op, "delta");
  check_prev_weight(prev, weight, op);
  check_same_dtype(prev, delta, op, "prev", "delta");
  check_same_device(prev, delta, op, "prev", "delta");
  check_size(prev, op, "prev", 0, delta.size(0), "batch, as delta");
  check_size(prev, op, "prev", 2, delta.size(2), "H, as delta");
  check_size(prev, op, "prev", 3, delta.size(3), "W, as delta");
  check_size(weight, op, "weight", 0, delta.size(1), "C, as delta.shape[1]");
  if (bias.has_value()) {
    check_dim(*bias, op, "bias", 1, "[C]");
    check_same_dtype(*bias, delta, op, "bias", "delta");
    check_same_device(*bias, delta, op, "bias", "delta");
    check_size(*bias, op, "bias", 0, delta.size(1), "C, as delta.shape[1]");
  }
}

// delta_fuse_backward: grad_out [B, C, H, W] against prev [B, C_in, H, W], weight [C, C_in].
inline void check_delta_fuse_backward(const at::Tensor& grad_out, const at::Tensor& prev,
                                      const at::Tensor& weight, const char* op) {
  check_prev_weight(prev, weight, op);
  check_dim(grad_out, op, "grad_out", 4, "[B, C, H, W]");
  check_same_dtype(grad_out, prev, op, "grad_out", "prev");
  check_same_device(grad_out, prev, op, "grad_out", "prev");
  check_size(grad_out, op, "grad_out", 0, prev.size(0), "batch, as prev");
  check_size(grad_out, op, "grad_out", 1, weight.size(0), "C, as weight.shape[0]");
  check_size(grad_out, op, "grad_out", 2, prev.size(2), "H, as prev");
  check_size(grad_out, op, "grad_out", 3, prev.size(3), "W, as prev");
}

// triplane_decode_backward: grad_out must have the forward output's shape, dtype, device.
inline void check_grad_out(const at::Tensor& grad_out, const at::Tensor& xy,
                           at::IntArrayRef shape, const char* op) {
  T3FAST_CHECK(grad_out.sizes() == shape, op, "grad_out must have shape ", shape, ", got ",
               grad_out.sizes());
  check_same_dtype(grad_out, xy, op, "grad_out", "xy");
  check_same_device(grad_out, xy, op, "grad_out", "xy");
}

}  // namespace t3fast
