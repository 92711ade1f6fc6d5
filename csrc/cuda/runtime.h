// Calls of the CUDA glue into the CUDA runtime, with errors that name the op.
#pragma once

#include <cuda_runtime.h>

#include "checks.h"

namespace t3fast {

// Turns a CUDA error (of a launch or a runtime call) into an error naming the op.
inline void check_launch(cudaError_t err, const char* op) {
  T3FAST_CHECK(err == cudaSuccess, op, "CUDA kernel launch failed: ", cudaGetErrorString(err));
}

// An attribute of a device, e.g. its multiprocessor count or shared memory per block.
inline int device_attribute(cudaDeviceAttr attr, int device, const char* op) {
  int value = 0;
  check_launch(cudaDeviceGetAttribute(&value, attr, device), op);
  return value;
}

}  // namespace t3fast
