// The current CUDA stream, for the CUDA glue files (csrc/cuda/<op>.cpp).
//
// It comes from stream.cpp, the only file that includes c10/cuda headers, so that the other
// glue files compile against any torch build (the CPU wheels ship c10/cuda headers that do
// not compile) and can be syntax-checked on machines without a CUDA torch.
#pragma once

#include <cuda_runtime.h>

namespace t3fast {

// The current CUDA stream of a device (torch's, so kernels order with torch's own work).
cudaStream_t current_stream(int device_index);

}  // namespace t3fast
