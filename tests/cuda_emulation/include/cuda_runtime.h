// The CUDA runtime API as far as t3fast's kernel files use it, on the emulator (t3emu.h).
#pragma once

#include "t3emu.h"

struct alignas(16) float4 {
  float x, y, z, w;
};
struct alignas(16) uint4 {
  unsigned x, y, z, w;
};

typedef int cudaError_t;
constexpr cudaError_t cudaSuccess = ::t3emu::kSuccess;
constexpr cudaError_t cudaErrorInvalidValue = ::t3emu::kInvalidValue;
constexpr cudaError_t cudaErrorInvalidConfiguration = ::t3emu::kInvalidConfiguration;
constexpr cudaError_t cudaErrorLaunchFailure = ::t3emu::kLaunchFailure;

typedef struct CUstream_st* cudaStream_t;

enum cudaDeviceAttr {
  cudaDevAttrMaxSharedMemoryPerBlockOptin,
  cudaDevAttrMultiProcessorCount,
  cudaDevAttrComputeCapabilityMajor,
};
enum cudaFuncAttribute { cudaFuncAttributeMaxDynamicSharedMemorySize };

inline cudaError_t cudaGetDevice(int* device) {
  *device = 0;
  return cudaSuccess;
}

// The device the emulator stands for: an H100 (132 SMs, 227 KB of shared memory per block
// when opted in), of compute capability 9.0 unless set otherwise.
inline cudaError_t cudaDeviceGetAttribute(int* value, cudaDeviceAttr attr, int device) {
  (void)device;
  switch (attr) {
    case cudaDevAttrMaxSharedMemoryPerBlockOptin:
      *value = ::t3emu::kOptinSmem;
      return cudaSuccess;
    case cudaDevAttrMultiProcessorCount:
      *value = ::t3emu::kSms;
      return cudaSuccess;
    case cudaDevAttrComputeCapabilityMajor:
      *value = ::t3emu::compute_capability_major();
      return cudaSuccess;
  }
  return cudaErrorInvalidValue;
}

template <typename Kernel>
cudaError_t cudaFuncSetAttribute(Kernel* kernel, cudaFuncAttribute attr, int value) {
  if (attr != cudaFuncAttributeMaxDynamicSharedMemorySize || value < 0 ||
      value > ::t3emu::kOptinSmem) {
    return cudaErrorInvalidValue;
  }
  ::t3emu::smem_limits()[reinterpret_cast<const void*>(kernel)] = value;
  return cudaSuccess;
}

inline cudaError_t cudaGetLastError() {
  const cudaError_t err = ::t3emu::last_error();
  ::t3emu::last_error() = cudaSuccess;
  return err;
}

// The message of the last failed launch (the emulator's reason), else the code's name.
inline const char* cudaGetErrorString(cudaError_t err) {
  if (err == cudaSuccess) return "no error";
  if (!::t3emu::launch_error().empty()) return ::t3emu::launch_error().c_str();
  return err == cudaErrorInvalidValue ? "invalid argument" : "unspecified launch failure";
}
