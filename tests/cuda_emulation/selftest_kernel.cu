// Kernels that check the emulator itself: each is correct only if the emulator keeps CUDA's
// rules (barriers, shared memory, asynchronous copies, WMMA alignment), or breaks one of them
// on purpose.
#include <cuda_pipeline.h>
#include <cuda_runtime.h>
#include <mma.h>

#include <string>

namespace {

constexpr int kThreads = 128;

// Which slot of shared memory a thread of exchange_kernel reads.
enum class Read { kReversed, kPrevious };

// Through shared memory: out = in reversed (kReversed), or out[t] = in[t - 1] and in[0] for
// thread 0 (kPrevious); right only if __syncthreads really waits. Without the barrier
// (`barrier` false) a race. Reversed, the emulator shows it every time: a thread runs until it
// returns, so thread 0 reads slots nobody has written yet. Previous, running the threads in
// order hides it (thread t - 1 has written its slot when thread t reads it), and running them
// last to first shows it.
__global__ void exchange_kernel(const float* in, float* out, bool barrier, Read read) {
  extern __shared__ __align__(16) unsigned char smem[];
  float* buf = reinterpret_cast<float*>(smem);
  const int t = threadIdx.x;
  buf[t] = in[blockIdx.x * kThreads + t];
  if (barrier) __syncthreads();
  const int slot = read == Read::kReversed ? kThreads - 1 - t : (t > 0 ? t - 1 : 0);
  out[blockIdx.x * kThreads + t] = buf[slot];
}

// out = in reversed, staged in shared memory by asynchronous copies: right only if a copy
// lands when its thread waits for it and the barrier orders every thread's copy before the
// reads. Without the wait (`wait` false) nothing has landed when the threads read.
__global__ void staged_reverse_kernel(const float* in, float* out, bool wait) {
  extern __shared__ __align__(16) unsigned char smem[];
  float* buf = reinterpret_cast<float*>(smem);
  const int t = threadIdx.x;
  __pipeline_memcpy_async(buf + t, in + blockIdx.x * kThreads + t, sizeof(float));
  __pipeline_commit();
  if (wait) __pipeline_wait_prior(0);
  __syncthreads();
  out[blockIdx.x * kThreads + t] = buf[kThreads - 1 - t];
}

// A 16-byte asynchronous copy from an address 4 bytes past an aligned one.
__global__ void misaligned_async_copy_kernel(const float* in) {
  extern __shared__ __align__(16) unsigned char smem[];
  if (threadIdx.x == 0) __pipeline_memcpy_async(smem, in + 1, 16);
  __pipeline_commit();
}

// out[block] = 1 when any input of the block is positive (__syncthreads_or), written by
// thread 0; every thread also counts how many of its warp's lanes passed __syncwarp.
__global__ void vote_kernel(const float* in, float* out) {
  __shared__ int lanes[kThreads / 32];
  const int t = threadIdx.x;
  if (t % 32 == 0) lanes[t / 32] = 0;
  __syncwarp();
  atomicAdd(&lanes[t / 32], 1);
  __syncwarp();
  const int any = __syncthreads_or(in[blockIdx.x * kThreads + t] > 0.f);
  if (t == 0) out[blockIdx.x] = static_cast<float>(any) + 10.f * lanes[0];
}

// Thread 0 waits at __syncthreads, the rest of its warp at __syncwarp: neither opens.
__global__ void divergent_kernel(float* out) {
  if (threadIdx.x == 0) {
    __syncthreads();
  } else {
    __syncwarp();
  }
  out[threadIdx.x] = 1.f;
}

// Writes one float past the end of the dynamic shared memory.
__global__ void overrun_kernel(int n) {
  extern __shared__ __align__(16) unsigned char smem[];
  float* buf = reinterpret_cast<float*>(smem);
  if (threadIdx.x == 0) buf[n] = 1.f;
}

// Loads a WMMA fragment from a pointer 2 bytes past an aligned one.
__global__ void misaligned_kernel() {
  extern __shared__ __align__(128) unsigned char smem[];
  nvcuda::wmma::fragment<nvcuda::wmma::matrix_a, 16, 16, 16, __half, nvcuda::wmma::row_major> a;
  nvcuda::wmma::load_matrix_sync(a, reinterpret_cast<const __half*>(smem + 2), 16);
}

}  // namespace

// Runs the self-test `name` (see above) on n = blocks * 128 floats of in, out.
cudaError_t emulator_selftest(const std::string& name, const float* in, float* out, int blocks) {
  if (name == "reverse" || name == "racy_reverse") {
    exchange_kernel<<<blocks, kThreads, kThreads * sizeof(float), nullptr>>>(in, out, name == "reverse",
                                                                              Read::kReversed);
  } else if (name == "shift" || name == "racy_shift") {
    exchange_kernel<<<blocks, kThreads, kThreads * sizeof(float), nullptr>>>(in, out, name == "shift",
                                                                              Read::kPrevious);
  } else if (name == "staged_reverse" || name == "unwaited_reverse") {
    staged_reverse_kernel<<<blocks, kThreads, kThreads * sizeof(float), nullptr>>>(in, out,
                                                                                    name == "staged_reverse");
  } else if (name == "misaligned_async_copy") {
    misaligned_async_copy_kernel<<<1, kThreads, 64>>>(in);
  } else if (name == "vote") {
    vote_kernel<<<blocks, kThreads>>>(in, out);
  } else if (name == "divergent") {
    divergent_kernel<<<1, kThreads>>>(out);
  } else if (name == "overrun") {
    overrun_kernel<<<1, kThreads, 64 * sizeof(float)>>>(64);
  } else if (name == "misaligned") {
    misaligned_kernel<<<1, 32, 1024>>>();
  } else if (name == "unopted_shared_memory") {
    // 64 KB without cudaFuncSetAttribute: over the default 48 KB limit
    exchange_kernel<<<1, kThreads, 64 * 1024>>>(in, out, true, Read::kReversed);
  } else {
    return cudaErrorInvalidValue;
  }
  return cudaGetLastError();
}
