// Argument checks of triplane_decode and its backward (see triplane_args.h). Every message
// names the op, the argument, and what was expected versus what was passed.
#include "triplane_args.h"

#include <string>

#include "checks.h"

namespace t3fast {
namespace {

// Planes as in check_planes, with at least one channel and non-empty spatial dims (a
// lookup needs a cell to read).
void check_triplane(const at::Tensor& xy, const at::Tensor& xz, const at::Tensor& yz,
                    const char* op) {
  check_planes(xy, xz, yz, kTriplane, op);
  T3FAST_CHECK(xy.size(1) > 0, op, "planes must have at least one channel, got xy ",
               xy.sizes());
  for (const auto* p : {&xy, &xz, &yz}) {
    T3FAST_CHECK(p->size(2) > 0 && p->size(3) > 0, op, "planes must have non-empty spatial ",
                 "dims, got xy ", xy.sizes(), ", xz ", xz.sizes(), ", yz ", yz.sizes());
  }
}

// Query arguments: exactly one of points [B, N, 3] / grid (X, Y, Z).
void check_query(const at::Tensor& xy, const c10::optional<at::Tensor>& points,
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

// Shapes of the MLP: weights[i] [out_i, in_i], biases[i] [out_i], in_0 == in_features,
// in_{i+1} == out_i. Returns the layer widths [in_0, out_0, out_1, ...].
std::vector<int64_t> check_mlp(at::TensorList weights, at::TensorList biases,
                               const at::Tensor& xy, int64_t in_features, const char* op) {
  T3FAST_CHECK(!weights.empty(), op, "weights must hold at least one layer, got none");
  T3FAST_CHECK(weights.size() == biases.size(), op, "weights and biases must have the same ",
               "number of layers, got ", weights.size(), " weights and ", biases.size(),
               " biases");
  std::vector<int64_t> widths{in_features};
  for (size_t i = 0; i < weights.size(); ++i) {
    const std::string w = "weights[" + std::to_string(i) + "]";
    const std::string b = "biases[" + std::to_string(i) + "]";
    check_same_device(weights[i], xy, op, w.c_str(), "xy");
    check_same_device(biases[i], xy, op, b.c_str(), "xy");
    check_same_dtype(weights[i], xy, op, w.c_str(), "xy");
    check_same_dtype(biases[i], xy, op, b.c_str(), "xy");
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

}  // namespace

std::vector<int64_t> TriplaneProblem::query_shape() const {
  if (grid_mode) return {B, GX, GY, GZ};
  return {B, per_batch};
}

std::vector<int64_t> TriplaneProblem::logits_shape() const {
  auto shape = query_shape();
  shape.push_back(classes());
  return shape;
}

at::Tensor TriplaneProblem::empty_output(const at::Tensor& xy, bool argmax) const {
  if (argmax) return at::empty(query_shape(), xy.options().dtype(at::kByte));
  return at::empty(logits_shape(), xy.options());
}

TriplaneProblem parse_triplane_args(const at::Tensor& xy, const at::Tensor& xz,
                                    const at::Tensor& yz, at::TensorList weights,
                                    at::TensorList biases,
                                    const c10::optional<at::Tensor>& points,
                                    c10::OptionalIntArrayRef grid, int64_t pe_freqs, bool argmax,
                                    const char* op) {
  check_triplane(xy, xz, yz, op);
  check_query(xy, points, grid, pe_freqs, op);
  TriplaneProblem p;
  p.B = xy.size(0);
  p.C = xy.size(1);
  p.PX = xy.size(2);
  p.PY = xy.size(3);
  p.PZ = xz.size(3);
  p.pe_freqs = pe_freqs;
  p.widths = check_mlp(weights, biases, xy, p.C + 6 * pe_freqs, op);
  T3FAST_CHECK(!argmax || (p.classes() >= 1 && p.classes() <= 256), op,
               "argmax=True needs 1 to 256 classes (uint8 labels), got ", p.classes());
  p.grid_mode = grid.has_value();
  if (p.grid_mode) {
    p.GX = (*grid)[0];
    p.GY = (*grid)[1];
    p.GZ = (*grid)[2];
    p.per_batch = p.GX * p.GY * p.GZ;
  } else {
    p.per_batch = points->size(1);
  }
  return p;
}

void check_live(const c10::optional<at::Tensor>& live, const TriplaneProblem& p, bool argmax,
                const at::Tensor& xy, const char* op) {
  if (!live.has_value()) return;
  T3FAST_CHECK(!p.grid_mode && argmax, op,
               "live counts the points to decode: it needs points and argmax=True");
  check_same_device(*live, xy, op, "live", "xy");
  T3FAST_CHECK(live->scalar_type() == at::kLong, op, "live must be int64, got ", live->scalar_type());
  T3FAST_CHECK(live->dim() == 1 && live->size(0) == p.B, op, "live must be [B] = [", p.B,
               "] (one count per batch element), got ", live->sizes());
}

TriplaneProblem parse_triplane_backward_args(const at::Tensor& grad_out, const at::Tensor& xy,
                                             const at::Tensor& xz, const at::Tensor& yz,
                                             at::TensorList weights, at::TensorList biases,
                                             const c10::optional<at::Tensor>& points,
                                             c10::OptionalIntArrayRef grid, int64_t pe_freqs,
                                             const char* op) {
  TriplaneProblem p =
      parse_triplane_args(xy, xz, yz, weights, biases, points, grid, pe_freqs, false, op);
  const auto logits_shape = p.logits_shape();
  const at::IntArrayRef shape(logits_shape);
  T3FAST_CHECK(grad_out.sizes() == shape, op, "grad_out must have shape ", shape, ", got ",
               grad_out.sizes());
  check_same_dtype(grad_out, xy, op, "grad_out", "xy");
  check_same_device(grad_out, xy, op, "grad_out", "xy");
  return p;
}

}  // namespace t3fast
