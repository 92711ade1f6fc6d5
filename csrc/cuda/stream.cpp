// The one glue file that includes c10/cuda (see stream.h).
#include "cuda/stream.h"

#include <c10/cuda/CUDAStream.h>

namespace t3fast {

cudaStream_t current_stream(int device_index) {
  return c10::cuda::getCurrentCUDAStream(static_cast<c10::DeviceIndex>(device_index)).stream();
}

}  // namespace t3fast
