// CUDA's __half on the emulator: IEEE binary16 storage, converted with round-to-nearest-even.
#pragma once

#include <cmath>
#include <cstdint>
#include <cstring>

struct __half {
  uint16_t bits;
};

inline float __half2float(__half h) {
  const uint32_t sign = static_cast<uint32_t>(h.bits & 0x8000u) << 16;
  const uint32_t exp = (h.bits >> 10) & 0x1Fu;
  const uint32_t man = h.bits & 0x3FFu;
  uint32_t u;
  if (exp == 0 && man == 0) {
    u = 0;
  } else if (exp == 0) {  // subnormal: man 2^-24
    float v = static_cast<float>(man) * 5.9604644775390625e-08f;
    std::memcpy(&u, &v, 4);
  } else if (exp == 31) {
    u = 0x7F800000u | (man << 13);
  } else {
    u = ((exp + 112u) << 23) | (man << 13);
  }
  u |= sign;
  float v;
  std::memcpy(&v, &u, 4);
  return v;
}

inline __half __float2half_rn(float f) {
  uint32_t u;
  std::memcpy(&u, &f, 4);
  const uint16_t sign = static_cast<uint16_t>((u >> 16) & 0x8000u);
  u &= 0x7FFFFFFFu;
  __half h;
  if (u > 0x7F800000u) {
    h.bits = sign | 0x7E00u;  // NaN
  } else if (u >= 0x477FF000u) {  // 65520 and above round to infinity
    h.bits = sign | 0x7C00u;
  } else if (u < 0x38800000u) {  // below 2^-14: multiples of 2^-24, ties to even
    float a;
    std::memcpy(&a, &u, 4);
    h.bits = sign | static_cast<uint16_t>(std::nearbyint(a * 16777216.f));
  } else {
    uint32_t bits = (((u >> 23) - 112u) << 10) | ((u & 0x7FFFFFu) >> 13);
    const uint32_t rest = u & 0x1FFFu;
    if (rest > 0x1000u || (rest == 0x1000u && (bits & 1u))) ++bits;  // carries into the exponent
    h.bits = sign | static_cast<uint16_t>(bits);
  }
  return h;
}
