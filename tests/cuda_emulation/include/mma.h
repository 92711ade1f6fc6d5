// WMMA (nvcuda::wmma) on the emulator. A fragment holds its whole tile in every thread (the
// hardware spreads it over the warp in an unspecified layout, so code may only apply
// elementwise operations to x[], which this keeps valid). The products accumulate in float32
// in k order; TF32 operands lose their low 13 mantissa bits in the product, as the tensor
// cores ignore them. Loads and stores check the alignment rules the hardware depends on:
// a 256-bit aligned pointer and a leading dimension that is a multiple of 16 bytes.
#pragma once

#include <cstdint>
#include <string>
#include <type_traits>

#include "cuda_bf16.h"
#include "cuda_fp16.h"
#include "float_bits.h"
#include "t3emu.h"

namespace nvcuda {
namespace wmma {

struct matrix_a {};
struct matrix_b {};
struct accumulator {};
struct row_major {};
struct col_major {};
namespace precision {
struct tf32 {};
}  // namespace precision
enum layout_t { mem_row_major, mem_col_major };

template <typename T>
struct storage {
  using type = T;
};
template <>
struct storage<precision::tf32> {
  using type = float;
};

template <typename Use, int M, int N, int K, typename T, typename Layout = void>
struct fragment {
  static constexpr int rows = std::is_same_v<Use, matrix_b> ? K : M;
  static constexpr int cols = std::is_same_v<Use, matrix_a> ? K : N;
  static constexpr int num_elements = rows * cols;
  using element_type = typename storage<T>::type;
  element_type x[num_elements];
  element_type& at(int r, int c) { return x[r * cols + c]; }
  const element_type& at(int r, int c) const { return x[r * cols + c]; }
};

inline float to_float(float v) { return v; }
inline float to_float(__half v) { return __half2float(v); }
inline float to_float(__nv_bfloat16 v) { return __bfloat162float(v); }

inline float __float_to_tf32(float v) {
  // cvt.rna.tf32.f32: round to 10 mantissa bits, ties away from zero
  if (!std::isfinite(v)) return v;
  return ::t3emu::bits_float((::t3emu::float_bits(v) + 0x1000u) & ~0x1FFFu);
}

inline float tf32_operand(float v) { return ::t3emu::bits_float(::t3emu::float_bits(v) & ~0x1FFFu); }

template <typename S>
inline void check_access(const S* p, unsigned ldm, const char* what) {
  if (reinterpret_cast<uintptr_t>(p) % 32 != 0) {
    ::t3emu::emu_fail(std::string(what) + ": pointer not 256-bit aligned");
  }
  if ((ldm * sizeof(S)) % 16 != 0) {
    ::t3emu::emu_fail(std::string(what) + ": leading dimension not a multiple of 16 bytes");
  }
}

template <typename Use, int M, int N, int K, typename T, typename Layout, typename S>
inline void load_matrix_sync(fragment<Use, M, N, K, T, Layout>& f, const S* p, unsigned ldm) {
  static_assert(std::is_same_v<S, typename fragment<Use, M, N, K, T, Layout>::element_type>,
                "operand storage type");
  check_access(p, ldm, "load_matrix_sync");
  using F = fragment<Use, M, N, K, T, Layout>;
  for (int r = 0; r < F::rows; ++r) {
    for (int c = 0; c < F::cols; ++c) {
      f.at(r, c) = std::is_same_v<Layout, col_major> ? p[c * ldm + r] : p[r * ldm + c];
    }
  }
}

template <int M, int N, int K>
inline void store_matrix_sync(float* p, const fragment<accumulator, M, N, K, float>& f,
                              unsigned ldm, layout_t layout) {
  check_access(p, ldm, "store_matrix_sync");
  for (int r = 0; r < M; ++r) {
    for (int c = 0; c < N; ++c) {
      (layout == mem_row_major ? p[r * ldm + c] : p[c * ldm + r]) = f.at(r, c);
    }
  }
}

template <typename Use, int M, int N, int K, typename T, typename Layout, typename V>
inline void fill_fragment(fragment<Use, M, N, K, T, Layout>& f, V v) {
  for (int i = 0; i < f.num_elements; ++i) f.x[i] = v;
}

template <typename T>
inline float operand(const typename storage<T>::type& v) {
  if constexpr (std::is_same_v<T, precision::tf32>) {
    return tf32_operand(v);
  } else {
    return to_float(v);
  }
}

template <int M, int N, int K, typename T, typename LA, typename LB>
inline void mma_sync(fragment<accumulator, M, N, K, float>& d,
                     const fragment<matrix_a, M, N, K, T, LA>& a,
                     const fragment<matrix_b, M, N, K, T, LB>& b,
                     const fragment<accumulator, M, N, K, float>& c) {
  float fa[M][K], fb[K][N];
  for (int r = 0; r < M; ++r) {
    for (int k = 0; k < K; ++k) fa[r][k] = operand<T>(a.at(r, k));
  }
  for (int k = 0; k < K; ++k) {
    for (int n = 0; n < N; ++n) fb[k][n] = operand<T>(b.at(k, n));
  }
  fragment<accumulator, M, N, K, float> out;
  for (int r = 0; r < M; ++r) {
    for (int n = 0; n < N; ++n) {
      float s = c.at(r, n);
      for (int k = 0; k < K; ++k) s += fa[r][k] * fb[k][n];
      out.at(r, n) = s;
    }
  }
  d = out;
}

}  // namespace wmma
}  // namespace nvcuda
