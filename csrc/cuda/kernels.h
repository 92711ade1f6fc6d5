// Launchers of the pure-CUDA kernels of t3fast (csrc/cuda/*_kernel.cu).
//
// No torch header on purpose: the kernels take raw pointers to contiguous tensors, sizes and
// a stream, and return the CUDA error of the launch (cudaSuccess on empty input, where
// nothing is launched). The torch glue (csrc/cuda/<op>.cpp) validates, allocates and turns
// errors into exceptions. Each launcher is explicitly instantiated for float, double, __half
// and __nv_bfloat16; arithmetic runs in acc_t<T> (double for double, float otherwise).
#pragma once

#include <cuda_bf16.h>
#include <cuda_fp16.h>
#include <cuda_runtime.h>

#include <cstdint>

namespace t3fast {
namespace cuda {

template <typename T>
struct AccType {
  using type = float;
};
template <>
struct AccType<double> {
  using type = double;
};
template <typename T>
using acc_t = typename AccType<T>::type;

#ifdef __CUDACC__
// Storage <-> accumulation conversions for the kernel files. Explicit intrinsics because torch
// compiles CUDA extensions with __CUDA_NO_HALF_CONVERSIONS__ and
// __CUDA_NO_BFLOAT16_CONVERSIONS__.
__device__ __forceinline__ float to_acc(float v) { return v; }
__device__ __forceinline__ double to_acc(double v) { return v; }
__device__ __forceinline__ float to_acc(__half v) { return __half2float(v); }
__device__ __forceinline__ float to_acc(__nv_bfloat16 v) { return __bfloat162float(v); }

template <typename T>
__device__ __forceinline__ T from_acc(acc_t<T> v) {
  return v;
}
template <>
__device__ __forceinline__ __half from_acc<__half>(float v) {
  return __float2half_rn(v);
}
template <>
__device__ __forceinline__ __nv_bfloat16 from_acc<__nv_bfloat16>(float v) {
  return __float2bfloat16_rn(v);
}
#endif  // __CUDACC__

// ------------------------------------------------------------------ triplane_decode

// Limits of the fused forward kernel: layers of the MLP and any layer width (including the
// input width C + 6 * pe_freqs and the number of classes).
constexpr int kTriplaneMaxLayers = 32;
constexpr int kTriplaneMaxWidth = 512;

// The three planes (contiguous): xy [batch, channels, sx, sy], xz [batch, channels, sx, sz],
// yz [batch, channels, sy, sz].
template <typename T>
struct Triplane {
  const T* xy;
  const T* xz;
  const T* yz;
  int64_t batch;
  int channels;
  int sx, sy, sz;
};

// The query points: points [batch, num_points, 3] (contiguous) or, when points is null, the
// voxel centres of a gx x gy x gz grid (num_points = gx * gy * gz, z fastest). Point g of the
// flattened [batch * num_points] range belongs to batch g / num_points. With live [batch]
// (points and labels only), point n of batch b is decoded when n < live[b]; the others get
// label 0.
template <typename T>
struct Query {
  const T* points;
  int64_t num_points;
  int gx, gy, gz;
  const int64_t* live;  // null: every point
};

// The MLP: weight[i] [width[i + 1], width[i]] and bias[i] [width[i + 1]], contiguous.
template <typename T>
struct Mlp {
  const T* weight[kTriplaneMaxLayers];
  const T* bias[kTriplaneMaxLayers];
  int width[kTriplaneMaxLayers + 1];
  int num_layers;
};

// Shared memory per block that the fused forward needs for these layer widths with its
// smallest point tile (0 if a width exceeds kTriplaneMaxWidth). The launcher picks the
// largest point tile that fits the device, so this is what a device must at least offer.
size_t triplane_decode_min_shared_bytes(const int* widths, int num_layers, bool double_precision);

// Fused forward over batch * num_points points. Writes logits [batch * num_points, K]
// (when logits is not null) or the first-maximum class labels [batch * num_points] (when
// labels is not null; K <= 256).
template <typename T>
cudaError_t triplane_decode_forward(const Triplane<T>& planes, const Query<T>& query,
                                    int pe_freqs, const Mlp<T>& mlp, T* logits, uint8_t* labels,
                                    cudaStream_t stream);

// ---- the fused forward on tensor cores (sm_80 and newer; triplane_decode_mma_kernel.cu)
//
// The MLP runs as warp-level matrix products with fp32 accumulation in the precision Mma:
// __half, __nv_bfloat16 or Tf32 (float32 inputs rounded to TF32). The plane lookups and the
// encoding are computed in fp32 from the planes and points (type T) and rounded to Mma once;
// every hidden layer's output (bias added and ReLU applied in fp32) is rounded to Mma, as
// torch.nn.functional.linear in that dtype rounds its result; the logits stay fp32 until
// they are written as T.

struct Tf32 {};  // marks the TF32 precision: operands stored as float, rounded to TF32

template <typename Mma>
struct MmaStorage {
  using type = Mma;
};
template <>
struct MmaStorage<Tf32> {
  using type = float;
};
// How the operands of precision Mma are stored: float for Tf32, Mma itself otherwise.
template <typename Mma>
using mma_storage_t = typename MmaStorage<Mma>::type;

// Rows and columns of the padded weights (multiples of kMmaPad): the MMA tiles read whole
// 16 x 16 blocks, and the padding (zeros) leaves the products unchanged.
constexpr int kMmaPad = 16;

// The MLP with padded parameters: weight[i] [pad(width[i + 1]), pad(width[i])] in storage
// type S, zero outside the real [width[i + 1], width[i]] block; bias[i] [pad(width[i + 1])]
// float32, zero-padded. width holds the real (unpadded) widths.
template <typename S>
struct MmaMlp {
  const S* weight[kTriplaneMaxLayers];
  const float* bias[kTriplaneMaxLayers];
  int width[kTriplaneMaxLayers + 1];
  int num_layers;
};

// Shared memory per block of the tensor-core forward for these widths and operand size
// (sizeof(mma_storage_t<Mma>): 2 or 4 bytes).
size_t triplane_decode_mma_shared_bytes(const int* widths, int num_layers, int operand_bytes);

// The fused forward of triplane_decode_forward with the MLP on tensor cores in precision
// Mma (see above). Needs a device of compute capability 8.0 or newer.
template <typename T, typename Mma>
cudaError_t triplane_decode_forward_mma(const Triplane<T>& planes, const Query<T>& query,
                                        int pe_freqs, const MmaMlp<mma_storage_t<Mma>>& mlp,
                                        T* logits, uint8_t* labels, cudaStream_t stream);

// Decoder input features [count, channels + 6 * pe_freqs] of the points start ..
// start + count - 1 of the flattened query range.
template <typename T>
cudaError_t triplane_features(const Triplane<T>& planes, const Query<T>& query, int pe_freqs,
                              int64_t start, int64_t count, acc_t<T>* features,
                              cudaStream_t stream);

// Adds the bilinear transpose of the feature gradient (row r of grad_features holds the
// gradient of the summed plane sample of point start + r in its first `channels` entries;
// rows are ld apart) into the zero-initialised plane gradients (shapes of the planes).
// Uses atomics: the summation order, hence the last bits, may vary between runs.
template <typename T>
cudaError_t triplane_scatter_grad(const Triplane<T>& planes, const Query<T>& query,
                                  int64_t start, int64_t count, const acc_t<T>* grad_features,
                                  int64_t ld, acc_t<T>* grad_xy, acc_t<T>* grad_xz,
                                  acc_t<T>* grad_yz, cudaStream_t stream);

// ------------------------------------------------------------------ axis_pool

// How axis_pool_forward splits the work: a block reduces x_chunk consecutive x-slabs of one
// (b, c) pair, in tiles of y_tile rows; with num_chunks > 1 the partial yz sums of the chunks
// go to a workspace of workspace_elems acc_t<T> values and a second pass adds them in a
// fixed order (deterministic, no atomics).
struct AxisPoolPlan {
  int64_t x_chunk;
  int64_t num_chunks;
  int64_t y_tile;
  int64_t workspace_elems;
  size_t shared_bytes;
};

// The plan for this shape on a device with num_sms multiprocessors.
AxisPoolPlan axis_pool_plan(int64_t batch, int64_t channels, int64_t x, int64_t y, int64_t z,
                            int num_sms, bool double_precision);

// volume [batch, channels, x, y, z] -> xy [.., x, y] (mean over z), xz [.., x, z] (over y),
// yz [.., y, z] (over x), reading the volume once. workspace: plan.workspace_elems values
// (may be null when that is 0).
template <typename T>
cudaError_t axis_pool_forward(const T* volume, int64_t batch, int64_t channels, int64_t x,
                              int64_t y, int64_t z, const AxisPoolPlan& plan, T* xy, T* xz,
                              T* yz, acc_t<T>* workspace, cudaStream_t stream);

// grad_volume[b, c, i, j, k] = grad_xy[b, c, i, j] / z + grad_xz[b, c, i, k] / y
//                              + grad_yz[b, c, j, k] / x.
template <typename T>
cudaError_t axis_pool_backward(const T* grad_xy, const T* grad_xz, const T* grad_yz,
                               int64_t batch, int64_t channels, int64_t x, int64_t y, int64_t z,
                               T* grad_volume, cudaStream_t stream);

// ------------------------------------------------------------------ delta_fuse

// out [batch, c_out, pixels] = delta + weight [c_out, c_in] @ prev [batch, c_in, pixels]
// (+ bias [c_out] when not null).
template <typename T>
cudaError_t delta_fuse_forward(const T* delta, const T* prev, const T* weight, const T* bias,
                               int64_t batch, int c_out, int c_in, int64_t pixels, T* out,
                               cudaStream_t stream);

// Shared memory per block of delta_fuse_backward with its smallest pixel tile.
size_t delta_fuse_backward_min_shared_bytes(int c_out, int c_in, bool double_precision);

// grad_prev [batch, c_in, pixels] = weight^T @ grad_out, and adds into the zero-initialised
// accumulators grad_weight [c_out, c_in] += sum over batch and pixels of grad_out prev^T,
// grad_bias [c_out] += sum of grad_out. Reads grad_out and prev once. The weight and bias
// gradients use atomics: their last bits may vary between runs.
template <typename T>
cudaError_t delta_fuse_backward(const T* grad_out, const T* prev, const T* weight,
                                int64_t batch, int c_out, int c_in, int64_t pixels, T* grad_prev,
                                acc_t<T>* grad_weight, acc_t<T>* grad_bias, cudaStream_t stream);

// ------------------------------------------------------------------ matching_costs

// out [batch, (2 radius + 1)^2, h, w]: minus the channel mean of |present - previous shifted|
// for each shift (replicate padding), present and previous [batch, channels, h, w].
template <typename T>
cudaError_t matching_costs_forward(const T* present, const T* previous, int64_t batch,
                                   int channels, int h, int w, int radius, T* out,
                                   cudaStream_t stream);

// grad_present and grad_previous [batch, channels, h, w] from grad [batch, shifts, h, w]; each
// value written by one thread (no atomics: deterministic).
template <typename T>
cudaError_t matching_costs_backward(const T* grad, const T* present, const T* previous,
                                    int64_t batch, int channels, int h, int w, int radius,
                                    T* grad_present, T* grad_previous, cudaStream_t stream);

// ------------------------------------------------------------------ group_norm_silu

// Chunks of kChunk values per (batch, channel) row of spatial values: the workspaces below
// hold 2 sums per chunk, batch * channels * chunks * 2 values.
int64_t group_norm_silu_chunks(int64_t spatial);

// y = silu((x - mean) * rstd * weight + bias [+ residual]) for x [batch, channels, spatial] in
// groups of channels / groups consecutive channels; mean and rstd [batch, groups] receive the
// groups' statistics. residual may be null.
template <typename T>
cudaError_t group_norm_silu_forward(const T* x, const T* weight, const T* bias, const T* residual,
                                    int64_t batch, int64_t channels, int64_t spatial,
                                    int64_t groups, double eps, T* y, acc_t<T>* mean,
                                    acc_t<T>* rstd, acc_t<T>* workspace, cudaStream_t stream);

// grad_input from grad (shaped as x), and the residual's gradient (silu's gradient, into
// grad_residual unless it is null); row_sums [batch * channels, 2] receives each row's sums of
// that gradient and of it times the normalised input (the bias' and weight's gradients summed
// over the batch).
template <typename T>
cudaError_t group_norm_silu_backward(const T* grad, const T* x, const T* weight, const T* bias,
                                     const T* residual, const acc_t<T>* mean,
                                     const acc_t<T>* rstd, int64_t batch, int64_t channels,
                                     int64_t spatial, int64_t groups, T* grad_input,
                                     T* grad_residual, acc_t<T>* row_sums, acc_t<T>* workspace,
                                     cudaStream_t stream);

// ------------------------------------------------------------------ label_conv3d

// out [batch, channels, x, y, z] = sum over the 27 taps t (dx, dy, dz each -1..1, dx slowest)
// of table [27, classes, channels] at (t, labels[b, i + dx, j + dy, k + dz]), taps outside the
// volume skipped; labels (contiguous, L = uint8_t, int32_t or int64_t) outside [0, classes)
// contribute nothing (they are not checked on the device: that would need a host sync).
template <typename T, typename L>
cudaError_t label_conv3d_forward(const L* labels, const T* table, int64_t batch, int x, int y,
                                 int z, int classes, int channels, T* out, cudaStream_t stream);

// ------------------------------------------------------------------ bev_components

// The 8-connected components of the masks [batch, x, y] (contiguous bool): parent [batch * x * y]
// receives, per cell on a mask, its component's root (the flat index, counted over the whole
// batch, of the component's last cell in row-major order), and -1 off the masks.
cudaError_t bev_component_roots(const bool* mask, int64_t batch, int x, int y, int* parent,
                                cudaStream_t stream);

// ------------------------------------------------------------------ draw_boxes

// Boxes painted into out [batch, x, y, z] (uint8, holding the volumes to draw into): box m of
// batch element n (boxes [batch, count, 6]: x, y, cos, sin, half length, half width) covers the
// columns within reach of its centre column that lie inside its footprint (and its centre
// column) over levels [levels[m, 0], levels[m, 1]) with labels[m] (per_volume: levels
// [batch, count, 2] and labels [batch, count], those of (n, m)); winner [batch * x * y * z]
// (int32, zeroed) keeps the last box of each voxel, whose label is then written.
cudaError_t draw_boxes(const double* boxes, const int64_t* levels, const uint8_t* labels,
                       bool per_volume, int64_t batch, int count, int x, int y, int z,
                       double lower_x, double lower_y, double voxel, int reach, int* winner,
                       uint8_t* out, cudaStream_t stream);

// ------------------------------------------------------------------ box_fit

// Boxes of agents fitted to their columns (see csrc/cpu/box_fit.cpp and box_fit_math.h), for
// batch windows of count agents and frames frames of x * y columns: ids [batch, frames, x, y],
// track [batch, count, frames], centroid [batch, count, frames, 2], poses [batch, frames, 3],
// start [batch, count, 7], reach [batch, count]; params [batch, count, 7] and iou
// [batch, count] receive the result. samples (4 floats per record) and sampled (int32) are
// scratch of box_fit_scratch(...) records and batch * count * frames counts.
struct BoxFitArgs {
  const int64_t* ids;
  const int64_t* track;
  const double* centroid;
  const double* poses;
  const double* start;
  const double* reach;
  int batch, count, frames, x, y;
  double lower_x, lower_y, voxel;
  int window, near, iters;
  double lr, softness_first, softness_last, accel_prior;
};
int64_t box_fit_scratch(int64_t batch, int64_t count, int64_t frames, int64_t window);
cudaError_t box_fit(const BoxFitArgs& args, float* samples, int* sampled, double* params,
                    double* iou, cudaStream_t stream);

}  // namespace cuda
}  // namespace t3fast
