// Operator schemas of the t3fast library and the Python module of the extension.
// Kernels are registered per backend in csrc/cpu/*.cpp (CPU) and csrc/cuda/*.cpp (CUDA);
// a build without CUDA simply has no CUDA registrations. The module is written against
// Python's C API, not pybind11: it has one function, and torch/extension.h would triple the
// file's compile time.
#include <Python.h>
#include <torch/library.h>
#include <torch/version.h>

#include <string>

#ifndef T3FAST_WITH_CUDA
#define T3FAST_WITH_CUDA 0
#endif
#ifndef T3FAST_CUDA_VERSION
#define T3FAST_CUDA_VERSION -1
#endif

TORCH_LIBRARY(t3fast, m) {
  // Fused query-sum-decode of a triplane. Exactly one of points [B, N, 3] / grid (X, Y, Z).
  // Returns logits [B, N, K] / [B, X, Y, Z, K], or uint8 labels [B, N] / [B, X, Y, Z] when
  // argmax is set. live (int64 [B], points and argmax only): decode the first live[b] points
  // of each batch element, label 0 for the rest.
  m.def(
      "triplane_decode(Tensor xy, Tensor xz, Tensor yz, Tensor[] weights, Tensor[] biases, "
      "Tensor? points, int[]? grid, int pe_freqs, bool argmax, Tensor? live=None) -> Tensor");
  // Gradients of the logits with respect to the planes, weights and biases.
  m.def(
      "triplane_decode_backward(Tensor grad_out, Tensor xy, Tensor xz, Tensor yz, "
      "Tensor[] weights, Tensor[] biases, Tensor? points, int[]? grid, int pe_freqs) "
      "-> (Tensor, Tensor, Tensor, Tensor[], Tensor[])");
  // [B, C, X, Y, Z] -> (mean over Z [B, C, X, Y], mean over Y [B, C, X, Z],
  //                     mean over X [B, C, Y, Z]), reading the volume once.
  m.def("axis_pool(Tensor volume) -> (Tensor, Tensor, Tensor)");
  m.def("axis_pool_backward(Tensor grad_xy, Tensor grad_xz, Tensor grad_yz) -> Tensor");
  // delta [B, C, H, W] + conv1x1(prev [B, C_in, H, W]; weight [C, C_in]) + bias [C].
  m.def("delta_fuse(Tensor delta, Tensor prev, Tensor weight, Tensor? bias) -> Tensor");
  // -> (grad_prev, grad_weight, grad_bias); grad_delta is grad_out itself.
  m.def(
      "delta_fuse_backward(Tensor grad_out, Tensor prev, Tensor weight) "
      "-> (Tensor, Tensor, Tensor)");
  // How well each cell of present [B, C, H, W] matches the cells of previous [B, C, H, W] around
  // it: out[b, n, i, j] = -(1/C) sum over c of |present[b, c, i, j] - previous[b, c, i', j']|,
  // i' = clamp(i + n / (2r + 1) - r), j' = clamp(j + n % (2r + 1) - r) (replicate padding), for
  // the (2r + 1)^2 shifts n of radius r. Returns [B, (2r + 1)^2, H, W].
  m.def("matching_costs(Tensor present, Tensor previous, int radius) -> Tensor");
  // -> (grad_present, grad_previous) from grad [B, (2r + 1)^2, H, W].
  m.def(
      "matching_costs_backward(Tensor grad, Tensor present, Tensor previous, int radius) "
      "-> (Tensor, Tensor)");
  // silu(group_norm(input) * weight + bias + residual): input [B, C, *] in groups of C / groups
  // channels, weight and bias [C], residual (optional) shaped as input. Returns (out, mean
  // [B, groups], rstd [B, groups]), the statistics in float32 (float64 for float64 input).
  m.def(
      "group_norm_silu(Tensor input, Tensor weight, Tensor bias, int groups, float eps, "
      "Tensor? residual=None) -> (Tensor, Tensor, Tensor)");
  // -> (grad_input, grad_weight, grad_bias, grad_residual); grad_residual is empty without a
  // residual.
  m.def(
      "group_norm_silu_backward(Tensor grad, Tensor input, Tensor weight, Tensor bias, "
      "Tensor? residual, Tensor mean, Tensor rstd, int groups) -> (Tensor, Tensor, Tensor, Tensor)");
  // out[b, :, v] = sum over the 27 taps t of table[t, labels[b, v + t], :] (zero outside the
  // volume): a 3 x 3 x 3 convolution of the class-embedded labels. labels [B, X, Y, Z] -> out
  // [B, C, X, Y, Z]; table [27, K, C], taps in (dx, dy, dz) order, each from -1 to 1.
  m.def("label_conv3d(Tensor labels, Tensor table) -> Tensor");
  // The gradient of label_conv3d's table [27, classes, C] from grad [B, C, X, Y, Z].
  m.def("label_conv3d_backward(Tensor grad, Tensor labels, int classes) -> Tensor");
  // The 8-connected components of bool masks [B, X, Y]: labels int64 [B, X, Y], 0 off the mask
  // and 1..n on it, numbered in the row-major order of each component's last cell, and n int64
  // [B] (a tensor: no host synchronisation).
  m.def("bev_components(Tensor mask) -> (Tensor, Tensor)");
  // Boxes drawn into label volumes [B, X, Y, Z] (uint8): box m of batch element b (boxes
  // [B, M, 6]: centre x, y, cos and sin of its heading, half length, half width; metres in the
  // volume's frame) fills the levels levels[m, 0] <= z < levels[m, 1] of every column within
  // reach columns of its centre column whose centre lies inside its footprint, and of its centre
  // column, with labels[m]; a later box wins where they overlap. levels [B, M, 2] and labels
  // [B, M]: each volume's boxes' own. Returns the drawn volumes.
  m.def(
      "draw_boxes(Tensor volume, Tensor boxes, Tensor levels, Tensor labels, float[] lower, "
      "float voxel_size, int reach) -> Tensor");
  // Agents' boxes fitted to their columns in every frame of a window (ids [B, T, X, Y] the
  // frames' component maps, track [B, n, T] each agent's component per frame or -1, centroid
  // [B, n, T, 2] its column centroid in cells, poses [B, T, 3], start [B, n, 7] the boxes to
  // start from, reach [B, n] cells sampled around the centroid, <= 0 not fitted): iters Adam
  // steps on the soft footprint loss. Returns (boxes [B, n, 7], footprint IoU [B, n]).
  m.def(
      "box_fit(Tensor ids, Tensor track, Tensor centroid, Tensor poses, Tensor start, "
      "Tensor reach, float[] lower, float voxel_size, int window, int near, int iters, float lr, "
      "float[] softness, float accel_prior) -> (Tensor, Tensor)");
}

namespace {

// {"cpu", "cuda", "cuda_version", "torch_version" (the torch compiled against), "openmp"}
PyObject* build_info(PyObject* /*self*/, PyObject* /*args*/) {
  const std::string torch_version = std::to_string(TORCH_VERSION_MAJOR) + "." +
                                    std::to_string(TORCH_VERSION_MINOR) + "." +
                                    std::to_string(TORCH_VERSION_PATCH);
#ifdef _OPENMP
  PyObject* openmp = Py_True;
#else
  PyObject* openmp = Py_False;
#endif
  // cuda_version: major * 1000 + minor * 10, -1 without CUDA
  return Py_BuildValue("{s:O,s:O,s:i,s:s,s:O}", "cpu", Py_True, "cuda",
                       T3FAST_WITH_CUDA ? Py_True : Py_False, "cuda_version",
                       T3FAST_CUDA_VERSION, "torch_version", torch_version.c_str(), "openmp",
                       openmp);
}

PyMethodDef methods[] = {
    {"build_info", build_info, METH_NOARGS, "How this extension was built"},
    {nullptr, nullptr, 0, nullptr},
};

PyModuleDef module = {
    PyModuleDef_HEAD_INIT,
    "t3fast._C",
    "Compiled operators of t3fast (registered under torch.ops.t3fast)",
    -1,
    methods,
    nullptr,
    nullptr,
    nullptr,
    nullptr,
};

}  // namespace

#define T3FAST_CONCAT_(a, b) a##b
#define T3FAST_CONCAT(a, b) T3FAST_CONCAT_(a, b)

PyMODINIT_FUNC T3FAST_CONCAT(PyInit_, TORCH_EXTENSION_NAME)(void) { return PyModule_Create(&module); }
