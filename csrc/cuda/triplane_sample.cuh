// Device helpers shared by the triplane_decode kernels: the query points (given or the voxel
// centres of a grid), the bilinear lookups of the three planes and the positional encoding,
// with the reference's rounding (t3fast/ops/reference.py). Arithmetic in A (float or double).
#pragma once

#include "cuda/kernels.h"

namespace t3fast {
namespace cuda {

// Clamp to [0, hi]; fmax returns 0 for a NaN coordinate, which keeps the indices in range.
__device__ __forceinline__ float clamp_border(float v, float hi) {
  return fminf(fmaxf(v, 0.f), hi);
}
__device__ __forceinline__ double clamp_border(double v, double hi) {
  return fmin(fmax(v, 0.0), hi);
}
__device__ __forceinline__ float sin_acc(float v) { return sinf(v); }
__device__ __forceinline__ double sin_acc(double v) { return sin(v); }
__device__ __forceinline__ float cos_acc(float v) { return cosf(v); }
__device__ __forceinline__ double cos_acc(double v) { return cos(v); }

// Voxel-centre coordinate of cell i of n, (2 i + 1) / n - 1, with the reference's rounding.
template <typename A>
__device__ __forceinline__ A voxel_centre(int64_t i, int n) {
  return static_cast<A>(2 * i + 1) / static_cast<A>(n) - A(1);
}

// Coordinates and batch index of point g of the flattened [batch * num_points] query range.
template <typename T, typename A>
__device__ __forceinline__ int64_t query_point(const Query<T>& q, int64_t g, A& x, A& y, A& z) {
  const int64_t b = g / q.num_points;
  if (q.points != nullptr) {
    const T* p = q.points + 3 * g;
    x = to_acc(p[0]);
    y = to_acc(p[1]);
    z = to_acc(p[2]);
  } else {
    const int64_t n = g - b * q.num_points;
    const int64_t plane = static_cast<int64_t>(q.gy) * q.gz;
    const int64_t i = n / plane;
    const int64_t r = n - i * plane;
    const int64_t j = r / q.gz;
    x = voxel_centre<A>(i, q.gx);
    y = voxel_centre<A>(j, q.gy);
    z = voxel_centre<A>(r - j * q.gz, q.gz);
  }
  return b;
}

// Linear interpolation along one plane axis of `size` cells: grid_sample's unnormalisation
// with align_corners=False, clamped to the border (a NaN coordinate clamps to 0).
template <typename A>
struct Lerp {
  int i0, i1;
  A w;  // weight of i1
};

template <typename A>
__device__ __forceinline__ Lerp<A> axis_lerp(A q, int size) {
  const A u = clamp_border(((q + A(1)) * static_cast<A>(size) - A(1)) / A(2),
                           static_cast<A>(size - 1));
  Lerp<A> l;
  l.i0 = static_cast<int>(u);  // u >= 0: truncation is floor
  l.i1 = min(l.i0 + 1, size - 1);
  l.w = u - static_cast<A>(l.i0);
  return l;
}

// Bilinear sample of one channel `plane` [rows, cols] (rows along r, cols along c).
template <typename T, typename A>
__device__ __forceinline__ A bilinear(const T* __restrict__ plane, int cols, const Lerp<A>& r,
                                      const Lerp<A>& c) {
  const T* row0 = plane + static_cast<int64_t>(r.i0) * cols;
  const T* row1 = plane + static_cast<int64_t>(r.i1) * cols;
  const A top = (A(1) - c.w) * to_acc(row0[c.i0]) + c.w * to_acc(row0[c.i1]);
  const A bottom = (A(1) - c.w) * to_acc(row1[c.i0]) + c.w * to_acc(row1[c.i1]);
  return (A(1) - r.w) * top + r.w * bottom;
}

// Channel c of xy(x, y) + xz(x, z) + yz(y, z) for a point of batch b.
template <typename T, typename A>
__device__ __forceinline__ A plane_feature(const Triplane<T>& t, int64_t b, int c, A x, A y,
                                           A z) {
  const Lerp<A> lx = axis_lerp(x, t.sx);
  const Lerp<A> ly = axis_lerp(y, t.sy);
  const Lerp<A> lz = axis_lerp(z, t.sz);
  const int64_t bc = b * t.channels + c;
  const A sxy = bilinear(t.xy + bc * t.sx * t.sy, t.sy, lx, ly);
  const A sxz = bilinear(t.xz + bc * t.sx * t.sz, t.sz, lx, lz);
  const A syz = bilinear(t.yz + bc * t.sy * t.sz, t.sz, ly, lz);
  return sxy + sxz + syz;
}

// Entry j of the positional encoding: for k = j / 6, [sin x, sin y, sin z, cos x, cos y,
// cos z][j % 6] of the coordinates scaled by 2^k (exact in floating point).
template <typename A>
__device__ __forceinline__ A pe_value(int j, A x, A y, A z) {
  const int k = j / 6;
  const int r = j - 6 * k;
  const int axis = r % 3;
  const A q = (axis == 0 ? x : axis == 1 ? y : z) * static_cast<A>(int64_t{1} << k);
  return r < 3 ? sin_acc(q) : cos_acc(q);
}

// A tile's points ``first .. first + P`` (padding repeats the last of ``total``; its results
// are not written) into shared memory: their batch and their coordinates ``[P][3]``, the
// block's threads striding by ``threads``.
template <typename T, typename A>
__device__ __forceinline__ void stage_points(const Query<T>& q, int64_t first, int64_t total, int P,
                                             int threads, int64_t* batch_of, A* coord) {
  for (int p = threadIdx.x; p < P; p += threads) {
    A x, y, z;
    batch_of[p] = query_point(q, min(first + p, total - 1), x, y, z);
    coord[3 * p] = x;
    coord[3 * p + 1] = y;
    coord[3 * p + 2] = z;
  }
}

// Whether point g of the flattened query range is decoded (see Query::live).
template <typename T>
__device__ __forceinline__ bool query_live(const Query<T>& q, int64_t g) {
  if (q.live == nullptr) return true;
  const int64_t b = g / q.num_points;
  return g - b * q.num_points < q.live[b];
}

// The labels of a block's points [first, first + P) when none of them is decoded: 0, and true
// (the block is done); false when some are. Block-uniform, so the block returns as a whole;
// every thread of the block must call it.
template <typename T>
__device__ __forceinline__ bool skip_dead_block(const Query<T>& q, int64_t first, int64_t total, int P,
                                                uint8_t* labels) {
  if (q.live == nullptr) return false;
  int any = 0;
  for (int p = threadIdx.x; p < P; p += blockDim.x) any |= first + p < total && query_live(q, first + p);
  if (__syncthreads_or(any)) return false;
  for (int p = threadIdx.x; p < P; p += blockDim.x) {
    if (first + p < total && labels != nullptr) labels[first + p] = 0;
  }
  return true;
}

// Feature ``j`` of the MLP's input at a point: a plane channel, then the positional encoding,
// then zero up to the padded width ``in0`` onwards.
template <typename T, typename A>
__device__ __forceinline__ A mlp_input(const Triplane<T>& t, int64_t b, int j, int in0, A x, A y, A z) {
  if (j < t.channels) return plane_feature(t, b, j, x, y, z);
  if (j < in0) return pe_value(j - t.channels, x, y, z);
  return A(0);
}

}  // namespace cuda
}  // namespace t3fast
