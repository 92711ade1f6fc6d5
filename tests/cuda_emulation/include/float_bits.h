// A binary32's bits and back, for the emulator's conversions to and from 16-bit and TF32
// operands.
#pragma once

#include <cstdint>
#include <cstring>

namespace t3emu {

inline uint32_t float_bits(float v) {
  uint32_t u;
  std::memcpy(&u, &v, sizeof u);
  return u;
}

inline float bits_float(uint32_t u) {
  float v;
  std::memcpy(&v, &u, sizeof v);
  return v;
}

}  // namespace t3emu
