// CPU kernels of axis_pool: the three axis means of a volume in one read, and the backward
// in one write. Work is split over the B*C slabs [X, Y, Z]; inside a slab the Z rows are
// contiguous, so each row feeds all three means while it is in L1.
#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include "checks.h"
#include "cpu/simd.h"

namespace t3fast {
namespace {

constexpr const char* kOp = "axis_pool";
constexpr const char* kOpBwd = "axis_pool_backward";

// kZ > 0 fixes the row length at compile time (Occ3D's 16 cells is the common case): the
// row then fits whole vector registers and the loops unroll completely.
template <typename T, int64_t kZ>
T3FAST_SIMD_CLONES void pool_slab(const T* v, T* xy, T* xz, T* yz, int64_t X, int64_t Y,
                                  int64_t runtime_z) {
  const int64_t Z = kZ > 0 ? kZ : runtime_z;
  const T inv_x = T(1) / T(X), inv_y = T(1) / T(Y), inv_z = T(1) / T(Z);
  std::fill(xz, xz + X * Z, T(0));
  std::fill(yz, yz + Y * Z, T(0));
  for (int64_t x = 0; x < X; ++x) {
    T* xz_row = xz + x * Z;
    for (int64_t y = 0; y < Y; ++y) {
      const T* row = v + (x * Y + y) * Z;
      T* yz_row = yz + y * Z;
      T sum = T(0);
#pragma omp simd reduction(+ : sum)
      for (int64_t z = 0; z < Z; ++z) {
        sum += row[z];
        xz_row[z] += row[z];
        yz_row[z] += row[z];
      }
      xy[x * Y + y] = sum * inv_z;
    }
    for (int64_t z = 0; z < Z; ++z) xz_row[z] *= inv_y;
  }
  for (int64_t i = 0; i < Y * Z; ++i) yz[i] *= inv_x;
}

// grad[b, c, x, y, z] = gxy[b, c, x, y] / Z + gxz[b, c, x, z] / Y + gyz[b, c, y, z] / X for the
// rows r = (b * C + c) * X + x in [r0, r1).
template <typename T>
T3FAST_SIMD_CLONES void unpool_rows(const T* gxy, const T* gxz, const T* gyz, T* out,
                                    int64_t r0, int64_t r1, int64_t X, int64_t Y, int64_t Z) {
  const T inv_x = T(1) / T(X), inv_y = T(1) / T(Y), inv_z = T(1) / T(Z);
  for (int64_t r = r0; r < r1; ++r) {
    const T* xz_row = gxz + r * Z;
    const T* yz_slab = gyz + (r / X) * Y * Z;
    for (int64_t y = 0; y < Y; ++y) {
      const T from_xy = gxy[r * Y + y] * inv_z;
      T* dst = out + (r * Y + y) * Z;
      const T* yz_row = yz_slab + y * Z;
      for (int64_t z = 0; z < Z; ++z) dst[z] = from_xy + xz_row[z] * inv_y + yz_row[z] * inv_x;
    }
  }
}

std::tuple<at::Tensor, at::Tensor, at::Tensor> axis_pool_cpu(const at::Tensor& volume) {
  const VolumeShape s = check_volume(volume, kOp);
  const int64_t B = s.B, C = s.C, X = s.X, Y = s.Y, Z = s.Z;
  const at::Tensor v = volume.contiguous();
  at::Tensor xy = at::empty({B, C, X, Y}, v.options());
  at::Tensor xz = at::empty({B, C, X, Z}, v.options());
  at::Tensor yz = at::empty({B, C, Y, Z}, v.options());
  AT_DISPATCH_FLOATING_TYPES(v.scalar_type(), "axis_pool_cpu", [&] {
    const scalar_t* pv = v.data_ptr<scalar_t>();
    scalar_t* pxy = xy.data_ptr<scalar_t>();
    scalar_t* pxz = xz.data_ptr<scalar_t>();
    scalar_t* pyz = yz.data_ptr<scalar_t>();
    at::parallel_for(0, B * C, 1, [&](int64_t s0, int64_t s1) {
      for (int64_t s = s0; s < s1; ++s) {
        auto* slab = Z == 16 ? &pool_slab<scalar_t, 16> : &pool_slab<scalar_t, 0>;
        slab(pv + s * X * Y * Z, pxy + s * X * Y, pxz + s * X * Z, pyz + s * Y * Z, X, Y, Z);
      }
    });
  });
  return {xy, xz, yz};
}

at::Tensor axis_pool_backward_cpu(const at::Tensor& grad_xy, const at::Tensor& grad_xz,
                                  const at::Tensor& grad_yz) {
  const VolumeShape s = check_planes(grad_xy, grad_xz, grad_yz, kPlaneGrads, kOpBwd);
  const int64_t B = s.B, C = s.C, X = s.X, Y = s.Y, Z = s.Z;
  const at::Tensor gxy = grad_xy.contiguous(), gxz = grad_xz.contiguous(),
                   gyz = grad_yz.contiguous();
  at::Tensor out = at::empty({B, C, X, Y, Z}, gxy.options());
  if (out.numel() == 0) return out;
  AT_DISPATCH_FLOATING_TYPES(gxy.scalar_type(), "axis_pool_backward_cpu", [&] {
    using T = scalar_t;
    const T* a = gxy.data_ptr<T>();
    const T* b = gxz.data_ptr<T>();
    const T* c = gyz.data_ptr<T>();
    T* o = out.data_ptr<T>();
    at::parallel_for(0, B * C * X, 1, [&](int64_t r0, int64_t r1) {
      unpool_rows(a, b, c, o, r0, r1, X, Y, Z);
    });
  });
  return out;
}

}  // namespace

TORCH_LIBRARY_IMPL(t3fast, CPU, m) {
  m.impl("axis_pool", &axis_pool_cpu);
  m.impl("axis_pool_backward", &axis_pool_backward_cpu);
}

}  // namespace t3fast
