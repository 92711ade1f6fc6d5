// CPU kernel of label_conv3d: a 3 x 3 x 3 convolution (zero padding 1) of a class-embedded
// label volume, computed as 27 table lookups per voxel instead of 27 * E * C multiply-adds.
// Work is split over the B * X slabs; each (x, y) row of Z voxels accumulates its C-vectors in
// a small [Z, C] buffer, then writes them channel by channel into [B, C, X, Y, Z].
#include <ATen/ATen.h>
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <atomic>
#include <utility>
#include <vector>

#include "checks.h"
#include "cpu/simd.h"
#include "label_types.h"

namespace t3fast {
namespace {

constexpr const char* kOp = "label_conv3d";
constexpr const char* kOpBwd = "label_conv3d_backward";

// Whether a label lies outside [0, K), and one such label.
template <typename L>
std::pair<bool, int64_t> find_bad_label(const L* labels, int64_t n, int64_t K) {
  std::atomic<bool> found{false};
  std::atomic<int64_t> value{0};
  at::parallel_for(0, n, 1 << 16, [&](int64_t i0, int64_t i1) {
    for (int64_t i = i0; i < i1; ++i) {
      const int64_t k = static_cast<int64_t>(labels[i]);
      if (k < 0 || k >= K) {
        if (!found.exchange(true)) value.store(k);
        return;
      }
    }
  });
  return {found.load(), value.load()};
}

// Output rows (b, x) in [r0, r1). Tap by tap, each table row is added to the accumulators of a
// whole (x, y) row of Z voxels: Z independent additions, where one voxel's 27 taps in turn would
// wait on each other's latency. kZ, kC > 0 fix the row length and the channels at compile time
// (Occ3D's 16 cells, the stem widths), so that the [Z, C] accumulators stay in registers.
template <typename T, typename A, typename L, int64_t kZ, int64_t kC>
T3FAST_SIMD_CLONES void conv_rows(const L* labels, const T* table, T* out, int64_t r0,
                                  int64_t r1, int64_t X, int64_t Y, int64_t runtime_z, int64_t K,
                                  int64_t runtime_c) {
  constexpr bool kFixed = kZ > 0 && kC > 0;
  const int64_t Z = kZ > 0 ? kZ : runtime_z, C = kC > 0 ? kC : runtime_c;
  const int64_t XYZ = X * Y * Z;
  A fixed[kFixed ? kZ * kC : 1];
  std::vector<A> heap(kFixed ? 0 : Z * C);
  A* acc = kFixed ? fixed : heap.data();  // [Z, C]: one row's outputs
  for (int64_t r = r0; r < r1; ++r) {
    const int64_t b = r / X, x = r - b * X;
    const L* slab = labels + b * XYZ;
    T* dst = out + b * C * XYZ + x * Y * Z;
    for (int64_t y = 0; y < Y; ++y) {
      for (int64_t i = 0; i < Z * C; ++i) acc[i] = A(0);
      for (int64_t d = 0; d < 9; ++d) {
        const int64_t nx = x + d / 3 - 1, ny = y + d % 3 - 1;
        if (nx < 0 || nx >= X || ny < 0 || ny >= Y) continue;
        const L* row = slab + (nx * Y + ny) * Z;
        for (int64_t dz = -1; dz <= 1; ++dz) {
          const T* tap = table + (d * 3 + dz + 1) * K * C;
          const int64_t z0 = dz < 0 ? 1 : 0, z1 = dz > 0 ? Z - 1 : Z;
#pragma GCC unroll 16
          for (int64_t z = z0; z < z1; ++z) {
            const T* entry = tap + static_cast<int64_t>(row[z + dz]) * C;
            A* a = acc + z * C;
#pragma omp simd
            for (int64_t c = 0; c < C; ++c) a[c] += static_cast<A>(entry[c]);
          }
        }
      }
      for (int64_t c = 0; c < C; ++c) {
        T* o = dst + c * XYZ + y * Z;
        for (int64_t z = 0; z < Z; ++z) o[z] = static_cast<T>(acc[z * C + c]);
      }
    }
  }
}

// The table gradient of rows (b, x) in [r0, r1) added into `grad_table` [27, K, C]: each voxel's
// output gradient goes, tap by tap, to the row of the label it read through that tap.
template <typename T, typename A, typename L, int64_t kZ, int64_t kC>
T3FAST_SIMD_CLONES void grad_rows(const T* grad, const L* labels, A* grad_table, int64_t r0,
                                  int64_t r1, int64_t X, int64_t Y, int64_t runtime_z, int64_t K,
                                  int64_t runtime_c) {
  constexpr bool kFixed = kZ > 0 && kC > 0;
  const int64_t Z = kZ > 0 ? kZ : runtime_z, C = kC > 0 ? kC : runtime_c;
  const int64_t XYZ = X * Y * Z;
  A fixed[kFixed ? kZ * kC : 1];
  std::vector<A> heap(kFixed ? 0 : Z * C);
  A* g = kFixed ? fixed : heap.data();  // [Z, C]: one row's output gradients
  for (int64_t r = r0; r < r1; ++r) {
    const int64_t b = r / X, x = r - b * X;
    const L* slab = labels + b * XYZ;
    const T* src = grad + b * C * XYZ + x * Y * Z;
    for (int64_t y = 0; y < Y; ++y) {
      for (int64_t c = 0; c < C; ++c) {
        const T* row = src + c * XYZ + y * Z;
        for (int64_t z = 0; z < Z; ++z) g[z * C + c] = static_cast<A>(row[z]);
      }
      for (int64_t d = 0; d < 9; ++d) {
        const int64_t nx = x + d / 3 - 1, ny = y + d % 3 - 1;
        if (nx < 0 || nx >= X || ny < 0 || ny >= Y) continue;
        const L* row = slab + (nx * Y + ny) * Z;
        for (int64_t dz = -1; dz <= 1; ++dz) {
          A* tap = grad_table + (d * 3 + dz + 1) * K * C;
          const int64_t z0 = dz < 0 ? 1 : 0, z1 = dz > 0 ? Z - 1 : Z;
          for (int64_t z = z0; z < z1; ++z) {
            A* entry = tap + static_cast<int64_t>(row[z + dz]) * C;
            const A* gz = g + z * C;
#pragma omp simd
            for (int64_t c = 0; c < C; ++c) entry[c] += gz[c];
          }
        }
      }
    }
  }
}

template <typename T, typename L>
void label_conv3d_backward_typed(const at::Tensor& grad, const at::Tensor& labels,
                                 at::Tensor& grad_table, const LabelConvShape& s) {
  using A = std::conditional_t<std::is_same_v<T, double>, double, float>;
  const L* pl = labels.data_ptr<L>();
  const auto [bad, value] = find_bad_label(pl, labels.numel(), s.K);
  T3FAST_CHECK(!bad, kOpBwd, "labels must be class ids in [0, ", s.K, "), got ", value);
  const int64_t entries = 27 * s.K * s.C;
  // one private table per thread, added in thread order: deterministic for a thread count
  const int64_t threads = at::get_num_threads();
  std::vector<A> partial(threads * entries, A(0));
  const T* pg = grad.data_ptr<T>();
  auto* rows = s.Z == 16 && s.C == 8    ? &grad_rows<T, A, L, 16, 8>
               : s.Z == 16 && s.C == 16 ? &grad_rows<T, A, L, 16, 16>
               : s.Z == 16 && s.C == 32 ? &grad_rows<T, A, L, 16, 32>
                                        : &grad_rows<T, A, L, 0, 0>;
  at::parallel_for(0, s.B * s.X, 1, [&](int64_t r0, int64_t r1) {
    A* mine = partial.data() + at::get_thread_num() * entries;
    rows(pg, pl, mine, r0, r1, s.X, s.Y, s.Z, s.K, s.C);
  });
  T* out = grad_table.data_ptr<T>();
  for (int64_t i = 0; i < entries; ++i) {
    A sum = A(0);
    for (int64_t t = 0; t < threads; ++t) sum += partial[t * entries + i];
    out[i] = static_cast<T>(sum);
  }
}

template <typename T, typename L>
void label_conv3d_typed(const at::Tensor& labels, const at::Tensor& table, at::Tensor& out,
                        const LabelConvShape& s) {
  const L* pl = labels.data_ptr<L>();
  const auto [bad, value] = find_bad_label(pl, labels.numel(), s.K);
  T3FAST_CHECK(!bad, kOp, "labels must be class ids in [0, ", s.K, ") (the rows of table), got ",
               value);
  using A = std::conditional_t<std::is_same_v<T, double>, double, float>;
  const T* pt = table.data_ptr<T>();
  T* po = out.data_ptr<T>();
  auto* rows = s.Z == 16 && s.C == 8    ? &conv_rows<T, A, L, 16, 8>
               : s.Z == 16 && s.C == 16 ? &conv_rows<T, A, L, 16, 16>
               : s.Z == 16 && s.C == 32 ? &conv_rows<T, A, L, 16, 32>
                                        : &conv_rows<T, A, L, 0, 0>;
  at::parallel_for(0, s.B * s.X, 1, [&](int64_t r0, int64_t r1) {
    rows(pl, pt, po, r0, r1, s.X, s.Y, s.Z, s.K, s.C);
  });
}

at::Tensor label_conv3d_cpu(const at::Tensor& labels, const at::Tensor& table) {
  const LabelConvShape s = check_label_conv3d(labels, table, kOp);
  const at::Tensor l = labels.contiguous(), t = table.contiguous();
  at::Tensor out = at::empty({s.B, s.C, s.X, s.Y, s.Z}, t.options());
  if (out.numel() == 0) return out;
  AT_DISPATCH_FLOATING_TYPES(t.scalar_type(), "label_conv3d_cpu", [&] {
    dispatch_label_type(l.scalar_type(), [&](auto label) {
      label_conv3d_typed<scalar_t, decltype(label)>(l, t, out, s);
    });
  });
  return out;
}

at::Tensor label_conv3d_backward_cpu(const at::Tensor& grad, const at::Tensor& labels,
                                     int64_t classes) {
  const LabelConvShape s = check_label_conv3d_backward(grad, labels, classes, kOpBwd);
  const at::Tensor g = grad.contiguous(), l = labels.contiguous();
  at::Tensor grad_table = at::zeros({27, s.K, s.C}, g.options());
  if (g.numel() == 0 || grad_table.numel() == 0) return grad_table;
  AT_DISPATCH_FLOATING_TYPES(g.scalar_type(), "label_conv3d_backward_cpu", [&] {
    dispatch_label_type(l.scalar_type(), [&](auto label) {
      label_conv3d_backward_typed<scalar_t, decltype(label)>(g, l, grad_table, s);
    });
  });
  return grad_table;
}

}  // namespace

TORCH_LIBRARY_IMPL(t3fast, CPU, m) {
  m.impl("label_conv3d", &label_conv3d_cpu);
  m.impl("label_conv3d_backward", &label_conv3d_backward_cpu);
}

}  // namespace t3fast
