// CUDA's __half on the emulator: IEEE binary16 storage, converted with round-to-nearest-even.
#pragma once

#include <cmath>
#include <cstdint>

#include "float_bits.h"

struct __half {
  uint16_t bits;
};

inline unsigned short __half_as_ushort(__half h) { return h.bits; }

inline float __half2float(__half h) {
  const uint32_t sign = static_cast<uint32_t>(h.bits & 0x8000u) << 16;
  const uint32_t exp = (h.bits >> 10) & 0x1Fu;
  const uint32_t man = h.bits & 0x3FFu;
  uint32_t u;
  if (exp == 0 && man == 0) {
    u = 0;
  } else if (exp == 0) {  // subnormal: man 2^-24
    u = t3emu::float_bits(static_cast<float>(man) * 5.9604644775390625e-08f);
  } else if (exp == 31) {
    u = 0x7F800000u | (man << 13);
  } else {
    u = ((exp + 112u) << 23) | (man << 13);
  }
  return t3emu::bits_float(u | sign);
}

inline __half __float2half_rn(float f) {
  const uint32_t raw = t3emu::float_bits(f);
  const uint16_t sign = static_cast<uint16_t>((raw >> 16) & 0x8000u);
  const uint32_t u = raw & 0x7FFFFFFFu;
  __half h;
  if (u > 0x7F800000u) {
    h.bits = sign | 0x7E00u;  // NaN
  } else if (u >= 0x477FF000u) {  // 65520 and above round to infinity
    h.bits = sign | 0x7C00u;
  } else if (u < 0x38800000u) {  // below 2^-14: multiples of 2^-24, ties to even
    h.bits = sign | static_cast<uint16_t>(std::nearbyint(t3emu::bits_float(u) * 16777216.f));
  } else {
    uint32_t bits = (((u >> 23) - 112u) << 10) | ((u & 0x7FFFFFu) >> 13);
    const uint32_t rest = u & 0x1FFFu;
    if (rest > 0x1000u || (rest == 0x1000u && (bits & 1u))) ++bits;  // carries into the exponent
    h.bits = sign | static_cast<uint16_t>(bits);
  }
  return h;
}
