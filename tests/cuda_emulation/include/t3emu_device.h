// What device code sees on the emulator (t3emu.h): CUDA's keywords, built-in variables,
// barriers, warp intrinsics and atomics. Included before every kernel file (never by the glue,
// which sees only the runtime API of cuda_runtime.h).
#pragma once

#include <cstdint>
#include <cstring>

#include "t3emu.h"

#define threadIdx (::t3emu::thread_idx())
#define blockIdx (::t3emu::block_idx())
#define blockDim (::t3emu::block_dim())
#define gridDim (::t3emu::grid_dim())

#define __global__
#define __device__
#define __host__
#define __forceinline__ inline
#define __launch_bounds__(...)
#define __grid_constant__
#define __align__(n) alignas(n)
#define __shared__ static

inline void __syncthreads() { ::t3emu::wait_at(::t3emu::Wait::kBlock, 0); }
inline int __syncthreads_or(int v) {
  ::t3emu::wait_at(::t3emu::Wait::kBlock, v != 0);
  return ::t3emu::block_state()->current->result;
}
inline void __syncwarp(unsigned mask = 0xffffffffu) {
  ::t3emu::require_full_warp(mask, "__syncwarp");
  ::t3emu::wait_at(::t3emu::Wait::kWarp, 0);
}
[[noreturn]] inline void __trap() { ::t3emu::emu_fail("__trap() reached"); }

namespace t3emu {

// The warp's lanes exchange values: each posts its own, and after a warp barrier reads any
// lane's (lanes that exited leave theirs stale, as reading them is undefined in CUDA); a
// second barrier keeps a lane from posting again before every lane has read.
template <typename T, typename Read>
inline auto warp_exchange(unsigned mask, T v, Read read) {
  static_assert(sizeof(T) <= sizeof(uint64_t), "exchanged values are at most 8 bytes");
  require_full_warp(mask, "a warp shuffle or ballot");
  BlockState* b = block_state();
  Fiber* self = b->current;
  std::memcpy(&self->posted, &v, sizeof(T));
  wait_at(Wait::kWarp, 0);
  const unsigned lane = self->linear % 32;
  const unsigned base = self->linear - lane;
  const unsigned lanes = b->fibers.size() - base < 32 ? b->fibers.size() - base : 32;
  const auto lane_value = [&](unsigned l) {
    T out;
    std::memcpy(&out, &b->fibers[base + l].posted, sizeof(T));
    return out;
  };
  const auto result = read(lane, lanes, lane_value);
  wait_at(Wait::kWarp, 0);
  return result;
}

}  // namespace t3emu

template <typename T>
inline T __shfl_down_sync(unsigned mask, T v, unsigned delta, int width = 32) {
  return ::t3emu::warp_exchange(mask, v, [&](unsigned lane, unsigned lanes, auto value) {
    const unsigned src = lane + delta;
    return (lane % width) + delta < static_cast<unsigned>(width) && src < lanes ? value(src) : v;
  });
}

inline unsigned __ballot_sync(unsigned mask, int predicate) {
  return ::t3emu::warp_exchange(mask, predicate != 0 ? 1 : 0, [](unsigned, unsigned lanes, auto value) {
    unsigned bits = 0;
    for (unsigned l = 0; l < lanes; ++l) bits |= static_cast<unsigned>(value(l)) << l;
    return bits;
  });
}

inline int __popc(unsigned v) { return __builtin_popcount(v); }

// Blocks run one at a time on one host thread: an atomic is a plain read-modify-write.
template <typename T>
inline T atomicAdd(T* address, T v) {
  const T old = *address;
  *address = old + v;
  return old;
}
template <typename T>
inline T atomicMax(T* address, T v) {
  const T old = *address;
  if (v > old) *address = v;
  return old;
}
template <typename T>
inline T atomicCAS(T* address, T compare, T v) {
  const T old = *address;
  if (old == compare) *address = v;
  return old;
}

// IEEE double operations, rounded to nearest (the emulator is built without contraction).
inline double __dadd_rn(double a, double b) { return a + b; }
inline double __dsub_rn(double a, double b) { return a - b; }
inline double __dmul_rn(double a, double b) { return a * b; }
inline double __ddiv_rn(double a, double b) { return a / b; }

inline int min(int a, int b) { return a < b ? a : b; }
inline int max(int a, int b) { return a > b ? a : b; }
inline int64_t min(int64_t a, int64_t b) { return a < b ? a : b; }
inline int64_t max(int64_t a, int64_t b) { return a > b ? a : b; }
