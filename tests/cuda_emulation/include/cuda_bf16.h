// CUDA's __nv_bfloat16 on the emulator: the upper half of a binary32, rounded to nearest even.
#pragma once

#include <cmath>
#include <cstdint>

#include "float_bits.h"

struct __nv_bfloat16 {
  uint16_t bits;
};

inline unsigned short __bfloat16_as_ushort(__nv_bfloat16 h) { return h.bits; }

inline float __bfloat162float(__nv_bfloat16 h) {
  return t3emu::bits_float(static_cast<uint32_t>(h.bits) << 16);
}

inline __nv_bfloat16 __float2bfloat16_rn(float f) {
  uint32_t u = t3emu::float_bits(f);
  __nv_bfloat16 h;
  if (std::isnan(f)) {
    h.bits = static_cast<uint16_t>((u >> 16) | 0x40u);
  } else {
    u += 0x7FFFu + ((u >> 16) & 1u);
    h.bits = static_cast<uint16_t>(u >> 16);
  }
  return h;
}
