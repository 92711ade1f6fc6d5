// Arguments of triplane_decode and its backward, checked once for both backends: the sizes
// of the planes, of the MLP and of the query, and the shape of the result.
#pragma once

#include <ATen/ATen.h>

#include <algorithm>
#include <cstdint>
#include <vector>

namespace t3fast {

struct TriplaneProblem {
  int64_t B = 0, C = 0;            // batch, plane channels
  int64_t PX = 0, PY = 0, PZ = 0;  // plane sizes X', Y', Z'
  bool grid_mode = false;          // query the grid (else the points)
  int64_t GX = 0, GY = 0, GZ = 0;  // grid sizes (grid mode)
  int64_t per_batch = 0;           // queries per batch element: N points or X * Y * Z voxels
  int64_t pe_freqs = 0;
  std::vector<int64_t> widths;  // [in_0 = C + 6 * pe_freqs, out_0, ..., out_{L-1} = K]

  int64_t layers() const { return static_cast<int64_t>(widths.size()) - 1; }
  int64_t classes() const { return widths.back(); }
  int64_t max_width() const { return *std::max_element(widths.begin(), widths.end()); }
  // [B, N] or [B, X, Y, Z]: the labels of argmax mode; the logits add a last dim K.
  std::vector<int64_t> query_shape() const;
  std::vector<int64_t> logits_shape() const;
  // The uninitialised result: uint8 labels (argmax) or logits of xy's dtype, on xy's device.
  at::Tensor empty_output(const at::Tensor& xy, bool argmax) const;
};

// Checks triplane_decode's arguments; `argmax` adds the uint8 labels' limit on the classes.
// `op` names the op in the messages.
TriplaneProblem parse_triplane_args(const at::Tensor& xy, const at::Tensor& xz,
                                    const at::Tensor& yz, at::TensorList weights,
                                    at::TensorList biases,
                                    const c10::optional<at::Tensor>& points,
                                    c10::OptionalIntArrayRef grid, int64_t pe_freqs, bool argmax,
                                    const char* op);

// Checks triplane_decode's `live` against the parsed problem: int64 [B] on xy's device, points
// and argmax mode only (its values are not read: the kernels clamp them to [0, N]).
void check_live(const c10::optional<at::Tensor>& live, const TriplaneProblem& p, bool argmax,
                const at::Tensor& xy, const char* op);

// The same for triplane_decode_backward, whose grad_out must look like the forward's logits.
TriplaneProblem parse_triplane_backward_args(const at::Tensor& grad_out, const at::Tensor& xy,
                                             const at::Tensor& xz, const at::Tensor& yz,
                                             at::TensorList weights, at::TensorList biases,
                                             const c10::optional<at::Tensor>& points,
                                             c10::OptionalIntArrayRef grid, int64_t pe_freqs,
                                             const char* op);

}  // namespace t3fast
