// The integer label dtypes label_conv3d takes, as C++ types, for the CPU and CUDA glue.
#pragma once

#include <c10/core/ScalarType.h>

#include <cstdint>

namespace t3fast {

// Calls f(L{}) with L the C++ type of a label dtype: uint8_t, int32_t or int64_t (the dtype
// checked before by check_class_ids).
template <typename F>
decltype(auto) dispatch_label_type(c10::ScalarType st, F&& f) {
  switch (st) {
    case c10::ScalarType::Byte:
      return f(uint8_t{});
    case c10::ScalarType::Int:
      return f(int32_t{});
    default:
      return f(int64_t{});
  }
}

}  // namespace t3fast
