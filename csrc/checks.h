// Argument checks shared by the CPU and CUDA glue. Every message names the op, the argument,
// and what was expected versus what was passed, e.g.
//   "t3fast.triplane_decode: xz must have 4 dims [B, C, X', Z'], got 3 dims [2, 8, 16]"
#pragma once

#include <ATen/ATen.h>

#include <cmath>
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

// The dtype the kernels accumulate a tensor's values in: float64 for float64, float32 otherwise
// (float16 and bfloat16 included).
inline at::ScalarType accumulation_dtype(const at::Tensor& t) {
  return t.scalar_type() == at::kDouble ? at::kDouble : at::kFloat;
}

// Sizes of a volume [B, C, X, Y, Z], which are also the sizes of its three axis planes
// xy [B, C, X, Y], xz [B, C, X, Z], yz [B, C, Y, Z].
struct VolumeShape {
  int64_t B, C, X, Y, Z;
};

// How the three planes and their axes are called in messages.
struct PlaneNames {
  const char *xy, *xz, *yz;
  const char *x, *y, *z;
};
// triplane_decode's planes, whose sizes X', Y', Z' are independent of the query grid's.
inline constexpr PlaneNames kTriplane{"xy", "xz", "yz", "X'", "Y'", "Z'"};
// axis_pool_backward's gradients of the three axis means.
inline constexpr PlaneNames kPlaneGrads{"grad_xy", "grad_xz", "grad_yz", "X", "Y", "Z"};

// Three planes xy [B, C, X, Y], xz [B, C, X, Z], yz [B, C, Y, Z] of one float dtype and one
// device. Returns their common sizes.
inline VolumeShape check_planes(const at::Tensor& xy, const at::Tensor& xz, const at::Tensor& yz,
                                const PlaneNames& n, const char* op) {
  const std::string b_c = "[B, C, ";
  check_dim(xy, op, n.xy, 4, (b_c + n.x + ", " + n.y + "]").c_str());
  check_dim(xz, op, n.xz, 4, (b_c + n.x + ", " + n.z + "]").c_str());
  check_dim(yz, op, n.yz, 4, (b_c + n.y + ", " + n.z + "]").c_str());
  check_float_dtype(xy, op, n.xy);
  check_same_dtype(xz, xy, op, n.xz, n.xy);
  check_same_dtype(yz, xy, op, n.yz, n.xy);
  check_same_device(xz, xy, op, n.xz, n.xy);
  check_same_device(yz, xy, op, n.yz, n.xy);
  const std::string as_xy = std::string(", as ") + n.xy;
  const std::string batch = "batch" + as_xy, channels = "channels" + as_xy;
  check_size(xz, op, n.xz, 0, xy.size(0), batch.c_str());
  check_size(yz, op, n.yz, 0, xy.size(0), batch.c_str());
  check_size(xz, op, n.xz, 1, xy.size(1), channels.c_str());
  check_size(yz, op, n.yz, 1, xy.size(1), channels.c_str());
  check_size(xz, op, n.xz, 2, xy.size(2), (n.x + as_xy + ".shape[2]").c_str());
  check_size(yz, op, n.yz, 2, xy.size(3), (n.y + as_xy + ".shape[3]").c_str());
  const std::string as_xz = std::string(", as ") + n.xz;
  check_size(yz, op, n.yz, 3, xz.size(3), (n.z + as_xz + ".shape[3]").c_str());
  return {xy.size(0), xy.size(1), xy.size(2), xy.size(3), xz.size(3)};
}

// axis_pool: volume [B, C, X, Y, Z] with non-empty X, Y, Z.
inline VolumeShape check_volume(const at::Tensor& volume, const char* op) {
  check_dim(volume, op, "volume", 5, "[B, C, X, Y, Z]");
  check_float_dtype(volume, op, "volume");
  T3FAST_CHECK(volume.size(2) > 0 && volume.size(3) > 0 && volume.size(4) > 0, op,
               "volume must have non-empty X, Y, Z, got ", volume.sizes());
  return {volume.size(0), volume.size(1), volume.size(2), volume.size(3), volume.size(4)};
}

// Sizes of delta_fuse: delta [B, C, H, W], prev [B, C_in, H, W], weight [C, C_in].
struct DeltaFuseShape {
  int64_t B, C, C_in, H, W;
};

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
inline DeltaFuseShape check_delta_fuse(const at::Tensor& delta, const at::Tensor& prev,
                                       const at::Tensor& weight,
                                       const c10::optional<at::Tensor>& bias, const char* op) {
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
  return {delta.size(0), delta.size(1), prev.size(1), delta.size(2), delta.size(3)};
}

// delta_fuse_backward: grad_out [B, C, H, W] against prev [B, C_in, H, W], weight [C, C_in].
inline DeltaFuseShape check_delta_fuse_backward(const at::Tensor& grad_out,
                                                const at::Tensor& prev, const at::Tensor& weight,
                                                const char* op) {
  check_prev_weight(prev, weight, op);
  check_dim(grad_out, op, "grad_out", 4, "[B, C, H, W]");
  check_same_dtype(grad_out, prev, op, "grad_out", "prev");
  check_same_device(grad_out, prev, op, "grad_out", "prev");
  check_size(grad_out, op, "grad_out", 0, prev.size(0), "batch, as prev");
  check_size(grad_out, op, "grad_out", 1, weight.size(0), "C, as weight.shape[0]");
  check_size(grad_out, op, "grad_out", 2, prev.size(2), "H, as prev");
  check_size(grad_out, op, "grad_out", 3, prev.size(3), "W, as prev");
  return {prev.size(0), weight.size(0), prev.size(1), prev.size(2), prev.size(3)};
}

// Sizes of matching_costs: present and previous [B, C, H, W], shifts (2 radius + 1)^2.
struct MatchingCostsShape {
  int64_t B, C, H, W, radius, shifts;
};

// matching_costs: present and previous [B, C, H, W] (at least one channel), radius >= 0.
inline MatchingCostsShape check_matching_costs(const at::Tensor& present,
                                               const at::Tensor& previous, int64_t radius,
                                               const char* op) {
  check_dim(present, op, "present", 4, "[B, C, H, W]");
  check_dim(previous, op, "previous", 4, "[B, C, H, W]");
  check_float_dtype(present, op, "present");
  check_same_device(previous, present, op, "previous", "present");
  check_same_dtype(previous, present, op, "previous", "present");
  T3FAST_CHECK(previous.sizes() == present.sizes(), op,
               "previous must have the shape of present ", present.sizes(), ", got ",
               previous.sizes());
  T3FAST_CHECK(present.size(1) > 0, op,
               "present must have at least one channel (the costs are channel means), got shape ",
               present.sizes());
  T3FAST_CHECK(radius >= 0 && radius <= 64, op, "radius must be in [0, 64], got ", radius);
  return {present.size(0), present.size(1), present.size(2), present.size(3), radius,
          (2 * radius + 1) * (2 * radius + 1)};
}

// matching_costs_backward: grad [B, (2 radius + 1)^2, H, W] against present and previous.
inline MatchingCostsShape check_matching_costs_backward(const at::Tensor& grad,
                                                        const at::Tensor& present,
                                                        const at::Tensor& previous,
                                                        int64_t radius, const char* op) {
  const MatchingCostsShape s = check_matching_costs(present, previous, radius, op);
  check_dim(grad, op, "grad", 4, "[B, (2 radius + 1)^2, H, W]");
  check_same_device(grad, present, op, "grad", "present");
  check_same_dtype(grad, present, op, "grad", "present");
  check_size(grad, op, "grad", 0, s.B, "batch, as present");
  check_size(grad, op, "grad", 1, s.shifts, "the (2 radius + 1)^2 shifts");
  check_size(grad, op, "grad", 2, s.H, "H, as present");
  check_size(grad, op, "grad", 3, s.W, "W, as present");
  return s;
}

// Sizes of group_norm_silu: input [B, C, *] viewed as [B, C, S], C in G groups of Cg channels.
struct GroupNormShape {
  int64_t B, C, S, G, Cg;
};

// group_norm_silu: input [B, C, *] (at least 2 dims), weight and bias [C], groups dividing C,
// eps >= 0, residual (if any) shaped, typed and placed as input.
inline GroupNormShape check_group_norm_silu(const at::Tensor& input, const at::Tensor& weight,
                                            const at::Tensor& bias,
                                            const c10::optional<at::Tensor>& residual,
                                            int64_t groups, double eps, const char* op) {
  T3FAST_CHECK(input.dim() >= 2, op, "input must have at least 2 dims [B, C, *], got ",
               input.dim(), " dims ", input.sizes());
  check_float_dtype(input, op, "input");
  check_dim(weight, op, "weight", 1, "[C]");
  check_dim(bias, op, "bias", 1, "[C]");
  check_same_device(weight, input, op, "weight", "input");
  check_same_device(bias, input, op, "bias", "input");
  check_same_dtype(weight, input, op, "weight", "input");
  check_same_dtype(bias, input, op, "bias", "input");
  const int64_t C = input.size(1);
  check_size(weight, op, "weight", 0, C, "C, as input.shape[1]");
  check_size(bias, op, "bias", 0, C, "C, as input.shape[1]");
  T3FAST_CHECK(groups >= 1 && C % groups == 0, op, "groups must be a positive divisor of the ",
               C, " channels, got ", groups);
  T3FAST_CHECK(eps >= 0.0 && std::isfinite(eps), op, "eps must be finite and >= 0, got ", eps);
  if (residual.has_value()) {
    check_same_device(*residual, input, op, "residual", "input");
    check_same_dtype(*residual, input, op, "residual", "input");
    T3FAST_CHECK(residual->sizes() == input.sizes(), op, "residual must have the shape of input ",
                 input.sizes(), ", got ", residual->sizes());
  }
  const int64_t B = input.size(0);
  const int64_t S = C == 0 || B == 0 ? 0 : input.numel() / (B * C);
  return {B, C, S, groups, C / groups};
}

// group_norm_silu_backward: grad shaped as input; mean and rstd [B, groups] in the accumulation
// dtype (float64 for float64 input, float32 otherwise).
inline GroupNormShape check_group_norm_silu_backward(
    const at::Tensor& grad, const at::Tensor& input, const at::Tensor& weight,
    const at::Tensor& bias, const c10::optional<at::Tensor>& residual, const at::Tensor& mean,
    const at::Tensor& rstd, int64_t groups, const char* op) {
  const GroupNormShape s = check_group_norm_silu(input, weight, bias, residual, groups, 0.0, op);
  check_same_device(grad, input, op, "grad", "input");
  check_same_dtype(grad, input, op, "grad", "input");
  T3FAST_CHECK(grad.sizes() == input.sizes(), op, "grad must have the shape of input ",
               input.sizes(), ", got ", grad.sizes());
  const auto acc = accumulation_dtype(input);
  for (const auto* t : {&mean, &rstd}) {
    const char* name = t == &mean ? "mean" : "rstd";
    check_same_device(*t, input, op, name, "input");
    T3FAST_CHECK(t->scalar_type() == acc, op, name, " must be ", acc, " for ",
                 input.scalar_type(), " input, got ", t->scalar_type());
    T3FAST_CHECK(t->dim() == 2 && t->size(0) == s.B && t->size(1) == s.G, op, name,
                 " must have shape [", s.B, ", ", s.G, "] (batch, groups), got ", t->sizes());
  }
  return s;
}

// Sizes of label_conv3d: labels [B, X, Y, Z], table [27, K, C].
struct LabelConvShape {
  int64_t B, X, Y, Z, K, C;
};

// label_conv3d's labels: [B, X, Y, Z] class ids of an integer dtype: uint8, int32 or int64.
inline void check_class_ids(const at::Tensor& labels, const char* op) {
  check_dim(labels, op, "labels", 4, "[B, X, Y, Z]");
  const auto st = labels.scalar_type();
  T3FAST_CHECK(st == at::kByte || st == at::kInt || st == at::kLong, op,
               "labels must be uint8, int32 or int64 class ids, got ", st);
}

// label_conv3d: class ids [B, X, Y, Z] and a float table [27, K, C] on the same device.
inline LabelConvShape check_label_conv3d(const at::Tensor& labels, const at::Tensor& table,
                                         const char* op) {
  check_class_ids(labels, op);
  check_dim(table, op, "table", 3, "[27, K, C]");
  check_float_dtype(table, op, "table");
  check_same_device(table, labels, op, "table", "labels");
  check_size(table, op, "table", 0, 27, "the 3 x 3 x 3 taps");
  T3FAST_CHECK(table.size(1) > 0, op, "table must hold at least one class, got ", table.sizes());
  return {labels.size(0), labels.size(1), labels.size(2), labels.size(3), table.size(1),
          table.size(2)};
}

// label_conv3d_backward: grad [B, C, X, Y, Z] of a float dtype and labels [B, X, Y, Z] as for
// label_conv3d, on one device, classes >= 1 (the rows of the table gradient).
inline LabelConvShape check_label_conv3d_backward(const at::Tensor& grad, const at::Tensor& labels,
                                                  int64_t classes, const char* op) {
  check_dim(grad, op, "grad", 5, "[B, C, X, Y, Z]");
  check_class_ids(labels, op);
  check_float_dtype(grad, op, "grad");
  check_same_device(labels, grad, op, "labels", "grad");
  check_size(grad, op, "grad", 0, labels.size(0), "batch, as labels");
  check_size(grad, op, "grad", 2, labels.size(1), "X, as labels");
  check_size(grad, op, "grad", 3, labels.size(2), "Y, as labels");
  check_size(grad, op, "grad", 4, labels.size(3), "Z, as labels");
  T3FAST_CHECK(classes > 0, op, "classes must be at least 1, got ", classes);
  return {labels.size(0), labels.size(1), labels.size(2), labels.size(3), classes, grad.size(1)};
}

// bev_components: a bool mask [B, X, Y] (the BEV cells of a class), any device.
inline void check_bev_mask(const at::Tensor& mask, const char* op) {
  check_dim(mask, op, "mask", 3, "[B, X, Y]");
  T3FAST_CHECK(mask.scalar_type() == at::kBool, op, "mask must be bool, got ", mask.scalar_type());
}

// draw_boxes: volume uint8 [B, X, Y, Z], boxes float64 [B, M, 6], levels int64 [M, 2] and labels
// uint8 [M] (every volume's) or [B, M, 2] and [B, M] (each volume's), all on one device; reach
// >= 0 columns.
// The columns of a label grid in metres: lower x, y of the grid and metres per column.
inline void check_grid_frame(c10::ArrayRef<double> lower, double voxel_size, const char* op) {
  T3FAST_CHECK(lower.size() == 2, op, "lower must hold the grid's lower x and y, got ",
               lower.size(), " values");
  T3FAST_CHECK(voxel_size > 0, op, "voxel_size must be positive, got ", voxel_size);
}

inline void check_draw_boxes(const at::Tensor& volume, const at::Tensor& boxes,
                             const at::Tensor& levels, const at::Tensor& labels,
                             c10::ArrayRef<double> lower, double voxel_size, int64_t reach,
                             const char* op) {
  check_dim(volume, op, "volume", 4, "[B, X, Y, Z]");
  T3FAST_CHECK(volume.scalar_type() == at::kByte, op, "volume must be uint8 labels, got ",
               volume.scalar_type());
  check_dim(boxes, op, "boxes", 3, "[B, M, 6]");
  T3FAST_CHECK(boxes.scalar_type() == at::kDouble, op, "boxes must be float64, got ",
               boxes.scalar_type());
  check_size(boxes, op, "boxes", 0, volume.size(0), "batch, as volume");
  check_size(boxes, op, "boxes", 2, 6, "x, y, cos, sin, half length, half width");
  T3FAST_CHECK(levels.dim() == 2 || levels.dim() == 3, op,
               "levels must have 2 dims [M, 2] (every volume's) or 3 dims [B, M, 2] (each "
               "volume's), got ", levels.dim(), " dims ", levels.sizes());
  T3FAST_CHECK(levels.scalar_type() == at::kLong, op, "levels must be int64, got ",
               levels.scalar_type());
  const bool per_volume = levels.dim() == 3;
  const int64_t d = per_volume ? 1 : 0;
  if (per_volume) check_size(levels, op, "levels", 0, volume.size(0), "batch, as volume");
  check_size(levels, op, "levels", d, boxes.size(1), "boxes, as boxes.shape[1]");
  check_size(levels, op, "levels", d + 1, 2, "bottom, top");
  T3FAST_CHECK(labels.dim() == levels.dim() - 1, op, "labels must have ", levels.dim() - 1,
               per_volume ? " dims [B, M], as levels is each volume's"
                          : " dim [M], as levels is every volume's",
               ", got ", labels.dim(), " dims ", labels.sizes());
  T3FAST_CHECK(labels.scalar_type() == at::kByte, op, "labels must be uint8, got ",
               labels.scalar_type());
  if (per_volume) check_size(labels, op, "labels", 0, volume.size(0), "batch, as volume");
  check_size(labels, op, "labels", d, boxes.size(1), "boxes, as boxes.shape[1]");
  check_same_device(boxes, volume, op, "boxes", "volume");
  check_same_device(levels, volume, op, "levels", "volume");
  check_same_device(labels, volume, op, "labels", "volume");
  check_grid_frame(lower, voxel_size, op);
  T3FAST_CHECK(reach >= 0, op, "reach must be at least 0, got ", reach);
}

// box_fit's arguments: ids [B, T, X, Y] int64, track [B, n, T] int64, centroid [B, n, T, 2],
// poses [B, T, 3], start [B, n, 7], reach [B, n] (float64), all on one device.
inline void check_box_fit(const at::Tensor& ids, const at::Tensor& track, const at::Tensor& centroid,
                          const at::Tensor& poses, const at::Tensor& start, const at::Tensor& reach,
                          c10::ArrayRef<double> lower, double voxel_size, int64_t window,
                          int64_t near, int64_t iters, double lr, c10::ArrayRef<double> softness,
                          const char* op) {
  check_dim(ids, op, "ids", 4, "[B, T, X, Y]");
  T3FAST_CHECK(ids.scalar_type() == at::kLong, op, "ids must be int64, got ", ids.scalar_type());
  check_dim(track, op, "track", 3, "[B, n, T]");
  T3FAST_CHECK(track.scalar_type() == at::kLong, op, "track must be int64, got ",
               track.scalar_type());
  check_size(track, op, "track", 0, ids.size(0), "batch, as ids");
  check_size(track, op, "track", 2, ids.size(1), "frames, as ids.shape[1]");
  const int64_t B = ids.size(0), n = track.size(1), T = ids.size(1);
  const struct {
    const at::Tensor& t;
    const char* name;
    const char* layout;
    std::vector<int64_t> shape;
  } floats[] = {{centroid, "centroid", "[B, n, T, 2]", {B, n, T, 2}},
                {poses, "poses", "[B, T, 3]", {B, T, 3}},
                {start, "start", "[B, n, 7]", {B, n, 7}},
                {reach, "reach", "[B, n]", {B, n}}};
  for (const auto& f : floats) {
    check_dim(f.t, op, f.name, static_cast<int64_t>(f.shape.size()), f.layout);
    T3FAST_CHECK(f.t.scalar_type() == at::kDouble, op, f.name, " must be float64, got ",
                 f.t.scalar_type());
    for (size_t d = 0; d < f.shape.size(); ++d) {
      T3FAST_CHECK(f.t.size(static_cast<int64_t>(d)) == f.shape[d], op, f.name, " must be ",
                   f.layout, " = ", c10::IntArrayRef(f.shape), " (ids ", ids.sizes(), ", track ",
                   track.sizes(), "), got ", f.t.sizes());
    }
    check_same_device(f.t, ids, op, f.name, "ids");
  }
  check_same_device(track, ids, op, "track", "ids");
  check_grid_frame(lower, voxel_size, op);
  T3FAST_CHECK(window >= 0 && window <= 1024, op, "window must be in [0, 1024] cells, got ",
               window);
  T3FAST_CHECK(near >= 0 && near <= 16, op, "near must be in [0, 16] cells, got ", near);
  T3FAST_CHECK(iters >= 0, op, "iters must be at least 0, got ", iters);
  T3FAST_CHECK(lr > 0, op, "lr must be positive, got ", lr);
  T3FAST_CHECK(softness.size() == 2 && softness[0] > 0 && softness[1] > 0, op,
               "softness must hold two positive widths (first and last iteration), got ",
               softness);
}

}  // namespace t3fast
